"""A gradient-based reference solver: the MPC's horizon problem solved by IPOPT (CasADi).

:class:`Ipopt` (``--solver ipopt``) solves the *same* horizon problem as the annealer
(:class:`controller.horizon.Horizon`): the
offsets vector ``z`` (``n_blocks * 4n`` entries, the same box bounds), pushed through the
same policy (:func:`controller.rollout.commands_from_policy`) and the same MF prediction
(:data:`controller.rollout.EXACT`'s kernels, model 0), with the same cost
(:func:`controller.rollout.batch_cost`, eq. 22-26 plus the regularisation R). The rollout and
cost are written again symbolically (CasADi SX), operation for operation, in the mirror
:mod:`controller.mirrors.casadi_rollout`, so IPOPT gets exact first and second derivatives;
``tests/test_ipopt.py`` checks that the mirror reproduces the numba rollout (the math
library's, ``EXACT``) to 1e-9. This
module builds the NLP from the mirror and solves it (:class:`HorizonNLP`, :class:`Ipopt`).

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
from dataclasses import dataclass

import numpy as np

from msagv.plant import layout as lay

from .mirrors.casadi_rollout import TINY_SQ, TINY_W2, ca, symbolic_cost, symbolic_rollout  # noqa: F401
from . import adaptation as _ad
from .horizon import Horizon, Solution
from .interface import ControllerError
from .models import MPCSettings


def require_casadi() -> None:
    """Raise :class:`ControllerError` unless CasADi (with IPOPT) can be imported."""
    if ca is None:
        raise ControllerError("the ipopt solver needs CasADi, which is not installed "
                              "(pip install 'msagv[ipopt]', or use the annealer: --solver sa)")


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


class HorizonNLP:
    """The horizon problem of one MPC configuration as a CasADi NLP (built once).

    Parameters of a solve: the state ``x0`` (6 + 2n), the reference rows ``ref``
    (N_p + 1, 6), the previous solution's first block ``zprev`` (2 * 2n).
    """

    def __init__(self, model, settings: MPCSettings, options: IpoptOptions = IpoptOptions()):
        Ipopt.check_supported(settings)
        self.settings, self.options = settings, options
        nw = model.n_wheels
        self.nw, self.dim = nw, model.dim
        Np = settings.N_p
        z = ca.SX.sym("z", model.dim)
        x0 = ca.SX.sym("x0", lay.x0_size(nw))
        ref = ca.SX.sym("ref", Np + 1, lay.N_REF)
        zprev = ca.SX.sym("zprev", 2 * nw)
        eps = ca.SX.sym("eps")
        dist = ca.SX.sym("dist", 3)  # the offset-free disturbance (controller.disturbance)
        self.model = model
        # --adapt: the tires the adaptation moves are parameters of each solve, not constants
        self.adapt = bool(settings.adapt)
        tires = ca.SX.sym("tires", _ad.N_TIRE if self.adapt else 0)
        P, S = _ad.symbolic(model.P, model.S, tires) if self.adapt else (model.P, model.S)
        poses, wear, cmds = symbolic_rollout(x0, ref, z, model.block, P, S,
                                             model.wx, model.wy, eps=eps,
                                             dist=[dist[i] for i in range(3)])
        L = settings.effective_L
        J = symbolic_cost(poses, wear, ref, z, zprev, settings.Q, L, settings.R, nw)
        p = ca.vertcat(x0, ca.vec(ref), zprev, eps, dist, tires)
        self.rollout_fn = ca.Function(
            "rollout", [x0, ref, z, eps, dist, tires],
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
        """The NLP's parameters: the state, the reference rows, the previous first block,
        the |.| smoothing, the model's current offset-free disturbance and (``--adapt``) its
        current tires."""
        e = self.options.eps_w if eps is None else eps
        return np.r_[np.asarray(x0, float), np.asarray(ref, float).reshape(-1, order="F"),
                     np.asarray(zprev, float), e, self.disturbance(), self.tires()]

    def tires(self) -> np.ndarray:
        """The adapted tire entries the prediction carries now (empty without ``--adapt``)."""
        return _ad.values(self.model) if self.adapt else np.zeros(0)

    def disturbance(self) -> np.ndarray:
        """The offset-free disturbance the prediction carries now (the model's ``S``)."""
        return self.model.S[[lay.S_DIST_U, lay.S_DIST_V, lay.S_DIST_R]].copy()

    def solve(self, x0, ref, zprev, z_init, lower, upper):
        """``(z, stats)``: IPOPT's answer from ``z_init`` inside [lower, upper] (its last
        iterate if it stopped early; see ``stats['return_status']``)."""
        r = self.solver(x0=z_init, p=self.params(x0, ref, zprev), lbx=lower, ubx=upper)
        st = self.solver.stats()
        return np.asarray(r["x"]).reshape(-1), st


class Ipopt:
    """IPOPT as a horizon solver (registered as ``ipopt`` in :mod:`controller.solvers`).

    Each solve starts from the better (by the horizon's cost) of the shifted previous
    solution and zero offsets (the annealer's chains 0 and 1); with ``options.keep_best``
    a solve that ends worse than that start (or fails) returns the start. The reported cost
    is the horizon's (numba rollout, true |.|) and the iterations IPOPT's. The annealer
    fields of the settings (chains, iterations, sigma_*, t_*, ladder, adapt_*, seed) are
    ignored; ``deadline_ms`` becomes IPOPT's wall-time limit unless
    ``options.max_wall_ms`` is set. ``options``: :class:`IpoptOptions` (smoothing,
    tolerance, Hessian); IPOPT's stats of the last solve are in ``last_stats``.
    """

    name = "ipopt"

    @classmethod
    def check_supported(cls, settings: MPCSettings) -> None:
        """Raise :class:`ControllerError` unless IPOPT can solve the MPC of ``settings``
        (CasADi installed, the paper's prediction model 'mf')."""
        require_casadi()
        if settings.model != "mf":
            raise ControllerError(f"the ipopt solver supports the prediction model 'mf' only, not "
                                  f"{settings.model!r} (the baselines use the annealer: --solver sa)")
        if settings.policy != "offsets":
            raise ControllerError(f"the ipopt solver supports the decision parametrisation "
                                  f"'offsets' only, not {settings.policy!r} (use the annealer: "
                                  f"--solver sa)")

    def __init__(self, horizon: Horizon, options: IpoptOptions | None = None):
        self.horizon = horizon
        self.options = options or IpoptOptions()
        self.nlp = HorizonNLP(horizon.model, horizon.settings, self.options)
        self.last_stats: dict = {}

    def reset(self) -> None:
        """Nothing carries over between solves (IPOPT starts from the warm start)."""
        self.last_stats = {}

    def solve(self, x0, R, zprev, warm, t0: float) -> Solution:
        """One IPOPT solve from the better of the shifted previous solution and zero
        offsets: ``(z, cost, IPOPT iterations)``; IPOPT's stats in ``last_stats``."""
        h = self.horizon
        warm, Jw = h.better_start(x0, R, zprev, warm)
        try:
            z, st = self.nlp.solve(x0, R, zprev, warm, h.lower, h.upper)
        except RuntimeError as e:  # CasADi raises on evaluation errors it cannot recover
            z, st = warm.copy(), {"return_status": f"error: {e}", "iter_count": 0,
                                  "success": False}
        if not np.all(np.isfinite(z)):
            z = warm.copy()
        z = h.clip(z)
        J = h.cost(x0, R, z, zprev)
        if self.options.keep_best and not (J <= Jw):
            z, J = warm, Jw
        self.last_stats = st
        return Solution(z, J, int(st.get("iter_count", 0)))
