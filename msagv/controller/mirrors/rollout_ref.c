/*
 * MIRROR: single-thread C reference of controller/rollout.py's batch rollout, model 0
 * (MODEL_MF: Magic Formula tires, linearly implicit trapezoidal velocity step).
 *
 * Written operation for operation after the numba kernels commands_from_policy,
 * tire_forces (with plant/tire.py's slip_ratio, slip_angle, slip_jacobian,
 * magic_formula_and_slope and wear powers), _solve3, wheel_terms, rigid_body_update and tile
 * (model 0), with the same expression order, so that a build without -ffast-math
 * reproduces the numba result to rounding (the numba kernels multiply by the reciprocals
 * of dt, r_w and the slip denominators where this divides: a few ulp apart, 1e-14 in the
 * benchmark's agreement). Used by benchmarks/rollout_bench.py (the
 * throughput the hardware allows) and pinned by tests/test_rollout_ref.py (equivalence).
 *
 * The indices into P, S, x0, ref and the outputs are plant/layout.py's names, from the
 * header msagv_layout.h that benchmarks/rollout_bench.py generates from it
 * (plant.layout.c_header) next to the build.
 *
 * Layouts (row-major, as in the module docstring of controller/rollout.py):
 *   x0     (6 + nw)       x, y, phi, vx, vy, r (velocities in G), then delta_ij
 *   ref    (Np + 1, 6)    reference x, y, phi, vx, vy, r at t0 + k dt (rows 0..Np-1 used)
 *   Z      (B, D)         D = n_blocks * 2 nw; per block: nw wheel-speed offsets, then nw
 *                         steering-angle offsets
 *   block  (Np)           block index of each prediction step (int64)
 *   P      plant parameter vector (plant.dynamics.pack_params)
 *   S      controller settings vector (controller.models.pack_settings)
 *   wx, wy (nw)           wheel positions in B
 *   poses  (B, Np, 3)     out: x, y, phi at step k + 1
 *   wear   (B, Np, 3)     out: P_s, P_alpha, P_t over step k [W]
 *   cmds   (B, 2, nw)     out: omega_w, omega_s of step 0
 *
 * Plain C99 with <math.h> only; no heap allocation (per-candidate work arrays are
 * variable-length arrays created once per call, outside the loops).
 */
#include <math.h>

#include "msagv_layout.h"

#define RR_PI 3.14159265358979323846
#define RR_THETA 0.5

/* controller.rollout._wrap: angle wrapped to (-pi, pi]. */
static inline double rr_wrap(double a)
{
    return a - 2.0 * RR_PI * ceil((a - RR_PI) / (2.0 * RR_PI));
}

