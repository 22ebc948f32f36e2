"""A real-time gradient NMPC: the MPC's horizon problem by acados SQP-RTI.

:class:`Acados` (``--solver acados``) solves the *same* horizon problem as the annealer and
IPOPT (:class:`controller.horizon.Horizon`) - the offsets ``z`` of the move blocks inside their box,
pushed through the feed-forward policy and the MF prediction, with the cost of eq. 22-26
plus ``R`` - by one Gauss-Newton SQP iteration per control period (real-time iteration,
RTI) of acados (code-generated, compiled C; its QPs by HPIPM).

The same problem as an optimal control problem
----------------------------------------------
acados wants stages: a state, a control and a dynamics ``x_{k+1} = f(x_k, u_k, p_k)`` per
prediction step. The offsets become part of the state, so the move blocking and every term
of the cost carry over exactly:

* state ``s_k = (x, y, phi, vx, vy, r, delta_1..n, zc_1..2n)``: the prediction state of
  :mod:`plant.layout` (``X0_*``) and ``zc``, the offsets in force before step ``k``
  (``zc_0`` = the previous solution's first block, the smoothing term's anchor);
* control ``u_k = dz``: the change of the offsets at step ``k``; it is free at the first
  step of each block and fixed to 0 (``lbu = ubu = 0``) inside a block, so the offsets of
  block ``b`` are ``z_b = zc`` after its first step, and ``u`` at the block's first step is
  ``z_b - z_{b-1}``;
* dynamics (discrete): ``zc' = zc + u``, then one step of the MF prediction with offsets
  ``zc'`` and the reference row ``p_k`` (:func:`controller.mirrors.casadi_rollout.symbolic_step`,
  the mirror IPOPT uses: the same graph, pinned to the numba kernels by tests/test_ipopt.py);
* cost, nonlinear least squares ``sum_k |y_k|^2_W_k``: the pose error of ``s_k`` against
  ``p_k`` (weights ``Q / N_p``, none at ``k = 0``, whose pose is given), the step's wear
  powers in kW (``L / N_p``; the linear weights ``E`` of 'two-energy' as the square of
  ``sqrt(P)``), ``u`` (the smoothing ``R_dw, R_dd``: nonzero only at block starts) and
  ``zc + u`` at block starts (the ridge ``R_ow, R_od``, once per block); at the terminal
  stage the pose error against row ``N_p``;
* bounds: the offset box on ``zc`` at stages 1..N_p (so on every block's offsets).

This is the single-shooting problem of the annealer lifted to multiple shooting: at a
dynamically consistent point the two have the same cost up to the smoothing of |.|
(DEVIATION(eq. 13-15), as for IPOPT: ``sqrt(p^2 + eps_w^2)``, default 1 W) and the same
minimisers. The heading wrap and the policy's clips stay exact, as for IPOPT.

One solve (RTI)
---------------
1. The warm start: the better (exact cost) of the shifted previous solution and zero
   offsets, as IPOPT's.
2. Its state trajectory by the symbolic prediction (a CasADi function), so the
   linearisation point is the warm start itself (dynamically consistent: the first
   Gauss-Newton step of multiple shooting is then the one of single shooting).
3. One SQP iteration: linearise (the compiled Jacobians), one QP (HPIPM); the new offsets
   are read from ``zc`` at each block's first step.
4. A line search on the exact cost: the step ``d`` from the warm start is tried at
   ``1, 1/2, ..., 1/128`` in one 8-candidate tile of the annealer's own prediction and
   cost (numba, true |.|), the best kept; with ``keep_best`` (default) the warm start is
   returned when no step size improves on it. ``Command.cost`` is the exact cost.

``AcadosOptions.iterations`` > 1 repeats 2-4 from the new point (SQP with that many
iterations); 1 is RTI.

The dependency
--------------
acados comes from the registry's ``comma-deps-acados`` (acados' libraries, its
``acados_template`` Python interface, its template renderer, and a slim CasADi 3.6.7
without IPOPT under the same import name ``casadi`` as the ``ipopt`` extra's). Installed
into the environment's site-packages it would replace the ``ipopt`` extra's CasADi, so it
is installed apart (``make test`` does this):

    pip install --no-deps --target .venv/acados comma-deps-acados

and found at ``$MSAGV_ACADOS`` or ``<sys.prefix>/acados`` (else as an ordinary import).
Only its ``acados`` package is imported from there; its code generation uses the
environment's CasADi (3.8.2 from the ``ipopt`` extra, which acados' template warns is newer
than the versions it lists; the generated C is plain CasADi C). Generating and compiling a
solver takes seconds (2 axles) to minutes (8 axles): solvers are cached by their
configuration under ``$MSAGV_ACADOS_CACHE``, else ``$XDG_CACHE_HOME/msagv/acados``, else
``~/.cache/msagv/acados``. A C compiler and ``make`` are needed for the first build.
"""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import fcntl
import hashlib
import importlib.util
import json
import math
import os
import subprocess
import sys
import tempfile
import weakref
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from msagv.plant import layout as lay

