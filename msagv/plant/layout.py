"""Named layouts of the plain arrays the compiled kernels take, in one place.

The numba kernels (:mod:`plant.dynamics`, :mod:`controller.rollout`,
:mod:`controller.sa_kernel`) take flat float64 vectors, because that is what numba
compiles fastest. Every index into them is one of the names below; nothing else in the
kernels may index these vectors by number. The CasADi mirror
(``controller/mirrors/casadi_rollout.py``) uses the same names, and the C mirror
(``controller/mirrors/rollout_ref.c``) gets them from a header generated from this module
(:func:`c_header`) when it is built.

Parameter vector ``P`` (:func:`plant.dynamics.pack_params`): every value of the vehicle
the plant uses, once - body, Magic Formula tires, actuator and steering limits, the plant's
optional realism, and the slip regularisation speed. A prediction model's own parameters
(:mod:`plant.model_params`) follow them in its ``P``.

Settings vector ``S`` (:func:`controller.models.pack_settings`): the MPC's own settings
only (prediction step, servo and feedback gains, the cornering feed-forward gain).

Plant state ``y`` (:mod:`plant.dynamics`, ``9 + 6 nw`` entries for ``nw`` wheels)::

    Y_X .. Y_R             x, y, phi, vx, vy, r   (velocities in G, eq. 20)
    Y_DELTA ..             delta_ij               (nw entries)
    y_wear(nw) + WEAR_*    W_s, W_alpha, W_t      (wear work, integrated)
    y_omega_w(nw) ..       actual wheel speeds    (nw; used with wheel_lag > 0)
    y_omega_s(nw) ..       actual steering rates  (nw; used with steer_lag > 0)
    y_wheel_wear(nw, k) + WEAR_*   W_s, W_alpha, W_t of wheel k (3 nw; integrated)

The integrator's error norm covers the first ``n_error_states(nw)`` entries only (all but
the per-wheel wear work, which sums to the totals that the norm does see), so the
per-wheel states never change the step-size control of the dynamics.

Controller state ``x0`` (:mod:`controller.rollout`, ``6 + nw``): the head of ``y``, the
same indices (``X0_*`` = ``Y_*``). Reference rows ``ref`` use ``REF_*`` (= ``Y_X .. Y_R``).
Predicted poses use ``POSE_*``, predicted wear powers and the wear work ``WEAR_*``, the
first commands ``CMD_*``. Per-wheel plant outputs ``aux`` (nw, N_AUX) use ``AUX_*``.

Cost weights: ``Q`` (``Q_*``), ``L`` (``L_*``), ``R`` (``R_*``).

Numba freezes these integers into the compiled code, and its on-disk cache is keyed on
each kernel file's own source only, so a change here (or in another kernel file a kernel
calls) would leave stale cached kernels. Each kernel module therefore compiles a stamp of
what it depends on (:func:`kernel_stamp`) and drops its own stale cache files at import
(:func:`drop_stale_cache`).

This module imports nothing of the project but numba (the FMU bundles ``plant/`` under
another name).
"""

from __future__ import annotations

import hashlib
import os
import sys

from numba import njit

# the offset functions below are called by the kernels too (inlined there)
_offset = njit(cache=True, inline="always")

# ---- parameter vector P (plant.dynamics.pack_params) -----------------------------------
P_MASS = 0            # m [kg]
P_YAW_INERTIA = 1     # I_vz [kg m^2]
P_WHEEL_RADIUS = 2    # r_w [m]
P_G = 3               # g [m/s^2]
P_K_T = 4             # k_t of eq. 15 [m]
P_V_EPS = 5           # slip regularisation speed [m/s]
P_LON_B = 6           # longitudinal Magic Formula B, C, mu, E
P_LON_C = 7
P_LON_MU = 8
P_LON_E = 9
P_LAT_B = 10          # lateral Magic Formula B, C, mu, E
P_LAT_C = 11
P_LAT_MU = 12
P_LAT_E = 13
P_OMEGA_W_MAX = 14    # largest wheel speed [rad/s] (the smallest is 0)
P_OMEGA_S_MIN = 15    # steering-rate range [rad/s]
P_OMEGA_S_MAX = 16
P_DELTA_MIN = 17      # steering stops [rad]
P_DELTA_MAX = 18
P_CG_HEIGHT = 19      # plant only: load transfer (0: off) [m]
P_WHEEL_LAG = 20      # plant only: wheel-speed lag (0: off) [s]
P_STEER_LAG = 21      # plant only: steering-rate lag (0: off) [s]
P_COMBINED_SLIP = 22  # plant only: combined-slip tire forces (0: off, 1: on)
N_PARAMS = 23
# A prediction model with parameters of its own (plant.model_params) appends them after
# these: the kernels read them at P[N_PARAMS + ModelParams.offset(name)].

