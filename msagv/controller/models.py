"""Prediction models behind one interface, and the MPC settings they share.

``model.rollout(x0, ref, Z) -> Rollout(poses, wear, first_commands)`` predicts a batch of
candidate decision vectors at once (layouts in :mod:`controller.rollout`). The four models
differ only in how the state evolves; the policy (feed-forward + offsets), the cost and
the optimiser are shared, which is the paper's "unified framework" for its baselines.
"""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass, fields, replace
from typing import NamedTuple

import numpy as np

from msagv.plant import layout as lay
from msagv.plant.dynamics import pack_params
from msagv.plant.model_params import DUGOFF, ModelParams
from msagv.plant.vehicle import Vehicle

from . import rollout as _ro

# The tables the settings' names are checked against and the command line's choices and
# help are read from. "method" is the wear term of the cost (eq. 26 or its linear form):
METHODS: dict[str, str] = {
    "two": "the paper's quadratic wear term P^T L P (weights L)",
    "two-energy": "a linear wear-energy term E . P (weights E: the predicted wear work)",
    "ntwo": "no wear term",
}
# the decision parametrisation (controller.rollout.commands_from_policy): name -> (the
# kernels' code, plant.layout.POLICY_*; one line)
POLICIES: dict[str, tuple[int, str]] = {
    "offsets": (lay.POLICY_OFFSETS, "per-wheel offsets from the kinematic feed-forward"),
    "twist": (lay.POLICY_TWIST, "offsets of the body twist, every wheel about one centre "
                                "(the paper's Kinematic)"),
    "raw": (lay.POLICY_RAW, "the commands themselves (eq. 27's U)"),
}