from . import adaptation as _ad
from . import rollout as _ro
from .cost_terms import pose_error, wear_kw
from .mirrors.casadi_rollout import ca, symbolic_step
from .horizon import Horizon, Solution
from .interface import ControllerError
from .models import MPCSettings

ACADOS_ENV = "MSAGV_ACADOS"  # the directory of an isolated install (pip install --target)
CACHE_ENV = "MSAGV_ACADOS_CACHE"
N_PARAM = lay.N_REF + 3  # a stage's parameters: the reference row, the disturbance
# (+ adaptation.N_TIRE with --adapt: the tires the online adaptation moves)
FORMULATION = 4  # bump when the generated problem changes (part of the cache key)
RUNTIME_OPTIONS = ("iterations", "keep_best", "line_search")  # not in the generated code
LINE_SEARCH = tuple(0.5 ** i for i in range(_ro.LANES))  # step sizes, one SIMD tile
INSTALL_HINT = ("pip install --no-deps --target .venv/acados comma-deps-acados (make test "
                "does this), or use --solver sa")

_acados = None  # the imported acados package, once found
_acados_error: str | None = None


def _import_acados():
    """Import acados' Python package (see the module docstring): the module, or raise
    :class:`ControllerError` saying what is missing."""
    global _acados, _acados_error
    if _acados is not None:
        return _acados
    if _acados_error is not None:
        raise ControllerError(_acados_error)
    places = [os.environ.get(ACADOS_ENV), os.path.join(sys.prefix, "acados")]
    mod = None
    for d in places:
        if d and os.path.isfile(os.path.join(d, "acados", "__init__.py")):
            pkg = os.path.join(d, "acados")
            spec = importlib.util.spec_from_file_location(
                "acados", os.path.join(pkg, "__init__.py"), submodule_search_locations=[pkg])
            mod = importlib.util.module_from_spec(spec)
            sys.modules["acados"] = mod
            try:
                spec.loader.exec_module(mod)
            except Exception:  # pragma: no cover - a broken install
                sys.modules.pop("acados", None)
                mod = None
                continue
            break
    if mod is None:
        try:
            import acados as mod  # type: ignore[no-redef]
        except ImportError:
            mod = None
    if mod is None or not hasattr(mod, "LIB_DIR"):
        _acados_error = (f"the acados solver needs acados (the registry's comma-deps-acados), "
                         f"which is not installed: {INSTALL_HINT}")
        raise ControllerError(_acados_error)
    os.environ.setdefault("ACADOS_SOURCE_DIR", mod.DIR)
    os.environ.setdefault("ACADOS_PYTHON_INTERFACE_PATH", mod.TEMPLATE_DIR)
    os.environ.setdefault("TERA_PATH", mod.TERA_PATH)
    # the solver libraries link libacados, libhpipm, libblasfeo (and libacados needs
    # qpOASES_e by its versioned name): load them globally, by path, before any solver
    for name in ("libblasfeo.so", "libhpipm.so", "libqpOASES_e.so.3.1", "libqpOASES_e.so",
                 "libacados.so"):
        p = os.path.join(mod.LIB_DIR, name)
        if os.path.isfile(p):
            ctypes.CDLL(p, mode=ctypes.RTLD_GLOBAL)
    _acados = mod
    return mod


def require_acados() -> None:
    """Raise :class:`ControllerError` unless CasADi and acados can be imported."""
    if ca is None:
        raise ControllerError("the acados solver needs CasADi, which is not installed "
                              "(pip install 'msagv[ipopt]'), or use --solver sa")
    _import_acados()