/* controller.rollout.commands_from_policy; x = (x, y, phi). */
static inline void rr_commands_from_policy(const double *x, const double *delta,
                                           const double *refk, const double *z, long base,
                                           int nw, const double *P, const double *S,
                                           const double *wx, const double *wy, double dt,
                                           double *om_w, double *om_s)
{
    const double r_w = P[P_WHEEL_RADIUS];
    const double phi = x[POSE_PHI];
    const double ex = refk[REF_X] - x[POSE_X];
    const double ey = refk[REF_Y] - x[POSE_Y];
    double cx = S[S_K_POS] * ex;
    double cy = S[S_K_POS] * ey;
    const double cn = sqrt(cx * cx + cy * cy);
    if (cn > S[S_V_FB_MAX]) {
        cx *= S[S_V_FB_MAX] / cn;
        cy *= S[S_V_FB_MAX] / cn;
    }
    const double vdx = refk[REF_VX] + cx;
    const double vdy = refk[REF_VY] + cy;
    double cr = S[S_K_PHI] * rr_wrap(refk[REF_PHI] - phi);
    if (cr > S[S_R_FB_MAX])
        cr = S[S_R_FB_MAX];
    else if (cr < -S[S_R_FB_MAX])
        cr = -S[S_R_FB_MAX];
    const double rd = refk[REF_R] + cr;
    const double c = cos(phi);
    const double s = sin(phi);
    const double ub = c * vdx + s * vdy;
    const double vb = -s * vdx + c * vdy;
    const double kservo = (1.0 - exp(-S[S_K_SERVO] * dt)) / dt;
    const double dmin = P[P_DELTA_MIN], dmax = P[P_DELTA_MAX];
    const double acorner = S[S_K_ALPHA] * sqrt(vdx * vdx + vdy * vdy) * rd;
    for (int k = 0; k < nw; ++k) {
        const double wvx = ub - rd * wy[k];
        const double wvy = vb + rd * wx[k];
        double dff = atan2(wvy, wvx) + acorner;
        double wff;
        if (dff > dmax || dff < dmin) {
            dff = dff > dmax ? dmax : dmin;
            wff = (wvx * cos(dff) + wvy * sin(dff)) / r_w;
            if (wff < 0.0)
                wff = 0.0;
        } else {
            wff = sqrt(wvx * wvx + wvy * wvy) / r_w;
        }
        double w = wff + z[base + k];
        if (w < 0.0)
            w = 0.0;
        else if (w > P[P_OMEGA_W_MAX])
            w = P[P_OMEGA_W_MAX];
        double tgt = dff + z[base + nw + k];
        if (tgt > dmax)
            tgt = dmax;
        else if (tgt < dmin)
            tgt = dmin;
        double ws = kservo * (tgt - delta[k]);
        double lo = P[P_OMEGA_S_MIN];
        double hi = P[P_OMEGA_S_MAX];
        const double lo2 = (dmin - delta[k]) / dt;
        const double hi2 = (dmax - delta[k]) / dt;
        if (lo2 > lo)
            lo = lo2;
        if (hi2 < hi)
            hi = hi2;
        if (lo > hi) { /* numerically at a stop: hold */
            lo = 0.0;
            hi = 0.0;
        }
        if (ws < lo)
            ws = lo;
        else if (ws > hi)
            ws = hi;
        om_w[k] = w;
        om_s[k] = ws;
    }
}

/* controller.rollout._solve3: A out = b by Cramer's rule. */
static inline void rr_solve3(const double A[3][3], const double *b, double *out)
{
    const double a = A[0][0], bb = A[0][1], c = A[0][2];
    const double d = A[1][0], e = A[1][1], f = A[1][2];
    const double g = A[2][0], h = A[2][1], i = A[2][2];
    const double det = a * (e * i - f * h) - bb * (d * i - f * g) + c * (d * h - e * g);
    out[0] = (b[0] * (e * i - f * h) - bb * (b[1] * i - f * b[2]) + c * (b[1] * h - e * b[2])) / det;
    out[1] = (a * (b[1] * i - f * b[2]) - b[0] * (d * i - f * g) + c * (d * b[2] - b[1] * g)) / det;
    out[2] = (a * (e * b[2] - b[1] * h) - bb * (d * b[2] - b[1] * g) + b[0] * (d * h - e * g)) / det;
}

/* plant.tire.magic_formula_and_slope: Magic Formula value *f and slope *df. */
static inline void rr_mf_and_slope(double xi, double B, double C, double D, double E,
                                   double *f, double *df)
{
    const double Bx = B * xi;
    const double arg = E != 0.0 ? Bx - E * (Bx - atan(Bx)) : Bx;
    const double ca = C * atan(arg);
    const double darg = B * (1.0 - E) + E * B / (1.0 + Bx * Bx);
    *f = D * sin(ca);
    *df = D * cos(ca) * C * darg / (1.0 + arg * arg);
}

/* controller.rollout.tire_forces, MF (plant.tire's slip_ratio, slip_angle, slip_jacobian).
 * out = (Fx, Fy, dFx/dvwx, dFx/dvwy, dFy/dvwx, dFy/dvwy, slip s, slip angle alpha). */