@dataclass(frozen=True)
class MPCSettings:
    """Settings of the tire-wear-aware MPC (paper Section 3.5) and of its annealer.

    Horizon (see docs/CONTROLLER.md for why these defaults):
      dt: prediction step [s] (10 control periods T = 0.01 s).
      N_p: prediction horizon in steps (N_p * dt = 1.0 s: 9.7 m at 35 km/h).
      blocks: move blocks in prediction steps; N_c = sum(blocks) (0.6 s), controls held
        after N_c. 3 blocks x 4n offsets = 24 decision variables for 2 axles.
    Cost (eq. 22-26):
      Q: (Q_X [1/m^2], Q_Y [1/m^2], Q_phi [1/rad^2]).
      L: (L_s, L_alpha, L_t) [1/kW^2], the paper's quadratic wear weights (eq. 26);
        applied only for method 'two'.
      E: (E_s, E_alpha, E_t) [1/kW], the wear-energy weights: the cost adds
        ``E . P_k`` per prediction step (its sum over the horizon times dt is the
        predicted wear work); applied only for method 'two-energy'.
      R: command regularisation shared by TWO and NTWO: (R_dw [1/(rad/s)^2],
        R_dd [1/rad^2]) on changes of the offsets between blocks and against the previous
        solution, (R_ow, R_od) on the offsets themselves.
    Policy:
      K_servo [1/s]: steering servo gain toward the target angle.
      K_pos [1/s], K_phi [1/s], v_fb_max [m/s], r_fb_max [rad/s]: the feed-forward's
        saturated pose feedback.
      offset_w_max [rad/s], offset_d_max [rad]: box of the decision offsets.
    Annealer:
      chains, iterations: fixed budget (deterministic); each chain proposes
        max(1, LANES // chains) moves per iteration (controller.rollout.LANES = 8: one
        SIMD tile) and takes the best. deadline_ms: optional wall-clock budget per solve
        (anytime). seed: the random generator's seed.
      sigma_w [rad/s], sigma_d [rad]: initial proposal scales; sigma_final: their final
        fraction; t_start, t_end: relative temperatures; ladder: the smallest initial
        per-chain step factor (chains start on a geometric ladder from it to 1);
        adapt_up, adapt_down: per-chain step factor after an accepted / rejected move.
      polish: at most this many Gauss-Newton steps after the annealing, from its best
        point (controller.sa_kernel, "the Gauss-Newton polish": the residuals' Jacobian by
        forward differences of the SIMD prediction, LANES Levenberg-Marquardt candidates
        in one tile per step, the best kept if it lowers the cost; stops when a step
        gains less than 1e-4 of the cost); 0: none. The defaults (5 iterations, then up
        to 8 steps, ~3 on average) replaced 40 iterations and no polish: within 0.01 % of
        IPOPT's optimum at the median at 2-8 axles, in a third less time at 2 axles
        (docs/PERFORMANCE.md).
    method: 'two-energy' (default: the linear wear-energy term, weights E), 'two' (the
      paper's quadratic wear term, weights L) or 'ntwo' (no wear term). The default is the
      wear energy because the study finds it the better controller at equal tracking error
      and the paper's quadratic term no better than none (docs/RESULTS.md); the paper's TWO
      is ``method='two'`` (``--method two``).
    model: 'mf' (paper), 'dugoff' (DH), 'kinematic', 'tct'.
    policy: the decision parametrisation (controller.rollout.commands_from_policy):
      'offsets' (per-wheel offsets from the kinematic feed-forward; default), 'twist'
      (offsets of the body twist, every wheel about one instantaneous centre: the paper's
      Kinematic baseline) or 'raw' (the commands omega_w, omega_s themselves: eq. 27's U).
    dugoff_stiffness: the DH baseline's Dugoff stiffnesses: 'derived' (default) from the
      Magic Formula tires at the vehicle's load (C_s = B C mu F_N of the longitudinal, C_alpha
      of the lateral curve: they scale with the mass) or 'file' (the vehicle file's
      [tire.dugoff] values, whatever the load).
    threads: 1 = serial rollouts (default: predictable when the plant or other runs share
      the cores); > 1 spreads the candidates over that many numba threads.
    ff_cornering: add the steady cornering slip angle to the feed-forward (dynamic models).
    ref_smoothing [m]: the controller tracks its reference smoothed along the path by a
      Gaussian of this standard deviation in arc length
      (:meth:`controller.reference.Reference.smoothed`), which cuts each corner toward its
      inside by about ``ref_smoothing^2 kappa / 2``; errors are still measured against the
      reference itself. 0 (default): the reference as given. The study's wear-blind lever
      of accuracy (docs/RESULTS.md).
    offset_free: carry a body-frame disturbance estimated from the measured states in the
      prediction (:mod:`controller.disturbance`), so that a constant model error (tires,
      mass, floor) leaves no steady tracking error. None (default): on for the prediction
      models where it does not hurt the nominal case (:data:`OFFSET_FREE_DEFAULT`: mf,
      dugoff and tct; measured in docs/CONTROLLER.md), off for kinematic.
      disturbance_tau [s]: its filter's time constant.
    adapt: re-estimate the prediction's tire factors (cornering and longitudinal stiffness,
      friction) online (:mod:`controller.adaptation`); the 'mf', 'dugoff' and 'tct'
      models (IPOPT and acados take the adapted entries as parameters of their generated
      problems, docs/CONTROLLER.md).
      adapt_sigma_v [m/s]: the standard deviation of a measured body velocity, the
      adaptation's measurement noise (raise it for noisy odometry: the factors then move
      more slowly and less on noise).
      adapt_window [periods]: the adaptation compares the velocity measured at the end of
      this many control periods with the prediction from the state measured at their start
      (one update per window; 1..100). 1 reads one period; with noisy odometry a longer window
      (10: 0.1 s) keeps the noise of the start state from biasing the factors
      (docs/CONTROLLER.md).
      adapt_noise: 'auto' (default): when the measured velocities' noise (estimated from
      their second differences) is over 3x adapt_sigma_v and 4 mm/s, the adaptation
      restarts from the file's tires with that noise as its R (followed from then on) and
      a window of at least 10 periods; a noise-free run never switches. 'fixed': adapt_sigma_v and
      adapt_window as given, and a warning when the noise is over 3x adapt_sigma_v.
    """

    method: str = "two-energy"
    model: str = "mf"
    dt: float = 0.1
    N_p: int = 10
    blocks: tuple[int, ...] = (1, 2, 3)
    Q: tuple[float, float, float] = (200.0, 200.0, 1000.0)
    L: tuple[float, float, float] = (0.02, 0.01, 0.02)
    E: tuple[float, float, float] = (0.1, 0.1, 0.1)
    R: tuple[float, float, float, float] = (0.05, 20.0, 0.005, 2.0)
    K_servo: float = 10.0
    K_pos: float = 1.0
    K_phi: float = 1.0
    v_fb_max: float = 1.5
    r_fb_max: float = 0.3
    offset_w_max: float = 3.0
    offset_d_max: float = 0.3
    chains: int = 2
    iterations: int = 5
    deadline_ms: float | None = None
    seed: int = 0
    sigma_w: float = 0.3
    sigma_d: float = 0.02
    sigma_final: float = 0.1
    t_start: float = 1e-2
    t_end: float = 1e-4
    ladder: float = 0.05
    adapt_up: float = 1.5
    adapt_down: float = 0.7
    polish: int = 8
    threads: int = 1
    ff_cornering: bool = True
    policy: str = "offsets"
    dugoff_stiffness: str = "derived"
    ref_smoothing: float = 0.0
    offset_free: bool | None = None
    disturbance_tau: float = 0.05
    adapt: bool = False
    adapt_sigma_v: float = 1e-3
    adapt_window: int = 1
    adapt_noise: str = "auto"

    def __post_init__(self):
        bad = None
        if self.method not in METHODS:
            bad = f"method: expected one of {', '.join(METHODS)}, got {self.method!r}"
        elif self.policy not in POLICIES:
            bad = f"policy: expected one of {', '.join(POLICIES)}, got {self.policy!r}"
        elif self.dugoff_stiffness not in ("derived", "file"):
            bad = f"dugoff_stiffness: expected 'derived' or 'file', got {self.dugoff_stiffness!r}"
        elif len(self.E) != 3 or any(not (q >= 0 and math.isfinite(q)) for q in self.E):
            bad = f"E: need 3 finite weights >= 0, got {self.E}"
        elif self.model not in MODELS:
            bad = f"model: expected one of {sorted(MODELS)}, got {self.model!r}"
        elif not (self.dt > 0 and math.isfinite(self.dt)):
            bad = f"dt: must be > 0, got {self.dt}"
        elif self.N_p < 1:
            bad = f"N_p: must be >= 1, got {self.N_p}"
        elif not self.blocks or any(int(b) < 1 for b in self.blocks):
            bad = f"blocks: need >= 1 block of >= 1 step, got {self.blocks}"
        elif sum(self.blocks) > self.N_p:
            bad = f"blocks: N_c = sum(blocks) = {sum(self.blocks)} exceeds N_p = {self.N_p}"
        elif len(self.Q) != 3 or any(not (q >= 0 and math.isfinite(q)) for q in self.Q):
            bad = f"Q: need 3 finite weights >= 0, got {self.Q}"
        elif len(self.L) != 3 or any(not (q >= 0 and math.isfinite(q)) for q in self.L):
            bad = f"L: need 3 finite weights >= 0, got {self.L}"
        elif len(self.R) != 4 or any(not (q >= 0 and math.isfinite(q)) for q in self.R):
            bad = f"R: need 4 finite weights >= 0, got {self.R}"
        elif self.chains < 2 or self.iterations < 1:
            bad = "chains must be >= 2 and iterations >= 1"
        elif not (0.0 < self.ladder <= 1.0):
            bad = f"ladder: must be in (0, 1], got {self.ladder}"
        elif not (self.adapt_up >= 1.0 and 0.0 < self.adapt_down <= 1.0):
            bad = f"adapt_up must be >= 1 and adapt_down in (0, 1], got {self.adapt_up}, {self.adapt_down}"
        elif self.polish < 0:
            bad = f"polish: must be >= 0, got {self.polish}"
        elif self.threads < 1:
            bad = f"threads: must be >= 1, got {self.threads}"
        elif not hasattr(self.seed, "__index__") or self.seed < 0:  # numpy's seeds are >= 0
            bad = f"seed: must be an integer >= 0, got {self.seed!r}"
        elif not (math.isfinite(self.ref_smoothing) and self.ref_smoothing >= 0):
            bad = f"ref_smoothing: must be a finite length >= 0 m, got {self.ref_smoothing}"
        elif self.offset_free not in (None, True, False):
            bad = f"offset_free: expected true or false, got {self.offset_free!r}"
        elif not (math.isfinite(self.adapt_sigma_v) and self.adapt_sigma_v > 0):
            bad = f"adapt_sigma_v: must be a finite speed > 0 m/s, got {self.adapt_sigma_v}"
        elif not _whole(self.adapt_window, 1, 100):
            bad = f"adapt_window: must be a whole number of periods in 1..100, got {self.adapt_window!r}"
        elif self.adapt_noise not in ("auto", "fixed"):
            bad = f"adapt_noise: expected 'auto' or 'fixed', got {self.adapt_noise!r}"
        elif self.adapt and self.model not in ADAPTABLE:
            bad = (f"adapt: the online tire adaptation needs a tire model "
                   f"({', '.join(repr(m) for m in ADAPTABLE)}), not {self.model!r}")
        elif not (math.isfinite(self.disturbance_tau) and self.disturbance_tau > 0):
            bad = f"disturbance_tau: must be a finite time > 0 s, got {self.disturbance_tau}"
        elif self.deadline_ms is not None and not self.deadline_ms > 0:
            bad = f"deadline_ms: must be > 0, got {self.deadline_ms}"
        elif min(self.K_servo, self.offset_w_max, self.offset_d_max, self.sigma_w,
                 self.sigma_d, self.sigma_final, self.t_start, self.t_end) <= 0:
            bad = "K_servo, offsets, sigmas and temperatures must be > 0"
        elif min(self.K_pos, self.K_phi, self.v_fb_max, self.r_fb_max) < 0:
            bad = "feedback gains and limits must be >= 0"
        if bad:
            raise ValueError(f"MPCSettings.{bad}")
        object.__setattr__(self, "blocks", tuple(int(b) for b in self.blocks))
        object.__setattr__(self, "adapt_window", int(self.adapt_window))

    @property
    def offset_free_on(self) -> bool:
        """Whether the prediction carries the offset-free disturbance (``offset_free``, or
        by default :data:`OFFSET_FREE_DEFAULT` of the model)."""
        if self.offset_free is None:
            return OFFSET_FREE_DEFAULT.get(self.model, False)
        return bool(self.offset_free)

    @property
    def N_c(self) -> int:
        return sum(self.blocks)

    @property
    def effective_L(self) -> tuple[float, ...]:
        """The kernels' wear weights (``plant.layout.L_*``, ``LE_*``): L for 'two', E for
        'two-energy', none for 'ntwo'."""
        quad = tuple(self.L) if self.method == "two" else (0.0, 0.0, 0.0)
        lin = tuple(self.E) if self.method == "two-energy" else (0.0, 0.0, 0.0)
        return quad + lin

    def with_(self, **kw) -> "MPCSettings":
        return replace(self, **kw)

    @classmethod
    def field_names(cls) -> list[str]:
        return [f.name for f in fields(cls)]

    @classmethod
    def parse_assignments(cls, items) -> dict:
        """``NAME=VALUE`` strings (a command line's ``--set``) as settings fields, each
        value in its field's type (a tuple as comma-separated values; a bool as
        1/true/yes/on or 0/false/no/off). Raises ValueError naming the bad item."""
        base = cls()
        kw = {}
        for item in items:
            if "=" not in item:
                raise ValueError(f"expected NAME=VALUE, got '{item}'")
            k, v = item.split("=", 1)
            k = k.strip()
            if k not in cls.field_names():
                raise ValueError(f"unknown setting '{k}' (known: "
                                 f"{', '.join(cls.field_names())})")
            cur = getattr(base, k)
            try:
                if isinstance(cur, tuple):
                    kw[k] = tuple(type(cur[0])(x) for x in v.split(","))
                elif isinstance(cur, bool) or k == "offset_free":
                    if v.lower() not in ("1", "true", "yes", "on", "0", "false", "no", "off"):
                        raise ValueError(v)
                    kw[k] = v.lower() in ("1", "true", "yes", "on")
                elif cur is None:
                    kw[k] = float(v)
                else:
                    kw[k] = type(cur)(v)
            except ValueError:
                raise ValueError(f"{k}: cannot parse '{v}'") from None
        return kw