# ---- settings vector S (controller.models.pack_settings) -------------------------------
S_DT = 0              # prediction step [s]
S_K_SERVO = 1         # steering servo gain [1/s]
S_K_POS = 2           # position feedback gain [1/s]
S_K_PHI = 3           # heading feedback gain [1/s]
S_V_FB_MAX = 4        # position feedback limit [m/s]
S_R_FB_MAX = 5        # heading feedback limit [rad/s]
S_K_ALPHA = 6         # cornering feed-forward gain [rad per (m/s)(rad/s)]
S_POLICY = 7          # decision parametrisation: POLICY_* below (an integer held as float)
S_STRIDE = 8          # decision variables per move block (an integer held as float)
S_DIST_U = 9          # the offset-free disturbance, body frame (controller.disturbance): the
S_DIST_V = 10         # dynamic models add (a_u, a_v) [m/s^2] and alpha_r [rad/s^2] to the body's
S_DIST_R = 11         # accelerations, the kinematic one (u, v) [m/s] and r [rad/s] to its twist
N_SETTINGS = 12

# decision parametrisations (S_POLICY); the policy maps a block's variables to commands
POLICY_OFFSETS = 0    # per-wheel offsets of wheel speed and steering target from the feed-forward
POLICY_TWIST = 1      # offsets of the body twist (u, v, r): every wheel about one centre
POLICY_RAW = 2        # the commands themselves (omega_w, omega_s): the paper's U of eq. 27

# ---- plant state y and controller state x0 ---------------------------------------------
Y_X, Y_Y, Y_PHI, Y_VX, Y_VY, Y_R = 0, 1, 2, 3, 4, 5
Y_DELTA = 6           # first steering angle
N_BODY = 6            # x .. r
N_WEAR = 3            # W_s, W_alpha, W_t (and P_s, P_alpha, P_t)
WEAR_S, WEAR_ALPHA, WEAR_T = 0, 1, 2  # within a wear block (y_wear, predicted wear)


@_offset
def y_wear(nw):
    """First index of the wear work W_s, W_alpha, W_t in ``y``."""
    return Y_DELTA + nw


@_offset
def y_omega_w(nw):
    """First index of the actual (lagged) wheel speeds in ``y``."""
    return Y_DELTA + nw + N_WEAR


@_offset
def y_omega_s(nw):
    """First index of the actual (lagged) steering rates in ``y``."""
    return Y_DELTA + 2 * nw + N_WEAR


@_offset
def y_wheel_wear(nw, k):
    """First index of wheel ``k``'s wear work W_s, W_alpha, W_t in ``y`` (wheel order
    11, 12, 21, ...; ``+ WEAR_*`` within the block)."""
    return Y_DELTA + 3 * nw + N_WEAR + N_WEAR * k


@_offset
def n_error_states(nw):
    """Leading entries of ``y`` in the integrator's error norm: everything up to the
    per-wheel wear work (which no right-hand side reads, and whose sum over the wheels
    is the totals at ``y_wear``, already in the norm)."""
    return Y_DELTA + 3 * nw + N_WEAR


@_offset
def state_size(nw):
    """Length of the plant state ``y`` for ``nw`` wheels."""
    return Y_DELTA + 3 * nw + N_WEAR + N_WEAR * nw


X0_X, X0_Y, X0_PHI, X0_VX, X0_VY, X0_R = Y_X, Y_Y, Y_PHI, Y_VX, Y_VY, Y_R
X0_DELTA = Y_DELTA


@_offset
def x0_size(nw):
    """Length of the controller's prediction state ``x0`` (the head of ``y``)."""
    return X0_DELTA + nw


REF_X, REF_Y, REF_PHI, REF_VX, REF_VY, REF_R = Y_X, Y_Y, Y_PHI, Y_VX, Y_VY, Y_R
N_REF = 6
POSE_X, POSE_Y, POSE_PHI = 0, 1, 2
N_POSE = 3
CMD_W, CMD_S = 0, 1  # rows of the first commands (2, nw): omega_w, omega_s