@dataclass(frozen=True)
class AcadosOptions:
    """Options of the acados backend (the horizon problem itself comes from MPCSettings).

    eps_w: smoothing of |.| in the wear powers eq. (13)-(15) [W], > 0 (as IPOPT's; > 0 also
      because the linear wear weights enter as the square of ``sqrt(P)``).
    iterations: SQP iterations per solve (1: real-time iteration).
    keep_best: return the warm start if no step improves its *exact* cost.
    line_search: try the step at 1, 1/2, ..., 1/128 on the exact cost (one SIMD tile) and
      keep the best; off: the full step only.
    levenberg: Levenberg-Marquardt term added to the Gauss-Newton Hessian.
    qp_solver: acados' QP solver ('PARTIAL_CONDENSING_HPIPM', 'FULL_CONDENSING_HPIPM',
      'FULL_CONDENSING_QPOASES').
    qp_iter_max: the QP solver's iteration limit.
    hpipm_mode: HPIPM's mode; 'SPEED_ABS' (default) took 3-4 interior-point iterations per
      QP here, 'BALANCE' (acados' default) 4 and 1.3x the time at 2 axles.
    cond_N: partial condensing's horizon (None: N_p, no condensing; 2 and 5 were 1.2-1.9x
      slower at 8 axles, full condensing 3.5x: the u of every stage is 4n wide).
    compile_flags: the C compiler's flags for the generated functions ('-O3 -march=native'
      was no faster than '-O2').
    """

    eps_w: float = 1.0
    iterations: int = 1
    keep_best: bool = True
    line_search: bool = True
    levenberg: float = 0.0
    qp_solver: str = "PARTIAL_CONDENSING_HPIPM"
    qp_iter_max: int = 50
    hpipm_mode: str = "SPEED_ABS"
    cond_N: int | None = None
    compile_flags: str = "-O2"

    def __post_init__(self):
        if not (self.eps_w > 0 and math.isfinite(self.eps_w)):
            raise ValueError(f"AcadosOptions.eps_w: must be > 0, got {self.eps_w}")
        if self.iterations < 1:
            raise ValueError(f"AcadosOptions.iterations: must be >= 1, got {self.iterations}")
        if not (self.levenberg >= 0 and math.isfinite(self.levenberg)):
            raise ValueError(f"AcadosOptions.levenberg: must be >= 0, got {self.levenberg}")
        if self.qp_solver not in ("PARTIAL_CONDENSING_HPIPM", "FULL_CONDENSING_HPIPM",
                                  "FULL_CONDENSING_QPOASES"):
            raise ValueError(f"AcadosOptions.qp_solver: unknown {self.qp_solver!r}")
        if self.qp_iter_max < 1:
            raise ValueError(f"AcadosOptions.qp_iter_max: must be >= 1, got {self.qp_iter_max}")


def cache_dir() -> Path:
    d = os.environ.get(CACHE_ENV)
    if d:
        return Path(d)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "msagv" / "acados"


@contextlib.contextmanager
def _stdout_to(log):
    """Send file descriptor 1 (acados' prints and its make) to ``log`` meanwhile: the
    command line prints its JSON document on stdout."""
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(log.fileno(), 1)
    try:
        with contextlib.redirect_stdout(log):  # and Python's, if sys.stdout is not fd 1
            yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


_LIVE: "weakref.WeakSet[HorizonOCP]" = weakref.WeakSet()


@atexit.register
def _free_solvers() -> None:
    """Free every acados solver while the interpreter is still whole: left to the garbage
    collector at teardown, acados' own ``AcadosOcpSolver.__del__`` finds ctypes half gone
    and prints ``TypeError: item 1 in _argtypes_ has no from_param method``."""
    for ocp in list(_LIVE):
        ocp.solver = None


