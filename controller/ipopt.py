"""A gradient-based reference solver: the MPC's horizon problem solved by IPOPT (CasADi).

:class:`IpoptMPC` solves the *same* decision problem as :class:`controller.mpc.MPC`: the
offsets vector ``z`` (``n_blocks * 4n`` entries, the same box bounds), pushed through the
same policy (:func:`controller.rollout.commands_from_policy`) and the same MF prediction
(:func:`controller.rollout._simulate`, model 0), with the same cost
(:func:`controller.rollout.batch_cost`, eq. 22-26 plus the regularisation R). The rollout is
written again here symbolically (CasADi SX), operation for operation, so IPOPT gets exact
first and second derivatives; ``tests/test_ipopt.py`` checks that it reproduces the numba
rollout to 1e-9.

Smoothing
---------
DEVIATION(eq. 13-15), for the gradient-based solver only: the absolute values of the wear
powers ``P_s = |Fx (omega_w r_w - v_wx)|``, ``P_alpha = |Fy v_wy|``, ``P_t = |k_t F_N
omega_s|`` are replaced by ``sqrt(p^2 + eps^2)`` [W] (``eps`` = :attr:`IpoptOptions.eps_w`,
default 1 W per wheel and term). This adds at most ``eps`` per wheel and term (0.012 kW for
2 axles, against wear powers of 0.1-10 kW) and rounds the corner of ``|.|`` over
``|p| < eps`` (for ``P_t``: steering rates below 1.1e-3 rad/s on the paper's vehicle). The
reported cost of every solution is the *exact* cost (numba ``batch_cost``, true ``|.|``), so
annealer and IPOPT are compared on the same function. The other corners of the problem
(the clips of the policy: pose-feedback saturation, steering and wheel-speed limits, servo
rate limits) are kept exact (``fmin``/``fmax``/``if_else``): they are piecewise smooth and
rarely active at a solution while tracking, but where they saturate their gradient is
zero, so IPOPT, a local method, can stall from a start deep in a saturated region (e.g.
a start from rest, where negative wheel-speed offsets clip the speeds at 0); ``keep_best``
and the exact-cost check bound the damage (docs/CONTROLLER.md, "The IPOPT backend").
The heading error is wrapped exactly (``ceil``, zero derivative), as in the numba cost.
Square roots whose argument can reach 0 (speeds) get ``1e-20 (m/s)^2`` added under the
root, which leaves their values unchanged to 1e-16.
The smoothed |.| gets ``1e-20 W^2``, so that ``eps_w = 0`` (exact |.| to 1e-10 W) still
has finite derivatives at p = 0: without it IPOPT stopped with ``Invalid_Number_Detected``
at a standstill (a steering rate of exactly 0 in ``P_t``). Defensively, a wheel whose
desired velocity is exactly zero takes its feed-forward angle atan2(0, 0) = 0 through a
guarded branch, since atan2's derivative is 0/0 there.

Solver: ``casadi.nlpsol('ipopt')`` with the exact Hessian (``hessian='exact'``) or L-BFGS
(``'limited-memory'``), bounds on ``z`` only, no constraints. Only the paper's model
(``model='mf'``) is written symbolically; the baselines keep the annealer.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from . import rollout as _ro
from .models import MPCSettings
from .mpc import MPC, T_CONTROL, Command, ControllerError
from .reference import Reference

try:  # CasADi is an optional dependency (pip install msagv[ipopt])
    import casadi as ca
except ImportError:  # pragma: no cover - exercised only without casadi
    ca = None

TINY_SQ = 1e-20  # (m/s)^2 under the square roots of speeds (zero-speed derivative guard)
TINY_W2 = 1e-20  # W^2 under the smoothed |.| of the wear powers (eps_w = 0 guard)


def require_casadi() -> None:
    """Raise :class:`ControllerError` unless CasADi (with IPOPT) can be imported."""
    if ca is None:
        raise ControllerError("the ipopt solver needs CasADi, which is not installed "
                              "(pip install 'msagv[ipopt]', or use the annealer: --solver sa)")


def check_supported(settings: MPCSettings) -> None:
    """Raise :class:`ControllerError` unless IPOPT can solve the MPC of ``settings``
    (CasADi installed, the paper's prediction model 'mf')."""
    require_casadi()
    if settings.model != "mf":
        raise ControllerError(f"the ipopt solver supports the prediction model 'mf' only, not "
                              f"{settings.model!r} (the baselines use the annealer: --solver sa)")


@dataclass(frozen=True)
class IpoptOptions:
    """Options of the IPOPT backend (the horizon problem itself comes from MPCSettings).

    eps_w: smoothing of |.| in the wear powers eq. (13)-(15) [W] (see the module docstring).
    tol: IPOPT's convergence tolerance (``ipopt.tol``); 1e-8 for the reference optimum.
    max_iter: IPOPT's iteration limit.
    max_wall_ms: wall-clock limit per solve [ms] (``ipopt.max_wall_time``); ``None``: use
      the settings' ``deadline_ms`` if given, else no limit.
    hessian: 'exact' (second derivatives of the SX graph) or 'limited-memory' (L-BFGS).
    keep_best: return the warm start if IPOPT's answer has a higher *exact* cost (guards
      the controller against a failed solve); off for the reference optimum.
    """

    eps_w: float = 1.0
    tol: float = 1e-6
    max_iter: int = 200
    max_wall_ms: float | None = None
    hessian: str = "exact"
    keep_best: bool = True

    def __post_init__(self):
        if not (self.eps_w >= 0 and math.isfinite(self.eps_w)):
            raise ValueError(f"IpoptOptions.eps_w: must be >= 0, got {self.eps_w}")
        if not self.tol > 0:
            raise ValueError(f"IpoptOptions.tol: must be > 0, got {self.tol}")
        if self.max_iter < 1:
            raise ValueError(f"IpoptOptions.max_iter: must be >= 1, got {self.max_iter}")
        if self.hessian not in ("exact", "limited-memory"):
            raise ValueError(f"IpoptOptions.hessian: 'exact' or 'limited-memory', "
                             f"got {self.hessian!r}")
        if self.max_wall_ms is not None and not self.max_wall_ms > 0:
            raise ValueError(f"IpoptOptions.max_wall_ms: must be > 0, got {self.max_wall_ms}")


REFERENCE_OPTIONS = IpoptOptions(eps_w=1e-3, tol=1e-8, max_iter=3000, keep_best=False)
"""Options for the reference optimum: tight tolerance, run to convergence, |.| smoothed
over 1 mW only (each wheel's wear power is then overestimated by at most 1 mW per term)."""


# ---- the symbolic rollout (mirrors controller/rollout.py, model 0) ----------------------
def _sabs(p, eps):
    """|p| smoothed: sqrt(p^2 + eps^2 + TINY_W2) [W] (|p| to 1e-10 W for eps = 0, with
    finite derivatives everywhere: ``eps`` may be a CasADi parameter equal to 0)."""
    return ca.sqrt(p * p + eps * eps + TINY_W2)


def _atan2_guarded(y, x):
    """atan2(y, x), with atan2(0, 0) = 0 reached through a branch with finite derivatives
    (CasADi's atan2 derivative is 0/0 at the origin, and 0 * NaN poisons the chain rule)."""
    at0 = x * x + y * y <= 0.0
    return ca.atan2(ca.if_else(at0, 0.0, y), ca.if_else(at0, 1.0, x))


def _clip(v, lo, hi):
    return ca.fmin(ca.fmax(v, lo), hi)


def _wrap(a):
    """Angle wrapped to (-pi, pi], as controller.rollout._wrap (ceil: zero derivative)."""
    return a - 2.0 * math.pi * ca.ceil((a - math.pi) / (2.0 * math.pi))


def _mf_and_slope(xi, B, C, D, E):
    """Magic Formula value and slope, as controller.rollout._mf_and_slope."""
    Bx = B * xi
    arg = Bx - E * (Bx - ca.atan(Bx)) if E != 0.0 else Bx
    ca_ = C * ca.atan(arg)
    darg = B * (1.0 - E) + E * B / (1.0 + Bx * Bx)
    return D * ca.sin(ca_), D * ca.cos(ca_) * C * darg / (1.0 + arg * arg)


def _policy(X, delta, refk, z, base, nw, P, S, wx, wy, dt):
    """Symbolic :func:`controller.rollout.commands_from_policy`; returns (om_w, om_s) lists."""
    r_w = P[2]
    phi = X[2]
    cx = S[2] * (refk[0] - X[0])
    cy = S[2] * (refk[1] - X[1])
    cn = ca.sqrt(cx * cx + cy * cy + TINY_SQ)
    sc = ca.if_else(cn > S[4], S[4] / cn, 1.0)
    vdx = refk[3] + sc * cx
    vdy = refk[4] + sc * cy
    cr = _clip(S[3] * _wrap(refk[2] - phi), -S[5], S[5])
    rd = refk[5] + cr
    c = ca.cos(phi)
    s = ca.sin(phi)
    ub = c * vdx + s * vdy
    vb = -s * vdx + c * vdy
    kservo = (1.0 - math.exp(-S[1] * dt)) / dt
    dmin, dmax = S[9], S[10]
    acorner = S[14] * ca.sqrt(vdx * vdx + vdy * vdy + TINY_SQ) * rd if S[14] != 0.0 else 0.0
    om_w, om_s = [], []
    for k in range(nw):
        wvx = ub - rd * wy[k]
        wvy = vb + rd * wx[k]
        dff0 = _atan2_guarded(wvy, wvx) + acorner
        out = ca.logic_or(dff0 > dmax, dff0 < dmin)
        dff = _clip(dff0, dmin, dmax)
        wff_clip = ca.fmax((wvx * ca.cos(dff) + wvy * ca.sin(dff)) / r_w, 0.0)
        wff_free = ca.sqrt(wvx * wvx + wvy * wvy + TINY_SQ) / r_w
        wff = ca.if_else(out, wff_clip, wff_free)
        w = _clip(wff + z[base + k], 0.0, S[6])
        tgt = _clip(dff + z[base + nw + k], dmin, dmax)
        ws = kservo * (tgt - delta[k])
        lo = ca.fmax(S[7], (dmin - delta[k]) / dt)
        hi = ca.fmin(S[8], (dmax - delta[k]) / dt)
        ws = ca.if_else(lo > hi, 0.0, _clip(ws, lo, hi))
        om_w.append(w)
        om_s.append(ws)
    return om_w, om_s


def _solve3(A, b):
    """Cramer's rule, as controller.rollout._solve3."""
    a, bb, c = A[0][0], A[0][1], A[0][2]
    d, e, f = A[1][0], A[1][1], A[1][2]
    g, h, i = A[2][0], A[2][1], A[2][2]
    det = a * (e * i - f * h) - bb * (d * i - f * g) + c * (d * h - e * g)
    return ((b[0] * (e * i - f * h) - bb * (b[1] * i - f * b[2]) + c * (b[1] * h - e * b[2])) / det,
            (a * (b[1] * i - f * b[2]) - b[0] * (d * i - f * g) + c * (d * b[2] - b[1] * g)) / det,
            (a * (e * b[2] - b[1] * h) - bb * (d * b[2] - b[1] * g) + b[0] * (d * h - e * g)) / det)


def symbolic_rollout(x0, ref, z, block, P, S, wx, wy, eps=0.0):
    """The MF prediction of one candidate, symbolically (paper eq. 9-21 with the
    DEVIATIONs of :mod:`controller.rollout`: linearly implicit trapezoidal body-frame step).

    ``x0`` (6 + 2n) and ``ref`` ((N_p + 1) x 6, indexable as ref[k, i]) and ``z`` are CasADi
    expressions; ``block``, ``P``, ``S``, ``wx``, ``wy`` plain numbers (they are baked into
    the graph). ``eps`` [W]: smoothing of |.| in eq. (13)-(15) (0: exact).
    Returns ``(poses, wear, cmds)``: lists of N_p ``(x, y, phi)``, N_p ``(P_s, P_alpha,
    P_t)`` [W] and the first step's ``(om_w, om_s)``.
    """
    require_casadi()
    nw = len(wx)
    Np = len(block)
    dt = float(S[0])
    m, Iz, r_w, g, k_t = (float(P[i]) for i in range(5))
    v_eps = float(P[5])
    FN = m * g / nw  # Assumption 2
    P = [float(p) for p in P]
    S = [float(v) for v in S]
    wx = [float(v) for v in wx]
    wy = [float(v) for v in wy]
    th = _ro.THETA
    X = [x0[0], x0[1], x0[2]]
    V = [x0[3], x0[4], x0[5]]
    delta = [x0[6 + j] for j in range(nw)]
    poses, wear, cmds = [], [], None
    for k in range(Np):
        refk = [ref[k, i] for i in range(6)]
        base = int(block[k]) * 2 * nw
        om_w, om_s = _policy(X, delta, refk, z, base, nw, P, S, wx, wy, dt)
        if k == 0:
            cmds = (om_w, om_s)
        phi = X[2]
        c = ca.cos(phi)
        s = ca.sin(phi)
        ub = c * V[0] + s * V[1]
        vb = -s * V[0] + c * V[1]
        r = V[2]
        ps = 0.0
        pa = 0.0
        pt = 0.0
        for j in range(nw):
            pt += _sabs(k_t * FN * om_s[j], eps)  # eq. (15)
        A = [[0.0] * 3 for _ in range(3)]
        F = [0.0, 0.0, 0.0]
        for j in range(nw):
            dm = delta[j] + 0.5 * dt * om_s[j]
            cd = ca.cos(dm)
            sd = ca.sin(dm)
            vbx_w = ub - r * wy[j]  # eq. (6)
            vby_w = vb + r * wx[j]  # eq. (7)
            vwx = cd * vbx_w + sd * vby_w  # eq. (8)
            vwy = -sd * vbx_w + cd * vby_w
            # tire (controller.rollout._tire_wheel, model 0)
            d2 = vwx * vwx + v_eps * v_eps
            d = ca.sqrt(d2)
            slip = om_w[j] * r_w - vwx
            sl = slip / d  # eq. (10), regularised
            al = -ca.atan(vwy / d)  # eq. (9)
            ds_dx = -1.0 / d - slip * vwx / (d2 * d)
            q = d2 + vwy * vwy
            da_dx = vwy * vwx / (d * q)
            da_dy = -d / q
            Fx, dFx_ds = _mf_and_slope(sl, P[6], P[7], P[8] * FN, P[9])  # eq. (11)
            Fy, dFy_da = _mf_and_slope(al, P[10], P[11], P[12] * FN, P[13])  # eq. (12)
            k11, k12 = dFx_ds * ds_dx, 0.0
            k21, k22 = dFy_da * da_dx, dFy_da * da_dy
            ps += _sabs(Fx * slip, eps)  # eq. (13)
            pa += _sabs(Fy * vwy, eps)  # eq. (14)
            fbx = cd * Fx - sd * Fy
            fby = sd * Fx + cd * Fy
            F[0] += fbx
            F[1] += fby
            F[2] += wx[j] * fby - wy[j] * fbx
            a11 = cd * k11 - sd * k21
            a12 = cd * k12 - sd * k22
            a21 = sd * k11 + cd * k21
            a22 = sd * k12 + cd * k22
            m11 = a11 * cd - a12 * sd
            m12 = a11 * sd + a12 * cd
            m21 = a21 * cd - a22 * sd
            m22 = a21 * sd + a22 * cd
            yw, xw = wy[j], wx[j]
            A[0][0] += m11
            A[0][1] += m12
            A[0][2] += -m11 * yw + m12 * xw
            A[1][0] += m21
            A[1][1] += m22
            A[1][2] += -m21 * yw + m22 * xw
            A[2][0] += -yw * m11 + xw * m21
            A[2][1] += -yw * m12 + xw * m22
            A[2][2] += (-yw * (-m11 * yw + m12 * xw) + xw * (-m21 * yw + m22 * xw))
        for i in range(3):
            inv = 1.0 / Iz if i == 2 else 1.0 / m
            for jj in range(3):
                A[i][jj] = -th * dt * inv * A[i][jj]
            A[i][i] += 1.0
            F[i] = dt * inv * F[i]
        F[0] += dt * r * vb
        F[1] -= dt * r * ub
        A[0][1] -= th * dt * r
        A[0][2] -= th * dt * vb
        A[1][0] += th * dt * r
        A[1][2] += th * dt * ub
        du = _solve3(A, F)
        v0x, v0y = V[0], V[1]
        r1 = r + du[2]
        X[2] = X[2] + 0.5 * dt * (r + r1)
        c1 = ca.cos(X[2])
        s1 = ca.sin(X[2])
        V = [c1 * (ub + du[0]) - s1 * (vb + du[1]), s1 * (ub + du[0]) + c1 * (vb + du[1]), r1]
        X[0] = X[0] + 0.5 * dt * (v0x + V[0])
        X[1] = X[1] + 0.5 * dt * (v0y + V[1])
        delta = [delta[j] + dt * om_s[j] for j in range(nw)]  # eq. (19)
        poses.append((X[0], X[1], X[2]))
        wear.append((ps, pa, pt))
    return poses, wear, cmds


def symbolic_cost(poses, wear, ref, z, zprev, Q, L, R, nw):
    """Symbolic :func:`controller.rollout.batch_cost` of one candidate (eq. 22-26 + R)."""
    Np = len(poses)
    J = 0.0
    for k in range(Np):
        ex = poses[k][0] - ref[k + 1, 0]
        ey = poses[k][1] - ref[k + 1, 1]
        ep = _wrap(poses[k][2] - ref[k + 1, 2])
        J += Q[0] * ex * ex + Q[1] * ey * ey + Q[2] * ep * ep
        p0, p1, p2 = (wear[k][i] * 1e-3 for i in range(3))  # kW
        J += L[0] * p0 * p0 + L[1] * p1 * p1 + L[2] * p2 * p2
    nb = z.shape[0] // (2 * nw)
    reg = 0.0
    for blk in range(nb):
        for j in range(2 * nw):
            zi = z[blk * 2 * nw + j]
            prev = zprev[j] if blk == 0 else z[(blk - 1) * 2 * nw + j]
            dz = zi - prev
            if j < nw:
                reg += R[0] * dz * dz + R[2] * zi * zi
            else:
                reg += R[1] * dz * dz + R[3] * zi * zi
    return J / Np + reg


class HorizonNLP:
    """The horizon problem of one MPC configuration as a CasADi NLP (built once).

    Parameters of a solve: the state ``x0`` (6 + 2n), the reference rows ``ref``
    (N_p + 1, 6), the previous solution's first block ``zprev`` (2 * 2n).
    """

    def __init__(self, model, settings: MPCSettings, options: IpoptOptions = IpoptOptions()):
        check_supported(settings)
        self.settings, self.options = settings, options
        nw = model.n_wheels
        self.nw, self.dim = nw, model.dim
        Np = settings.N_p
        z = ca.SX.sym("z", model.dim)
        x0 = ca.SX.sym("x0", 6 + nw)
        ref = ca.SX.sym("ref", Np + 1, 6)
        zprev = ca.SX.sym("zprev", 2 * nw)
        eps = ca.SX.sym("eps")
        poses, wear, cmds = symbolic_rollout(x0, ref, z, model.block, model.P, model.S,
                                             model.wx, model.wy, eps=eps)
        L = settings.effective_L
        J = symbolic_cost(poses, wear, ref, z, zprev, settings.Q, L, settings.R, nw)
        p = ca.vertcat(x0, ca.vec(ref), zprev, eps)
        self.rollout_fn = ca.Function(
            "rollout", [x0, ref, z, eps],
            [ca.vertcat(*[ca.horzcat(*pk) for pk in poses]),
             ca.vertcat(*[ca.horzcat(*wk) for wk in wear]),
             ca.vertcat(ca.horzcat(*cmds[0]), ca.horzcat(*cmds[1]))])
        self.cost_fn = ca.Function("cost", [z, p], [J])
        opts = {"ipopt.print_level": 0, "ipopt.sb": "yes", "print_time": False,
                "ipopt.tol": options.tol, "ipopt.max_iter": options.max_iter,
                "ipopt.hessian_approximation": options.hessian}
        wall = options.max_wall_ms if options.max_wall_ms is not None else settings.deadline_ms
        if wall is not None:
            opts["ipopt.max_wall_time"] = wall / 1000.0
        self.solver = ca.nlpsol("horizon", "ipopt", {"x": z, "p": p, "f": J}, opts)

    def params(self, x0, ref, zprev, eps=None) -> np.ndarray:
        e = self.options.eps_w if eps is None else eps
        return np.r_[np.asarray(x0, float), np.asarray(ref, float).reshape(-1, order="F"),
                     np.asarray(zprev, float), e]

    def solve(self, x0, ref, zprev, z_init, lower, upper):
        """``(z, stats)``: IPOPT's answer from ``z_init`` inside [lower, upper] (its last
        iterate if it stopped early; see ``stats['return_status']``)."""
        r = self.solver(x0=z_init, p=self.params(x0, ref, zprev), lbx=lower, ubx=upper)
        st = self.solver.stats()
        return np.asarray(r["x"]).reshape(-1), st


class IpoptMPC(MPC):
    """The MPC of :class:`controller.mpc.MPC` with IPOPT in place of the annealer.

    Same interface: ``IpoptMPC(vehicle, settings, reference=None, period=0.01)``,
    ``step(state, reference=None) -> Command``, ``reset()``, ``warmup(state)``,
    ``set_reference(ref)``, ``solve_times_ms``. The horizon problem, the warm start
    (previous solution shifted by one period), the bounds and the returned commands are
    the annealer MPC's, except that IPOPT starts from the better (exact cost) of the
    shifted previous solution and zero offsets (the annealer's chains 0 and 1); with
    ``options.keep_best`` a solve that ends worse than that start (or fails) returns the
    start. ``Command.cost`` is the exact cost (numba ``batch_cost``) of the
    solution and ``Command.iterations`` IPOPT's iteration count. The annealer fields of
    ``settings`` (chains, iterations, sigma_*, t_*, ladder, adapt_*, seed) are ignored;
    ``deadline_ms`` becomes IPOPT's wall-time limit unless ``options.max_wall_ms`` is set.

    Extra parameter ``options``: :class:`IpoptOptions` (smoothing, tolerance, Hessian).
    """

    solver_name = "ipopt"

    def __init__(self, vehicle, settings: MPCSettings | None = None,
                 reference: Reference | None = None, period: float = T_CONTROL,
                 options: IpoptOptions | None = None):
        check_supported(settings or MPCSettings())
        super().__init__(vehicle, settings, reference, period)
        self.options = options or IpoptOptions()
        self.nlp = HorizonNLP(self.model, self.settings, self.options)
        self._buf1 = self.model.allocate(1)
        self._cost1 = np.empty(1)
        self.last_stats: dict = {}

    def exact_cost(self, x0, R, z, zprev) -> float:
        """The annealer's cost (numba rollout + batch_cost, exact |.|) of one vector z."""
        Z = np.ascontiguousarray(np.asarray(z, float)[None, :])
        self.model.rollout(x0, R, Z, out=self._buf1)
        _ro.batch_cost(self._buf1.poses, self._buf1.wear, R, Z, np.ascontiguousarray(zprev),
                       self.Q, self.L, self.R, self.nw, self._cost1)
        return float(self._cost1[0])

    def step(self, state: Mapping, reference: Reference | None = None) -> Command:
        """One IPOPT solve from the shifted previous solution: commands for one period."""
        t0 = time.perf_counter()
        x0, R, zprev, warm = self.horizon_problem(state, reference)
        warm = np.clip(warm, self.lower, self.upper)
        Jw = self.exact_cost(x0, R, warm, zprev)
        zero = np.clip(np.zeros_like(warm), self.lower, self.upper)
        J0 = self.exact_cost(x0, R, zero, zprev)
        if J0 < Jw:
            warm, Jw = zero, J0
        try:
            z, st = self.nlp.solve(x0, R, zprev, warm, self.lower, self.upper)
        except RuntimeError as e:  # CasADi raises on evaluation errors it cannot recover
            z, st = warm.copy(), {"return_status": f"error: {e}", "iter_count": 0,
                                  "success": False}
        if not np.all(np.isfinite(z)):
            z = warm.copy()
        z = np.clip(z, self.lower, self.upper)
        J = self.exact_cost(x0, R, z, zprev)
        if self.options.keep_best and not (J <= Jw):
            z, J = warm, Jw
        self.last_stats = st
        self.z = z
        om_w, om_s = self.commands_for(x0, R[0], z)
        ms = (time.perf_counter() - t0) * 1000.0
        self.solve_times_ms.append(ms)
        return Command(om_w, om_s, ms, J, int(st.get("iter_count", 0)))