class Rollout(NamedTuple):
    poses: np.ndarray  # (B, N_p, 3) x, y, phi at steps 1..N_p
    wear: np.ndarray  # (B, N_p, 3) P_s, P_alpha, P_t over steps 0..N_p-1 [W]
    first_commands: np.ndarray  # (B, 2, 2n) omega_w, omega_s of step 0


def _whole(v, lo: int, hi: int) -> bool:
    """``v`` is a whole number (an int or a numpy integer, not a bool) in ``lo..hi``."""
    if isinstance(v, bool):
        return False
    try:
        return lo <= operator.index(v) <= hi
    except TypeError:
        return False


def pack_settings(vehicle: Vehicle, s: MPCSettings) -> np.ndarray:
    """The kernels' settings vector ``S`` (layout ``plant.layout.S_*``): the MPC's own
    settings only; every vehicle value (limits, a model's own parameters) is in ``P``
    (:meth:`PredictionModel.pack`)."""
    la = vehicle.tire_lateral
    # cornering stiffness per wheel as each model sees it: MF slope at 0 is B C D
    if s.model == "kinematic" or not s.ff_cornering:
        k_alpha = 0.0
    else:
        c_alpha = (dugoff_stiffness(vehicle, s)[1] if s.model == "dugoff"
                   else la.B * la.C * la.mu * vehicle.normal_load)
        k_alpha = vehicle.mass / (vehicle.n_wheels * c_alpha)
    S = np.full(lay.N_SETTINGS, np.nan)
    S[lay.S_DT] = s.dt
    S[lay.S_K_SERVO] = s.K_servo
    S[lay.S_K_POS] = s.K_pos
    S[lay.S_K_PHI] = s.K_phi
    S[lay.S_V_FB_MAX] = s.v_fb_max
    S[lay.S_R_FB_MAX] = s.r_fb_max
    S[lay.S_K_ALPHA] = k_alpha
    S[lay.S_POLICY] = POLICIES[s.policy][0]
    S[lay.S_STRIDE] = policy_stride(s.policy, vehicle.n_wheels)
    S[[lay.S_DIST_U, lay.S_DIST_V, lay.S_DIST_R]] = 0.0  # set each solve by the observer
    return S