class HorizonOCP:
    """The horizon problem of one MPC configuration as an acados OCP (see the module
    docstring), generated and compiled once per configuration (cached on disk), with
    direct ctypes setters for the per-solve data."""

    def __init__(self, model, settings: MPCSettings, options: AcadosOptions = AcadosOptions()):
        Acados.check_supported(settings)
        acados = _import_acados()
        self.settings, self.options = settings, options
        nw = model.n_wheels
        self.nw, self.nz = nw, 2 * nw
        self.nx6 = lay.x0_size(nw)  # the prediction state
        self.nx = self.nx6 + self.nz + 3  # + the last step's wear powers [kW]
        self.nu = self.nz
        self.N = settings.N_p
        self.starts = [int(k) for k in np.cumsum((0,) + settings.blocks[:-1])]  # blocks' first steps
        self.linear = any(v > 0 for v in settings.effective_L[3:])
        self.adapt = bool(settings.adapt)  # the adapted tires: stage parameters
        self.n_param = N_PARAM + (_ad.N_TIRE if self.adapt else 0)
        s, u, p, f, y, ye = self._export_model(model)
        self.ny = int(y.shape[0])
        self._weights(settings)
        lower, upper, _ = model.box()
        self.box_lo, self.box_hi = lower[:self.nu].copy(), upper[:self.nu].copy()
        key = self._key(model, settings, options, acados)
        ocp = self._ocp(f"msagv_{key[:16]}", s, u, p, f, y, ye)
        self.traj_fn = self._trajectory_function(model, s, u, p, f)
        self._build(ocp, cache_dir() / key)
        self._set_constant_data()

    # ---- the model, the OCP, the build (acados' examples: export the model, set up the
    # ---- OCP from it, cache the generated solver apart) ----
    def _export_model(self, model):
        """The symbolic stage: state ``s``, control ``u``, parameter ``p`` (the reference
        row), discrete dynamics ``f`` and the least-squares residuals ``y`` (stages) and
        ``ye`` (terminal), from the prediction's mirror (module docstring)."""
        nx6, nu = self.nx6, self.nu
        s = ca.SX.sym("s", self.nx)
        u = ca.SX.sym("u", nu)
        p = ca.SX.sym("p", self.n_param)  # the reference row, the offset-free disturbance
        # (, the adapted tires)
        P, S = model.P, model.S
        if self.adapt:
            P, S = _ad.symbolic(P, S, [p[N_PARAM + i] for i in range(_ad.N_TIRE)])
        zc = s[nx6:nx6 + nu]
        wp = s[nx6 + nu:]
        znew = zc + u
        X = [None] * 3
        X[lay.POSE_X], X[lay.POSE_Y], X[lay.POSE_PHI] = s[lay.X0_X], s[lay.X0_Y], s[lay.X0_PHI]
        V = [s[lay.X0_VX], s[lay.X0_VY], s[lay.X0_R]]
        delta = [s[lay.X0_DELTA + j] for j in range(self.nw)]
        refk = [p[i] for i in range(lay.N_REF)]
        X1, V1, delta1, wear, _ = symbolic_step(X, V, delta, refk, znew, 0, P, S,
                                                model.wx, model.wy, eps=self.options.eps_w,
                                                dist=[p[lay.N_REF + i] for i in range(3)])
        nxt = [None] * nx6
        nxt[lay.X0_X], nxt[lay.X0_Y], nxt[lay.X0_PHI] = X1[lay.POSE_X], X1[lay.POSE_Y], X1[lay.POSE_PHI]
        nxt[lay.X0_VX], nxt[lay.X0_VY], nxt[lay.X0_R] = V1
        for j in range(self.nw):
            nxt[lay.X0_DELTA + j] = delta1[j]
        pw = [None] * 3  # the residuals of controller.cost_terms' terms (module docstring)
        pw[lay.WEAR_S], pw[lay.WEAR_ALPHA], pw[lay.WEAR_T] = wear_kw(
            wear[lay.WEAR_S], wear[lay.WEAR_ALPHA], wear[lay.WEAR_T])
        f = ca.vertcat(*nxt, znew, *pw)
        err = ca.vertcat(*pose_error(s[lay.X0_X], s[lay.X0_Y], s[lay.X0_PHI], p[lay.REF_X],
                                     p[lay.REF_Y], p[lay.REF_PHI]))
        ye = [err, wp] + ([ca.sqrt(wp)] if self.linear else [])
        y = ca.vertcat(*ye, u, znew)
        return s, u, p, f, y, ca.vertcat(*ye)

    def _weights(self, settings: MPCSettings) -> None:
        """``W`` per stage and ``W_e``: J = sum_k |y_k|^2_W (acados: 1/2 |.|^2_W, hence the
        2); stage k weighs the pose reached and the wear of the step before it (none at
        k = 0: given); the smoothing at every step (nonzero only at block starts), the
        ridge once per block."""
        nw, nu, Np = self.nw, self.nu, self.N
        L = settings.effective_L
        Q = np.asarray(settings.Q, float)
        Rr = np.asarray(settings.R, float)
        smooth = np.r_[np.full(nw, Rr[lay.R_DW]), np.full(nw, Rr[lay.R_DD])]
        ridge = np.r_[np.full(nw, Rr[lay.R_OW]), np.full(nw, Rr[lay.R_OD])]
        wq = np.concatenate([Q, np.asarray(L[:3], float)]
                            + ([np.asarray(L[3:], float)] if self.linear else [])) / Np
        self.W = []
        for k in range(Np):
            w = [wq if k > 0 else np.zeros_like(wq), smooth,
                 ridge if k in self.starts else np.zeros(nu)]
            self.W.append(2.0 * np.diag(np.concatenate(w)))
        self.W_e = 2.0 * np.diag(wq)
        self._n_terminal = len(wq)

    def _ocp(self, name: str, s, u, p, f, y, ye):
        """The acados OCP of the exported model: cost, bounds, solver options."""
        from acados.acados_template import AcadosModel, AcadosOcp

        nu, nx6, Np, options = self.nu, self.nx6, self.N, self.options
        am = AcadosModel()
        am.name = name
        am.x, am.u, am.p = s, u, p
        am.disc_dyn_expr = f
        am.cost_y_expr = y
        am.cost_y_expr_e = ye
        ocp = AcadosOcp()
        ocp.model = am
        ocp.dims.N = Np
        # acados scales each stage's cost by its time step: 1, so that the OCP's cost is
        # J (the dynamics are discrete and do not see it)
        ocp.solver_options.tf = float(Np)
        ocp.parameter_values = np.zeros(self.n_param)
        ocp.cost.cost_type = "NONLINEAR_LS"
        ocp.cost.cost_type_e = "NONLINEAR_LS"
        ocp.cost.W = self.W[1]
        ocp.cost.W_e = self.W_e
        ocp.cost.yref = np.zeros(self.ny)
        ocp.cost.yref_e = np.zeros(self._n_terminal)
        self._big = 2.0 * np.maximum(np.abs(self.box_lo), np.abs(self.box_hi))
        ocp.constraints.x0 = np.zeros(self.nx)
        ocp.constraints.idxbu = np.arange(nu)
        ocp.constraints.lbu = -self._big
        ocp.constraints.ubu = self._big
        ocp.constraints.idxbx = np.arange(nx6, nx6 + nu)
        ocp.constraints.lbx = self.box_lo
        ocp.constraints.ubx = self.box_hi
        ocp.constraints.idxbx_e = np.arange(nx6, nx6 + nu)
        ocp.constraints.lbx_e = self.box_lo
        ocp.constraints.ubx_e = self.box_hi
        so = ocp.solver_options
        so.integrator_type = "DISCRETE"
        so.nlp_solver_type = "SQP_RTI"
        so.hessian_approx = "GAUSS_NEWTON"
        so.qp_solver = options.qp_solver
        so.qp_solver_iter_max = options.qp_iter_max
        so.levenberg_marquardt = options.levenberg
        so.print_level = 0
        so.hpipm_mode = options.hpipm_mode
        so.ext_fun_compile_flags = options.compile_flags
        if options.cond_N is not None:
            so.qp_solver_cond_N = options.cond_N
        return ocp

    def _trajectory_function(self, model, s, u, p, f):
        """The state trajectory of a decision vector (the warm start as the linearisation
        point), as a CasADi function compiled to C beside the solver."""
        nu, nx6, Np = self.nu, self.nx6, self.N
        x0 = ca.SX.sym("x0", self.nx)
        ref = ca.SX.sym("ref", Np + 1, lay.N_REF)
        z = ca.SX.sym("z", model.dim)
        dist = ca.SX.sym("dist", 3)
        tires = ca.SX.sym("tires", _ad.N_TIRE if self.adapt else 0)
        Fs = ca.Function("f", [s, u, p], [f])
        traj = [x0]
        cur = x0
        for k in range(Np):
            b = int(model.block[k])
            uk = z[b * nu:(b + 1) * nu] - cur[nx6:nx6 + nu] if k in self.starts \
                else ca.DM.zeros(nu)
            cur = Fs(cur, uk, ca.vertcat(ref[k, :].T, dist, tires))
            traj.append(cur)
        args = [x0, ref, z, dist] + ([tires] if self.adapt else [])
        return ca.Function("msagv_traj", args, [ca.horzcat(*traj)]).expand()

    def _build(self, ocp, d: Path) -> None:
        """Generate and compile the solver and the trajectory into ``d`` once per
        configuration (cached; one build at a time, under a lock), then load them."""
        from acados.acados_template import AcadosOcpSolver

        name = ocp.model.name
        d.mkdir(parents=True, exist_ok=True)
        ocp.code_export_directory = str(d / "c_generated_code")
        json_file = str(d / "ocp.json")
        lib = d / "c_generated_code" / f"libacados_ocp_solver_{name}.so"
        self.build_log = ""
        with open(d / "lock", "w") as lk:
            fcntl.flock(lk, fcntl.LOCK_EX)  # one build per configuration at a time
            fresh = not (lib.is_file() and (d / "ok").is_file())
            with tempfile.TemporaryFile(mode="w+") as log:
                cwd = os.getcwd()
                try:
                    with _stdout_to(log):
                        self.solver = AcadosOcpSolver(ocp, json_file=json_file, build=fresh,
                                                      generate=fresh, verbose=False)
                except Exception as e:
                    log.seek(0)
                    raise ControllerError(f"acados: building the solver failed ({e}); its "
                                          f"output: {log.read()[-2000:]}") from e
                finally:
                    os.chdir(cwd)
                if fresh:
                    self._compile_traj(d, log)
                log.seek(0)
                self.build_log = log.read()
            if fresh:
                (d / "ok").write_text("built\n")
        self.built = fresh
        _LIVE.add(self)
        self.cache = d
        self._bind()
        self._load_traj(d / "libtraj.so")

    def _set_constant_data(self) -> None:
        """What every solve shares: the weights per stage, the controls fixed to 0 inside
        a block, the offset box at stages 1..N."""
        Np, nu = self.N, self.nu
        for k in range(Np):
            self._cost_set(k, "W", self.W[k])
            lim = np.zeros(nu) if k not in self.starts else self._big
            self._con_set(k, "lbu", -lim)
            self._con_set(k, "ubu", lim)
        self._cost_set(Np, "W", self.W_e)
        for k in range(1, Np + 1):
            self._con_set(k, "lbx", self.box_lo)
            self._con_set(k, "ubx", self.box_hi)

    def _compile_traj(self, d: Path, log) -> None:
        cg = ca.CodeGenerator("traj.c", {"with_header": False})
        cg.add(self.traj_fn)
        cg.generate(str(d) + os.sep)
        cc = os.environ.get("CC", "cc")
        r = subprocess.run([cc, "-O2", "-fPIC", "-shared", "-o", str(d / "libtraj.so"),
                            str(d / "traj.c"), "-lm"], capture_output=True, text=True)
        log.write(r.stdout + r.stderr)
        if r.returncode != 0:
            raise ControllerError(f"acados: compiling the trajectory function failed: "
                                  f"{r.stderr[-2000:]}")

    def _load_traj(self, path: Path) -> None:
        """The compiled trajectory function, called through ctypes with work arrays sized
        by CasADi (CasADi's C calling convention: arg, res, iw, w, mem)."""
        lib = ctypes.CDLL(str(path))
        fn = lib.msagv_traj
        P = ctypes.c_void_p
        fn.argtypes = [P, P, P, P, ctypes.c_int]
        fn.restype = ctypes.c_int
        f = self.traj_fn
        self._traj_lib, self._traj = lib, fn
        self._traj_arg = (ctypes.c_void_p * max(f.sz_arg(), 5))()
        self._traj_res = (ctypes.c_void_p * max(f.sz_res(), 1))()
        self._traj_iw = np.zeros(max(f.sz_iw(), 1), dtype=np.int64)
        self._traj_w = np.zeros(max(f.sz_w(), 1))
        self._traj_out = np.zeros((self.N + 1, self.nx))
        self._traj_ref = np.zeros((lay.N_REF, self.N + 1))  # column-major (N + 1, 6)
        self._dist = np.zeros(3)
        self._tires = np.zeros(self.n_param - N_PARAM)
        self._stage_p = np.zeros((self.N + 1, self.n_param))  # per stage: ref row, dist, tires

    def trajectory(self, s0: np.ndarray, ref: np.ndarray, z: np.ndarray,
                   dist: np.ndarray | None = None, tires: np.ndarray | None = None
                   ) -> np.ndarray:
        """``(N + 1, nx)``: the OCP's states along the prediction of ``z`` from ``s0`` (with
        the offset-free disturbance ``dist``, None: zero; with ``--adapt`` the adapted tire
        entries ``tires``, :func:`controller.adaptation.values`)."""
        s0 = np.ascontiguousarray(s0, dtype=float)
        z = np.ascontiguousarray(z, dtype=float)
        self._traj_ref[:] = ref.T
        self._dist[:] = 0.0 if dist is None else dist
        a = self._traj_arg
        a[0], a[1], a[2] = s0.ctypes.data, self._traj_ref.ctypes.data, z.ctypes.data
        a[3] = self._dist.ctypes.data
        if self.adapt:
            if tires is None:
                raise ValueError("acados: --adapt: the trajectory needs the adapted tires")
            self._tires[:] = tires
            a[4] = self._tires.ctypes.data
        self._traj_res[0] = self._traj_out.ctypes.data
        if self._traj(a, self._traj_res, self._traj_iw.ctypes.data, self._traj_w.ctypes.data, 0):
            raise RuntimeError("acados: the trajectory function failed")
        return self._traj_out

    @staticmethod
    def _key(model, settings, options, acados) -> str:
        """The cache key: what the generated code depends on."""
        S = model.S.copy()
        S[[lay.S_DIST_U, lay.S_DIST_V, lay.S_DIST_R]] = 0.0  # a parameter, not in the code
        P = model.P.copy()
        if settings.adapt:  # the adapted tires are parameters, not in the code either
            P[list(_ad.TIRE_P)] = 0.0
            S[list(_ad.TIRE_S)] = 0.0
        cfg = {"formulation": FORMULATION, "P": list(map(float, P)),
               "S": list(map(float, S)), "wx": list(map(float, model.wx)),
               "wy": list(map(float, model.wy)), "block": list(map(int, model.block)),
               # the weights and bounds are set at run time: only the residual's shape
               "linear": any(v > 0 for v in settings.effective_L[3:]),
               "options": {k: v for k, v in asdict(options).items()
                           if k not in RUNTIME_OPTIONS}, "casadi": ca.__version__,
               "acados": getattr(acados, "__file__", ""), "python": sys.version_info[:2]}
        if settings.adapt:  # (only then: the keys of every other configuration stay)
            cfg["adapt"] = [list(_ad.TIRE_P), list(_ad.TIRE_S)]
        return hashlib.sha256(json.dumps(cfg, sort_keys=True, default=str).encode()).hexdigest()

    # ---- direct setters (the Python wrapper re-declares ctypes types on every call) ----
    def _bind(self):
        sv = self.solver
        lib = sv.shared_lib
        P = ctypes.c_void_p
        self._cfg, self._dims = sv.nlp_config, sv.nlp_dims
        self._in, self._out = sv.nlp_in, sv.nlp_out
        self._capsule = sv.capsule
        self._out_set = lib.ocp_nlp_out_set
        self._out_set.argtypes = [P, P, P, ctypes.c_int, ctypes.c_char_p, P]
        self._out_get = lib.ocp_nlp_out_get
        self._out_get.argtypes = [P, P, P, ctypes.c_int, ctypes.c_char_p, P]
        self._cons = lib.ocp_nlp_constraints_model_set
        self._cons.argtypes = [P, P, P, ctypes.c_int, ctypes.c_char_p, P]
        self._costs = lib.ocp_nlp_cost_model_set
        self._costs.argtypes = [P, P, P, ctypes.c_int, ctypes.c_char_p, P]
        name = sv.model_name
        self._params = getattr(lib, f"{name}_acados_update_params")
        self._params.argtypes = [P, ctypes.c_int, ctypes.POINTER(ctypes.c_double), ctypes.c_int]
        self._params.restype = ctypes.c_int
        self._solve = getattr(lib, f"{name}_acados_solve")
        self._solve.argtypes = [P]
        self._solve.restype = ctypes.c_int
        self._xbuf = np.zeros(self.nx)

    def _cost_set(self, k, field, v):
        v = np.ascontiguousarray(v, dtype=float)
        self._costs(self._cfg, self._dims, self._in, k, field.encode(), v.ctypes.data)

    def _con_set(self, k, field, v):
        v = np.ascontiguousarray(v, dtype=float)
        self._cons(self._cfg, self._dims, self._in, k, field.encode(), v.ctypes.data)

    def solve(self, x0, ref, zprev, z_init, dist=None, tires=None):
        """One SQP iteration from ``z_init`` (its state trajectory as the linearisation
        point) with the offset-free disturbance ``dist`` (None: zero) and, with ``--adapt``,
        the adapted tires ``tires``: ``(z, status)``, the new offsets (unclipped) and
        acados' status."""
        Np, nu, nx6 = self.N, self.nu, self.nx6
        s0 = np.empty(self.nx)
        s0[:nx6] = x0
        s0[nx6:nx6 + nu] = zprev
        s0[nx6 + nu:] = 1.0  # the wear slots of stage 0 are not weighed (> 0 for sqrt)
        S = self.trajectory(s0, ref, z_init, dist, tires)
        U = np.zeros((Np, nu))
        zb_prev = zprev
        blocks = z_init.reshape(-1, nu)
        for b, k in enumerate(self.starts):
            U[k] = blocks[b] - zb_prev
            zb_prev = blocks[b]
        ref = np.ascontiguousarray(ref, dtype=float)
        cfg, dims, out = self._cfg, self._dims, self._out
        self._con_set(0, "lbx", s0)
        self._con_set(0, "ubx", s0)
        dp = ctypes.POINTER(ctypes.c_double)
        sp = self._stage_p
        sp[:, :lay.N_REF] = ref
        sp[:, lay.N_REF:N_PARAM] = self._dist
        sp[:, N_PARAM:] = self._tires
        for k in range(Np + 1):
            self._params(self._capsule, k, sp[k].ctypes.data_as(dp), self.n_param)
            self._out_set(cfg, dims, out, k, b"x", S[k].ctypes.data)
            if k < Np:
                self._out_set(cfg, dims, out, k, b"u", U[k].ctypes.data)
        status = int(self._solve(self._capsule))
        z = np.empty(len(self.starts) * nu)
        buf = self._xbuf
        for b, k in enumerate(self.starts):
            self._out_get(cfg, dims, out, k + 1, b"x", buf.ctypes.data)
            z[b * nu:(b + 1) * nu] = buf[nx6:nx6 + nu]
        return z, status