# ---- per-wheel plant outputs aux (nw, N_AUX) -------------------------------------------
AUX_VWX = 0           # wheel velocity in W_ij [m/s]
AUX_VWY = 1
AUX_S = 2             # slip ratio
AUX_ALPHA = 3         # slip angle [rad]
AUX_FX = 4            # tire forces in W_ij [N]
AUX_FY = 5
AUX_FN = 6            # normal load [N]
AUX_DDELTA = 7        # actual steering rate (0 at a stop) [rad/s]
AUX_PS = 8            # wear powers P_s, P_alpha, P_t [W]
AUX_PALPHA = 9
AUX_PT = 10
AUX_OMEGA_W = 11      # actual wheel speed [rad/s]
N_AUX = 12

# ---- cost weights ----------------------------------------------------------------------
Q_X, Q_Y, Q_PHI = 0, 1, 2
L_S, L_ALPHA, L_T = 0, 1, 2  # quadratic wear weights (eq. 26) [1/kW^2]
LE_S, LE_ALPHA, LE_T = 3, 4, 5  # linear (wear-energy) weights [1/kW]
N_L = 6
R_DW, R_DD, R_OW, R_OD = 0, 1, 2, 3  # smoothing (wheel, angle), ridge (wheel, angle)

# vectors whose names must cover 0 .. N - 1 exactly once (checked below and by a test)
VECTORS = {
    "P": ("P_", "N_PARAMS"),
    "S": ("S_", "N_SETTINGS"),
    "AUX": ("AUX_", "N_AUX"),
}


def names(prefix: str) -> dict[str, int]:
    """The constants of this module starting with ``prefix`` (e.g. 'P_'), by name."""
    g = globals()
    return {k: v for k, v in g.items()
            if k.startswith(prefix) and k.isupper() and type(v) is int and not k.startswith("N_")}


def check() -> None:
    """Raise ``AssertionError`` unless every vector's names are 0 .. N - 1, once each."""
    for vec, (prefix, size) in VECTORS.items():
        got = sorted(names(prefix).values())
        assert got == list(range(globals()[size])), f"layout of {vec}: {got}"


check()


# ---- the C mirror's header -------------------------------------------------------------
def c_header() -> str:
    """``#define`` lines of the P, S, x0 and output indices for the C mirror."""
    lines = ["/* Generated from plant/layout.py by plant.layout.c_header(); do not edit. */",
             "#ifndef MSAGV_LAYOUT_H", "#define MSAGV_LAYOUT_H"]
    for prefix in ("P_", "S_", "X0_", "REF_", "POSE_", "WEAR_", "CMD_"):
        for k, v in sorted(names(prefix).items(), key=lambda kv: kv[1]):
            lines.append(f"#define {k} {v}")
    for k in ("N_PARAMS", "N_SETTINGS", "N_REF", "N_POSE", "N_WEAR"):
        lines.append(f"#define {k} {globals()[k]}")
    lines.append("#endif")
    return "\n".join(lines) + "\n"


# ---- stale-cache guard for the kernel modules ------------------------------------------
def kernel_stamp(*depends_on: str) -> int:
    """A 56-bit stamp of this file (its constants and the offset functions the kernels
    inline) and of the source files ``depends_on`` (the other kernel modules whose
    functions a kernel module compiles into its own)."""
    h = hashlib.blake2b(digest_size=7)
    h.update(__name__.encode())  # a cache of the package under another name is stale too
    for path in (__file__, *depends_on):
        with open(path, "rb") as f:
            h.update(f.read())
    return int.from_bytes(h.digest(), "little")


def drop_stale_cache(stamp_kernel, stamp: int, module_file: str) -> bool:
    """Remove the cache files of ``module_file``'s kernels if ``stamp_kernel()`` (a
    ``njit(cache=True)`` function of that module returning its :func:`kernel_stamp`,
    compiled or loaded from the cache) differs from ``stamp``. Call it at import, before
    any other kernel of the module runs (numba loads cached kernels on their first call).
    Returns True when files were removed. A cache that cannot even be loaded (e.g. written
    when the package had another name: its pickled environment names a module that no
    longer exists) is stale too."""
    try:
        if stamp_kernel() == stamp:
            return False
    except Exception:  # an unloadable cache entry: drop it like a stale one
        pass
    cache = getattr(stamp_kernel, "_cache", None)
    path = getattr(cache, "cache_path", None)
    if not path or not os.path.isdir(path):
        return False
    stem = os.path.splitext(os.path.basename(module_file))[0] + "."
    for name in os.listdir(path):
        if name.startswith(stem) and name.endswith((".nbi", ".nbc")):
            try:
                os.unlink(os.path.join(path, name))
            except OSError:  # another process got there first
                pass
    if os.environ.get("MSAGV_CACHE_VERBOSE"):
        print(f"[msagv] dropped stale numba cache of {module_file}", file=sys.stderr)
    return True