def policy_stride(policy: str, n_wheels: int) -> int:
    """Decision variables per move block: 3 for the twist, 2 per wheel otherwise."""
    return 3 if policy == "twist" else 2 * n_wheels


def dugoff_stiffness(vehicle: Vehicle, s: MPCSettings) -> tuple[float, float]:
    """``(C_s, C_alpha)`` of the DH baseline's Dugoff tires: derived from the Magic Formula
    at the vehicle's load (the slopes at zero slip, ``B C mu F_N``; paper-faithful: the
    same tires and load as the plant) or, with ``dugoff_stiffness='file'``, the file's."""
    if s.dugoff_stiffness == "file":
        own = vehicle.model_values(DUGOFF.section)
        return own["C_s"], own["C_alpha"]
    lo, la, FN = vehicle.tire_longitudinal, vehicle.tire_lateral, vehicle.normal_load
    return lo.B * lo.C * lo.mu * FN, la.B * la.C * la.mu * FN


class PredictionModel:
    """Base of the prediction models: a batch rollout over the shared policy."""

    model_id: int = _ro.MODEL_MF
    name: str = "mf"
    summary: str = ""  # one line for the command line's help
    #: the model's own parameters (plant.model_params: the vehicle file's section, the
    #: checks, the FMU's variables follow from it), packed after the shared P; None: none
    params: ModelParams | None = None

    def __init__(self, vehicle: Vehicle, settings: MPCSettings):
        self.vehicle = vehicle
        self.settings = settings
        P, self.wx, self.wy = pack_params(vehicle)
        self.P = P if self.params is None else np.r_[P, self.pack(vehicle, settings)]
        self.S = pack_settings(vehicle, settings)
        steps = []
        for b, n in enumerate(settings.blocks):
            steps += [b] * n
        steps += [len(settings.blocks) - 1] * (settings.N_p - len(steps))
        self.block = np.array(steps, dtype=np.int64)
        self.n_wheels = vehicle.n_wheels
        self.policy = settings.policy
        self.stride = policy_stride(settings.policy, vehicle.n_wheels)
        # the first nsplit variables of a block are weighted as wheel speeds (R_dw, R_ow)
        self.nsplit = 3 if settings.policy == "twist" else vehicle.n_wheels
        self.dim = len(settings.blocks) * self.stride

    @classmethod
    def pack(cls, vehicle: Vehicle, settings: MPCSettings) -> np.ndarray:
        """The model's own parameters as the kernels read them after the shared ``P``
        (at ``plant.layout.N_PARAMS + params.offset(name)``): the vehicle's values, in the
        declared order. A model that derives some of them overrides this."""
        return np.array(vehicle.model_values(cls.params.section).values, dtype=np.float64)

    def box(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(lower, upper, sigma)`` of the decision vector: its bounds and the annealer's
        initial proposal scales, per parametrisation. Offsets: +-offset_w_max [rad/s] and
        +-offset_d_max [rad] (sigma_w, sigma_d); twist: +-v_fb_max [m/s] on (du, dv) and
        +-r_fb_max [rad/s] on dr (sigma_w r_w, sigma_w r_w, sigma_w r_w / 3); raw: eq. 27's
        bounds [0, omega_w_max] and [omega_s_min, omega_s_max] (sigma_w, K_servo sigma_d)."""
        s, nw, nb = self.settings, self.n_wheels, len(self.settings.blocks)
        lim = self.vehicle.limits
        if s.policy == "twist":
            hi = np.array([s.v_fb_max, s.v_fb_max, s.r_fb_max])
            lo = -hi
            sw = s.sigma_w * self.vehicle.wheel_radius
            sig = np.array([sw, sw, sw / 3.0])
        elif s.policy == "raw":
            lo = np.r_[np.zeros(nw), np.full(nw, lim.omega_s_min)]
            hi = np.r_[np.full(nw, lim.omega_w_max), np.full(nw, lim.omega_s_max)]
            sig = np.r_[np.full(nw, s.sigma_w), np.full(nw, s.K_servo * s.sigma_d)]
        else:
            hi = np.r_[np.full(nw, s.offset_w_max), np.full(nw, s.offset_d_max)]
            lo = -hi
            sig = np.r_[np.full(nw, s.sigma_w), np.full(nw, s.sigma_d)]
        return np.tile(lo, nb), np.tile(hi, nb), np.tile(sig, nb)

    def origin(self, x0: np.ndarray, ref0: np.ndarray, period: float) -> np.ndarray:
        """The decision vector of the plain feed-forward at ``x0`` (annealer chain 1's start
        and a fresh controller's warm start): zero offsets, or for 'raw' the feed-forward's
        commands held over the horizon."""
        if self.policy != "raw":
            return np.zeros(self.dim)
        nw = self.n_wheels
        S = self.S.copy()
        S[lay.S_POLICY] = lay.POLICY_OFFSETS
        S[lay.S_STRIDE] = 2 * nw
        om_w, om_s = np.empty(nw), np.empty(nw)
        _ro.commands_from_policy(np.ascontiguousarray(x0[lay.X0_X:lay.X0_PHI + 1]),
                                 np.ascontiguousarray(x0[lay.X0_DELTA:]), ref0,
                                 np.zeros(2 * nw), 0, nw, self.P, S, self.wx, self.wy, period,
                                 om_w, om_s)
        return np.tile(np.r_[om_w, om_s], len(self.settings.blocks))

    def allocate(self, batch: int) -> Rollout:
        Np, nw = self.settings.N_p, self.n_wheels
        return Rollout(np.empty((batch, Np, lay.N_POSE)), np.empty((batch, Np, lay.N_WEAR)),
                       np.empty((batch, 2, nw)))

    def rollout(self, x0: np.ndarray, ref: np.ndarray, Z: np.ndarray,
                out: Rollout | None = None, exact: bool = False) -> Rollout:
        """Predict every row of ``Z`` (B, D) from ``x0`` against ``ref`` (N_p + 1, 6) with
        the controller's SIMD prediction (:data:`controller.rollout.FAST`), or with
        ``exact`` the same kernels on the math library's functions (``EXACT``)."""
        Z = np.ascontiguousarray(Z, dtype=np.float64)
        if Z.ndim == 1:
            Z = Z[None, :]
        if Z.shape[1] != self.dim:
            raise ValueError(f"rollout: decision vectors must have {self.dim} entries, got {Z.shape[1]}")
        if ref.shape != (self.settings.N_p + 1, lay.N_REF):
            raise ValueError(f"rollout: reference must have shape ({self.settings.N_p + 1}, 6)")
        out = out if out is not None and out.poses.shape[0] == Z.shape[0] else self.allocate(Z.shape[0])
        pred = _ro.EXACT if exact else _ro.FAST
        fn = pred.rollout_batch if self.settings.threads <= 1 else pred.rollout_batch_parallel
        fn(self.model_id, np.ascontiguousarray(x0, dtype=np.float64),
                          np.ascontiguousarray(ref), Z, self.block, self.P, self.S, self.wx,
                          self.wy, out.poses, out.wear, out.first_commands)
        return out


class MagicFormulaModel(PredictionModel):
    """The paper's model (TWO/NTWO): rigid body eq. (17)-(21) with Magic Formula tires
    (eq. 9-12) and the wear powers eq. (13)-(16), constant loads (Assumption 2)."""

    summary = "the paper's: Magic Formula tires and wear powers (TWO/NTWO)"
    model_id = _ro.MODEL_MF
    name = "mf"


class DugoffModel(PredictionModel):
    """DH baseline (Du et al. 2024, "hierarchical coordinated control ... tire wear"):
    the same rigid-body dynamics with the Dugoff tire model (:func:`plant.tire.dugoff_forces`)
    in place of the Magic Formula. Simplification: linear stiffness up to a friction-circle
    saturation. Its stiffnesses are derived from the same Magic Formula tires at the same
    load as the plant (:func:`dugoff_stiffness`), so they scale with the mass; the file's
    fixed values with ``dugoff_stiffness='file'`` (the project's earlier DH)."""

    summary = "the DH baseline: Dugoff tires"
    model_id = _ro.MODEL_DUGOFF
    name = "dugoff"
    params = DUGOFF

    @classmethod
    def pack(cls, vehicle: Vehicle, settings: MPCSettings) -> np.ndarray:
        """The file's ``[tire.dugoff]`` with the stiffnesses of :func:`dugoff_stiffness`."""
        own = super().pack(vehicle, settings)
        own[[DUGOFF.offset("C_s"), DUGOFF.offset("C_alpha")]] = dugoff_stiffness(vehicle, settings)
        return own


class KinematicModel(PredictionModel):
    """Kinematic baseline (Zhang et al. 2016, rotation-centre-distance based steering):
    the body twist is the rigid motion that best fits the commanded wheel velocities
    ``omega_w r_w (cos delta, sin delta)`` (exactly one instantaneous centre when the
    wheels are steered consistently). Simplifications: pure rolling, no slip and no tire
    forces, velocity follows the commands instantly; the predicted slip wear is zero.
    The paper's Kinematic method ("considers only geometric relationships", Section 4.2;
    its explanation of why it wears least is that every wheel turns about one centre)
    pairs it with ``policy='twist'``: the decision is the body twist, every wheel follows
    it about one instantaneous centre."""

    summary = "the Kinematic baseline: pure rolling, no tire forces"
    model_id = _ro.MODEL_KINEMATIC
    name = "kinematic"


class TCTModel(PredictionModel):
    """TCT baseline (Tang et al. 2024, all-wheel-steering multi-axle vehicle): lateral and
    yaw dynamics only, with Magic Formula lateral forces; the longitudinal speed is held at
    the reference speed (no longitudinal tire forces, no longitudinal dynamics)."""

    summary = "the TCT baseline: lateral and yaw dynamics only"
    model_id = _ro.MODEL_TCT
    name = "tct"


# the offset-free disturbance by default (MPCSettings.offset_free = None): on where it does
# not hurt the nominal case. Measured (docs/CONTROLLER.md): the kinematic model's prediction
# error is its missing velocity dynamics (the twist follows the command at once), not a
# constant: the disturbance chases the lag and tracks worse with the right tires.
OFFSET_FREE_DEFAULT = {"mf": True, "dugoff": True, "tct": True, "kinematic": False}
ADAPTABLE = ("mf", "dugoff", "tct")  # the models whose tires --adapt scales (adaptation.py)

MODELS = {"mf": MagicFormulaModel, "dugoff": DugoffModel, "kinematic": KinematicModel,
          "tct": TCTModel}


def make_model(vehicle: Vehicle, settings: MPCSettings) -> PredictionModel:
    return MODELS[settings.model](vehicle, settings)