static inline void rr_tire_wheel_mf(double vwx, double vwy, double omw, double FN,
                                    const double *P, double *out)
{
    const double r_w = P[P_WHEEL_RADIUS], v_eps = P[P_V_EPS];
    const double d2 = vwx * vwx + v_eps * v_eps;
    const double d = sqrt(d2);
    const double sl = (omw * r_w - vwx) / d;
    const double al = -atan(vwy / d);
    const double ds_dx = -1.0 / d - (omw * r_w - vwx) * vwx / (d2 * d);
    const double q = d2 + vwy * vwy;
    const double da_dx = vwy * vwx / (d * q);
    const double da_dy = -d / q;
    double Fx, dFx_ds, Fy, dFy_da;
    rr_mf_and_slope(sl, P[P_LON_B], P[P_LON_C], P[P_LON_MU] * FN, P[P_LON_E], &Fx, &dFx_ds);
    rr_mf_and_slope(al, P[P_LAT_B], P[P_LAT_C], P[P_LAT_MU] * FN, P[P_LAT_E], &Fy, &dFy_da);
    const double dFx_da = 0.0;
    const double dFy_ds = 0.0;
    out[0] = Fx;
    out[1] = Fy;
    out[2] = dFx_ds * ds_dx + dFx_da * da_dx;
    out[3] = dFx_da * da_dy;
    out[4] = dFy_ds * ds_dx + dFy_da * da_dx;
    out[5] = dFy_da * da_dy;
    out[6] = sl;
    out[7] = al;
}

/* controller.rollout's tile with model == 0 (wheel_terms, rigid_body_update), for one candidate z (D,).
 * delta, om_w, om_s: caller-provided work arrays of nw entries. */