class Acados:
    """acados SQP-RTI as a horizon solver (registered as ``acados`` in
    :mod:`controller.solvers`; see the module docstring for one solve).

    The warm start is the better (by the horizon's cost) of the shifted previous solution
    and zero offsets, as IPOPT's; the reported cost is the horizon's (numba, true |.|) and
    the iterations the SQP iterations run. The annealer fields of the settings are ignored
    (``deadline_ms`` too: one RTI iteration is its own budget). ``options``:
    :class:`AcadosOptions`; the QP status of the last iteration is in ``last_status``.
    """

    name = "acados"

    @classmethod
    def check_supported(cls, settings: MPCSettings) -> None:
        """Raise :class:`ControllerError` unless acados can solve the MPC of ``settings``
        (CasADi and acados installed, the paper's model 'mf', the offsets parametrisation)."""
        if settings.model != "mf":
            raise ControllerError(f"the acados solver supports the prediction model 'mf' only, not "
                                  f"{settings.model!r} (the baselines use the annealer: --solver sa)")
        if settings.policy != "offsets":
            raise ControllerError(f"the acados solver supports the decision parametrisation "
                                  f"'offsets' only, not {settings.policy!r} (use the annealer: "
                                  f"--solver sa)")
        require_acados()

    def __init__(self, horizon: Horizon, options: AcadosOptions | None = None):
        self.horizon = horizon
        self.options = options or AcadosOptions()
        self.ocp = HorizonOCP(horizon.model, horizon.settings, self.options)
        self._alpha = np.asarray(LINE_SEARCH)[:, None]
        self.last_status = 0

    def reset(self) -> None:
        """Nothing carries over between solves (each starts from the warm start)."""
        self.last_status = 0

    def solve(self, x0, R, zprev, warm, t0: float) -> Solution:
        h = self.horizon
        z, J = h.better_start(x0, R, zprev, warm)
        dist = h.model.S[[lay.S_DIST_U, lay.S_DIST_V, lay.S_DIST_R]]  # offset-free
        tires = _ad.values(h.model) if self.ocp.adapt else None  # --adapt's tires
        its = 0
        for _ in range(self.options.iterations):
            its += 1
            try:
                zn, status = self.ocp.solve(x0, R, zprev, z, dist, tires)
            except RuntimeError:  # CasADi's evaluation of the trajectory
                status, zn = -1, z
            self.last_status = status
            if not np.all(np.isfinite(zn)):
                break
            zn = h.clip(zn)
            if self.options.line_search:
                cand = z[None, :] + self._alpha * (zn - z)[None, :]
                c = h.costs(x0, R, cand, zprev)
                i = int(np.argmin(c))
                zn, Jn = cand[i], float(c[i])
            else:
                Jn = h.cost(x0, R, zn, zprev)
            if self.options.keep_best and not (Jn <= J):
                break
            z, J = zn, Jn
        return Solution(z, J, its)