static inline void rr_simulate_mf(int nw, int Np, const double *x0, const double *ref,
                                  const double *z, const long *block, const double *P,
                                  const double *S, const double *wx, const double *wy,
                                  double *poses, double *wear, double *cmds,
                                  double *delta, double *om_w, double *om_s)
{
    const double dt = S[S_DT];
    const double m = P[P_MASS], Iz = P[P_YAW_INERTIA], r_w = P[P_WHEEL_RADIUS], g = P[P_G],
                 k_t = P[P_K_T];
    const double FN = m * g / nw; /* Assumption 2 */
    double X[3], V[3], tw[8], A[3][3], F[3], du[3];
    X[POSE_X] = x0[X0_X];
    X[POSE_Y] = x0[X0_Y];
    X[POSE_PHI] = x0[X0_PHI];
    V[0] = x0[X0_VX];
    V[1] = x0[X0_VY];
    V[2] = x0[X0_R];
    for (int j = 0; j < nw; ++j)
        delta[j] = x0[X0_DELTA + j];
    for (int k = 0; k < Np; ++k) {
        const long base = block[k] * 2 * nw;
        rr_commands_from_policy(X, delta, ref + N_REF * k, z, base, nw, P, S, wx, wy, dt,
                                om_w, om_s);
        if (k == 0) {
            for (int j = 0; j < nw; ++j) {
                cmds[CMD_W * nw + j] = om_w[j];
                cmds[CMD_S * nw + j] = om_s[j];
            }
        }
        const double phi = X[POSE_PHI];
        const double c = cos(phi);
        const double s = sin(phi);
        const double ub = c * V[0] + s * V[1];
        const double vb = -s * V[0] + c * V[1];
        const double r = V[2];
        double ps = 0.0;
        double pa = 0.0;
        double pt = 0.0;
        for (int j = 0; j < nw; ++j)
            pt += fabs(k_t * FN * om_s[j]); /* eq. (15) */
        /* rigid body with tire forces (eq. 4, 5, 17), linearly implicit in the velocity */
        for (int i = 0; i < 3; ++i) {
            F[i] = 0.0;
            for (int jj = 0; jj < 3; ++jj)
                A[i][jj] = 0.0;
        }
        for (int j = 0; j < nw; ++j) {
            const double dm = delta[j] + 0.5 * dt * om_s[j]; /* mid steering angle */
            const double cd = cos(dm);
            const double sd = sin(dm);
            const double vbx_w = ub - r * wy[j]; /* eq. (6) */
            const double vby_w = vb + r * wx[j]; /* eq. (7) */
            const double vwx = cd * vbx_w + sd * vby_w; /* eq. (8) */
            const double vwy = -sd * vbx_w + cd * vby_w;
            rr_tire_wheel_mf(vwx, vwy, om_w[j], FN, P, tw);
            const double Fx = tw[0], Fy = tw[1];
            ps += fabs(Fx * (om_w[j] * r_w - vwx)); /* eq. (13) */
            pa += fabs(Fy * vwy); /* eq. (14) */
            /* generalised force (F_Bx, F_By, M_z) = Lw^T R(delta) F_W */
            const double fbx = cd * Fx - sd * Fy;
            const double fby = sd * Fx + cd * Fy;
            F[0] += fbx;
            F[1] += fby;
            F[2] += wx[j] * fby - wy[j] * fbx;
            /* Jacobian: Lw^T R K R^T Lw, K = d(Fx, Fy)/d(vwx, vwy) */
            const double k11 = tw[2], k12 = tw[3], k21 = tw[4], k22 = tw[5];
            const double a11 = cd * k11 - sd * k21;
            const double a12 = cd * k12 - sd * k22;
            const double a21 = sd * k11 + cd * k21;
            const double a22 = sd * k12 + cd * k22;
            const double m11 = a11 * cd - a12 * sd;
            const double m12 = a11 * sd + a12 * cd;
            const double m21 = a21 * cd - a22 * sd;
            const double m22 = a21 * sd + a22 * cd;
            const double yw = wy[j];
            const double xw = wx[j];
            A[0][0] += m11;
            A[0][1] += m12;
            A[0][2] += -m11 * yw + m12 * xw;
            A[1][0] += m21;
            A[1][1] += m22;
            A[1][2] += -m21 * yw + m22 * xw;
            A[2][0] += -yw * m11 + xw * m21;
            A[2][1] += -yw * m12 + xw * m22;
            A[2][2] += (-yw * (-m11 * yw + m12 * xw) + xw * (-m21 * yw + m22 * xw));
        }
        for (int i = 0; i < 3; ++i) {
            const double inv = i == 2 ? 1.0 / Iz : 1.0 / m;
            for (int jj = 0; jj < 3; ++jj)
                A[i][jj] = -RR_THETA * dt * inv * A[i][jj];
            A[i][i] += 1.0;
            F[i] = dt * inv * F[i];
        }
        /* body-frame form of eq. (17) with the transport terms (also in the Jacobian) */
        F[0] += dt * r * vb;
        F[1] -= dt * r * ub;
        A[0][1] -= RR_THETA * dt * r;
        A[0][2] -= RR_THETA * dt * vb;
        A[1][0] += RR_THETA * dt * r;
        A[1][2] += RR_THETA * dt * ub;
        rr_solve3((const double (*)[3])A, F, du);
        const double v0x = V[0], v0y = V[1];
        const double r1 = r + du[2];
        /* trapezoidal heading and position updates (DEVIATION eq. 21) */
        X[POSE_PHI] += 0.5 * dt * (r + r1);
        const double c1 = cos(X[POSE_PHI]);
        const double s1 = sin(X[POSE_PHI]);
        V[0] = c1 * (ub + du[0]) - s1 * (vb + du[1]); /* back to G (eq. 20) */
        V[1] = s1 * (ub + du[0]) + c1 * (vb + du[1]);
        V[2] = r1;
        X[POSE_X] += 0.5 * dt * (v0x + V[0]);
        X[POSE_Y] += 0.5 * dt * (v0y + V[1]);
        for (int j = 0; j < nw; ++j)
            delta[j] += dt * om_s[j]; /* eq. (19) */
        poses[N_POSE * k + POSE_X] = X[POSE_X];
        poses[N_POSE * k + POSE_Y] = X[POSE_Y];
        poses[N_POSE * k + POSE_PHI] = X[POSE_PHI];
        wear[N_WEAR * k + WEAR_S] = ps;
        wear[N_WEAR * k + WEAR_ALPHA] = pa;
        wear[N_WEAR * k + WEAR_T] = pt;
    }
}

/* controller.rollout.rollout_batch(MODEL_MF, ...): every row of Z, serially. */
void rollout_batch_mf(int B, int nw, int Np, const double *x0, const double *ref,
                      const double *Z, int D, const long *block, const double *P,
                      const double *S, const double *wx, const double *wy,
                      double *poses, double *wear, double *cmds)
{
    if (B <= 0 || nw <= 0 || Np <= 0)
        return;
    double delta[nw], om_w[nw], om_s[nw]; /* C99 VLAs: once per call, on the stack */
    for (int b = 0; b < B; ++b)
        rr_simulate_mf(nw, Np, x0, ref, Z + (long)b * D, block, P, S, wx, wy,
                       poses + (long)b * Np * N_POSE, wear + (long)b * Np * N_WEAR,
                       cmds + (long)b * 2 * nw, delta, om_w, om_s);
}
