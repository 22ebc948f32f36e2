"""The MPC's simulated annealing, compiled: the whole solver loop runs in numba.

The algorithm (docs/CONTROLLER.md, "Simulated annealing", says what each choice bought):

* **Chains**: Metropolis chains; chain 0 starts at the warm start, chain 1 at zero offsets
  (the pure feed-forward), the rest at the warm start plus a Gaussian spread.
* **One batch per iteration**: each iteration proposes ``proposals`` moves per chain (the
  MPC fills its tile: ``LANES // chains`` each, at least one), predicts and
  costs all of them (the prediction's ``evaluate``: :mod:`controller.rollout`'s tiles of
  ``LANES`` chains, rollout and cost fused, SIMD across the chains of a tile), then applies
  the Metropolis test to each chain's best proposal (with more than one proposal a chain
  takes the best of several steps of the same scale, as a (1+K) evolution strategy).
* **Proposals**: Gaussian steps with a per-coordinate scale ``sigma``, times a per-chain
  factor, shrinking geometrically to ``sigma_final`` of their start over the budget, and
  clipped to the box. The per-chain factors start on a geometric ladder from ``ladder``
  to 1 and adapt: x ``adapt_up`` after an accepted move, x ``adapt_down`` after a rejected
  one, kept within [SCALE_MIN, SCALE_MAX].
* **Acceptance**: Metropolis, ``exp(-(J' - J) / T)`` with a temperature relative to the
  best cost so far, ``T_i = J_best * t_start (t_end / t_start)^(i / (I - 1))``.
* **Exploitation**: every ``restart_every`` iterations the worst quarter of the chains
  (at least one) restarts from the best point found.
* **Budgets**: a fixed iteration count runs in one kernel call (deterministic: same seed,
  same result); with a wall-clock deadline the kernel is called in chunks of up to
  ``CHUNK`` iterations, sized from the time per iteration measured so far, the clock read
  between chunks, and the cooling follows the elapsed fraction of the deadline.
* **Seeding**: every random number of a solve is drawn up front from the
  ``numpy.random.Generator`` passed in: the acceptance uniforms, and an offset into a pool
  of standard normals drawn once per annealer (:func:`draw_noise`), whose window are the
  proposals' normals.

``tests/annealer_reference.py`` is the same algorithm written plainly for any batch cost
function; ``tests/test_controller.py`` checks that this kernel returns what it returns on
the MPC's cost for the same seed (the same random draws).

Two variants: serial (default; predictable when other processes share the cores) and
``parallel`` (the tiles of an iteration spread over numba's threads with ``prange``). A
chain's cost does not depend on which tile, lane or thread evaluates it, so both give
identical results for any thread count (``tests/test_rollout_simd.py``); threads help only
when there is more than one tile, i.e. more than ``LANES`` chains.
"""

from __future__ import annotations

import math
import time
import types
from dataclasses import dataclass

import numpy as np
from numba import njit

import msagv.plant.tire as _tire
from msagv.plant import layout as lay
from msagv.plant import model_params as _mp

from . import approx as _approx
from . import cost_terms as _cost
from . import rollout as _ro
from .cost_terms import KW, pose_error

CHUNK = 16  # iterations per kernel call under a deadline (the clock is read between calls)
SCALE_MIN, SCALE_MAX = 1e-4, 10.0  # bounds of the adaptive per-chain step factors

# stale-cache guard (plant.layout): the layout and the kernels compiled into these
_STAMP = lay.kernel_stamp(_ro.__file__, _mp.__file__, _tire.__file__, _approx.__file__,
                          _cost.__file__)


@njit(cache=True)
def _layout_stamp():
    return _STAMP


lay.drop_stale_cache(_layout_stamp, _STAMP, __file__)


POOL = 1 << 18  # standard normals drawn once per annealer (2 MiB)


def noise_pool(seed: int) -> np.ndarray:
    """The annealer's pool of standard normals, drawn once (``seed``)."""
    return np.random.default_rng(seed).standard_normal(POOL)


def draw_noise(rng: np.random.Generator, pool: np.ndarray | None, iterations: int, chains: int,
               dim: int) -> tuple[np.ndarray, np.ndarray]:
    """The random numbers of one solve: ``(noise, unif)``, the proposals' standard normals
    (iterations + 1, chains, dim) and the acceptance tests' uniforms (iterations, chains).
    The normals are a window of ``pool`` at an offset drawn from ``rng`` (drawing ten
    thousands of fresh normals cost 0.1-0.3 ms per solve, a quarter of a 2-axle solve);
    without a pool, or when the window would not fit in it, fresh draws. Either way a
    solve takes a fixed number of draws from ``rng``, so a solve cut short by a deadline
    does not shift the next solve's numbers."""
    n = (iterations + 1) * chains * dim
    if pool is not None and n <= pool.shape[0]:
        off = int(rng.integers(0, pool.shape[0] - n + 1))
        noise = pool[off:off + n].reshape(iterations + 1, chains, dim)
    else:
        noise = rng.standard_normal((iterations + 1, chains, dim))
    return noise, rng.random((iterations, chains))


@dataclass
class AnnealResult:
    x: np.ndarray  # best point (D,)
    cost: float  # its cost
    iterations: int  # iterations run
    evaluations: int  # candidate evaluations (incl. the initial ones)
    accepted: float  # fraction of proposals accepted
    polish_steps: int = 0  # Gauss-Newton steps taken after the annealing (CompiledAnnealer.polish)


def ladder_factors(chains: int, ladder: float) -> np.ndarray:
    """Initial per-chain step factors: geometric from ``ladder`` (chain 0) to 1."""
    if not 0.0 < ladder <= 1.0:
        raise ValueError(f"anneal: ladder must be in (0, 1], got {ladder}")
    return np.geomspace(ladder, 1.0, chains) if chains > 1 else np.ones(1)


def _iterate(model, x0, ref, block, P, S, wx, wy, Q, L, R, nsplit, zprev, X, J, Xp, Jp, best_x,
             best, scale, noise, unif, it0, fracs, sigma, lower, upper, log_sf, t_start, log_tr,
             restart_every, n_restart, iterations, up, down, ws):
    """Iterations ``it0 .. it0 + len(fracs) - 1`` of the annealing (module docstring;
    ``fracs``: the schedule's progress fraction of each). ``best`` = [best_J, accepted
    count] is updated in place, as are X, J, best_x and the per-chain step factors
    ``scale``. ``evaluate`` is a global bound by :func:`_make_iterate`."""
    C, D = X.shape
    K = Xp.shape[0] // C  # proposals per chain
    for i in range(fracs.shape[0]):
        it = it0 + i
        frac = fracs[i]
        sf = math.exp(log_sf * frac)
        for c in range(C):
            for q in range(K):
                p = c * K + q
                for d in range(D):
                    v = X[c, d] + sigma[d] * sf * scale[c] * noise[it + 1, p, d]
                    Xp[p, d] = min(max(v, lower[d]), upper[d])
        evaluate(model, x0, ref, Xp, block, P, S, wx, wy, Q, L, R, nsplit, zprev, ws, Jp)  # noqa: F821
        temp = max(best[0], 1e-12) * t_start * math.exp(log_tr * frac)
        for c in range(C):
            pb = c * K  # the chain's best proposal (the first of equals)
            for q in range(1, K):
                if Jp[c * K + q] < Jp[pb]:
                    pb = c * K + q
            dJ = Jp[pb] - J[c]
            if dJ <= 0.0 or unif[it, c] < math.exp(-max(dJ, 0.0) / temp):
                best[1] += 1.0
                for d in range(D):
                    X[c, d] = Xp[pb, d]
                J[c] = Jp[pb]
                scale[c] = min(max(scale[c] * up, SCALE_MIN), SCALE_MAX)
            else:
                scale[c] = min(max(scale[c] * down, SCALE_MIN), SCALE_MAX)
        ib = 0
        for c in range(1, C):
            if J[c] < J[ib]:
                ib = c
        if J[ib] < best[0]:
            best[0] = J[ib]
            for d in range(D):
                best_x[d] = X[ib, d]
        if restart_every > 0 and (it + 1) % restart_every == 0 and it + 1 < iterations:
            order = np.argsort(J, kind="mergesort")
            for q in range(C - n_restart, C):
                w = order[q]
                for d in range(D):
                    X[w, d] = best_x[d]
                J[w] = best[0]


def _make_iterate(evaluate, name: str):
    """:func:`_iterate` compiled with ``evaluate`` as its global ``evaluate``.

    Not a closure: numba keys a closure's cache entry by a pickle of the captured
    dispatcher, which differs in every process, so a closure over ``evaluate`` missed the
    cache and compiled again in every run (several seconds of every ``msagv run``'s
    start, and a new cache file each time). A function whose ``evaluate`` is a global is
    cached like any other; its own name keeps the two variants' cache files apart."""
    g = dict(globals(), evaluate=evaluate)
    f = types.FunctionType(_iterate.__code__, g, name, _iterate.__defaults__)
    f.__qualname__ = name
    f.__doc__ = _iterate.__doc__
    f.__module__ = __name__
    return njit(cache=True, error_model="numpy")(f)


ITERATE = {(pred.name, kind, parallel): _make_iterate(
    pred.kernels[kind]["evaluate_parallel" if parallel else "evaluate_serial"],
    f"iterate_{'parallel' if parallel else 'serial'}_{kind}_{pred.name}")
    for pred in (_ro.FAST, _ro.EXACT) for kind in _ro.KINDS for parallel in (False, True)}


# ---- the Gauss-Newton polish of the annealer's best point ------------------------------
# The horizon cost is a sum of squares (the pose errors, the quadratic wear term's powers),
# a linear part (the wear-energy term) and a quadratic form of the decision vector (the
# smoothing and the ridge): J(z) = |r(z)|^2 + e(z) + z'Az + b'z + c. The polish takes the
# residuals' Jacobian Jr (stored by residual, JrT) by forward differences once (D perturbed
# candidates: D / LANES tiles of the SIMD prediction, each started at its variables' block's
# first step from the saved nominal rollout: rollout.rollout_from), then steps: the
# Gauss-Newton model's gradient g = 2 Jr'r + grad e + 2Az + b and Hessian H = 2 Jr'Jr + 2A, the Levenberg-Marquardt
# steps (H + mu diag H) dz = -g for the damping factors GN_MUS (by Cholesky, or through
# the M residuals by Woodbury's identity when D > GN_LOWRANK M: lowrank_step), each at the
# lengths GN_ALPHAS: clipped to the box, these LANES candidates are one tile; the best is kept if
# it lowers the cost, and the Jacobian follows the step by Broyden's rank-one update
# (Jr += (r' - r - Jr dz) dz' / dz'dz, the same for grad e) instead of new differences.
# When a step stalls (gains less than GN_TOL of the cost) with an updated Jacobian, the
# differences are taken again (GN_REFRESH times at most); with a fresh one, it stops.
# docs/PERFORMANCE.md has what each choice bought.
# Its linear algebra is IEEE arithmetic (no fastmath flags): with numba's full fastmath LLVM
# vectorised these sums differently when a kernel was compiled in the process than when it
# was loaded from numba's cache (a process loading the cache and one that compiled
# disagreed at step 0 by 4e-14 rad/s; tests/test_polish.py checks it), and even
# "contract" alone leaves where a multiply is fused to the code around each copy of a
# function (controller.approx's docstring; tests/test_determinism.py).
GN_MUS = np.array([1e-2, 0.1, 1.0, 10.0])  # damping factors
GN_ALPHAS = np.array([1.0, 0.3])  # step lengths of each damped step
GN_TOL = 1e-4  # a step that lowers the cost by less than this fraction of it has stalled
GN_REFRESH = 1  # after a stall, fresh differences this many times at most (then stop)
GN_STEP = 1e-4  # forward-difference steps: this times sigma / max(sigma) (1e-4 rad/s, 7e-6 rad)
GN_CANDIDATES = GN_MUS.shape[0] * GN_ALPHAS.shape[0]  # one tile


@njit(cache=True, error_model="numpy")
def quadratic_terms(stride, nsplit, R, zprev, A, b):
    """The smoothing and ridge terms of the cost (:func:`controller.rollout.smoothing_cost`,
    :func:`~controller.rollout.ridge_cost`) as ``z'Az + b'z + c``: fills ``A`` (D, D)
    and ``b`` (D,), returns ``c``."""
    D = A.shape[0]
    A[:] = 0.0
    b[:] = 0.0
    c = 0.0
    for i in range(D):
        blk, j = divmod(i, stride)
        w = R[lay.R_DW] if j < nsplit else R[lay.R_DD]
        A[i, i] += (R[lay.R_OW] if j < nsplit else R[lay.R_OD]) + w
        if blk == 0:
            b[i] -= 2.0 * w * zprev[j]
            c += w * zprev[j] * zprev[j]
        else:
            p = i - stride
            A[p, p] += w
            A[i, p] -= w
            A[p, i] -= w
    return c


@njit(cache=True, error_model="numpy")
def residuals(poses, wear, ref, Q, Lw, row, r, rrow):
    """The cost's squared terms of candidate ``row`` as residuals ``r[rrow]`` (6 N_p: per
    step the weighted pose errors (:func:`controller.cost_terms.pose_error`), then the
    weighted wear powers [kW]) and its linear wear-energy term, returned: ``|r|^2 + e`` is
    the horizon part of :func:`controller.cost_terms.candidate_cost` (the least-squares
    form of :func:`~controller.cost_terms.tracking_cost` and
    :func:`~controller.cost_terms.wear_cost`; ``tests/test_polish.py`` checks the sum)."""
    Np = poses.shape[1]
    sq = (math.sqrt(Q[lay.Q_X] / Np), math.sqrt(Q[lay.Q_Y] / Np), math.sqrt(Q[lay.Q_PHI] / Np))
    sl = (math.sqrt(Lw[lay.L_S] / Np) * KW, math.sqrt(Lw[lay.L_ALPHA] / Np) * KW,
          math.sqrt(Lw[lay.L_T] / Np) * KW)
    e = 0.0
    for k in range(Np):
        o = 6 * k
        ex, ey, ephi = pose_error(poses[row, k, lay.POSE_X], poses[row, k, lay.POSE_Y],
                                  poses[row, k, lay.POSE_PHI], ref[k + 1, lay.REF_X],
                                  ref[k + 1, lay.REF_Y], ref[k + 1, lay.REF_PHI])
        r[rrow, o] = sq[0] * ex
        r[rrow, o + 1] = sq[1] * ey
        r[rrow, o + 2] = sq[2] * ephi
        ps = wear[row, k, lay.WEAR_S]
        pa = wear[row, k, lay.WEAR_ALPHA]
        pt = wear[row, k, lay.WEAR_T]
        r[rrow, o + 3] = sl[0] * ps
        r[rrow, o + 4] = sl[1] * pa
        r[rrow, o + 5] = sl[2] * pt
        e += Lw[lay.LE_S] * ps + Lw[lay.LE_ALPHA] * pa + Lw[lay.LE_T] * pt
    return e * KW / Np


# The polish's linear algebra is written so that LLVM vectorises it without reassociating
# a sum (IEEE, see below): the inner loops are updates y += a x over rows (views indexed
# from 0: a loop over range(lo, hi) kept numba's index checks and stayed scalar), never
# running dot products, whose single chain of dependent additions cannot be split without
# changing the result; the Jacobian is stored by residual (JrT (M, D)) so that its rows
# are those of the products. Measured at 8 axles (D = 96): the factorisation 82 -> 40 us,
# the Hessian 143 -> 60 us, then by eight pivots (residuals) a pass (_axpy8) the damped
# step 42 -> 31 us, the Hessian 52 -> 41 us (python -m msagv.benchmarks.polish_bench,
# "linear_algebra"; docs/PERFORMANCE.md, issue 31; each on a loaded machine).
@njit(cache=True, inline="always", error_model="numpy")
def _axpy(y, x, a):
    """``y += a x`` (views of equal length)."""
    for j in range(y.shape[0]):
        y[j] += a * x[j]


@njit(cache=True, inline="always", error_model="numpy")
def _axpy8(y, X, r, c, a):
    """``y += a[0] X[r, c:] + ... + a[7] X[r + 7, c:]``, the eight terms added to each
    element in that order (so the same sums as eight :func:`_axpy` calls, with one pass
    over ``y`` instead of eight: the loop is bound by its loads and stores). The rows
    are taken here, not passed as a 2-d view: a view's rows lose numba's contiguous
    layout, and the loop stayed scalar."""
    x0, x1, x2, x3 = X[r, c:], X[r + 1, c:], X[r + 2, c:], X[r + 3, c:]
    x4, x5, x6, x7 = X[r + 4, c:], X[r + 5, c:], X[r + 6, c:], X[r + 7, c:]
    a0, a1, a2, a3, a4, a5, a6, a7 = a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7]
    for j in range(y.shape[0]):
        v = y[j]
        v += a0 * x0[j]
        v += a1 * x1[j]
        v += a2 * x2[j]
        v += a3 * x3[j]
        v += a4 * x4[j]
        v += a5 * x5[j]
        v += a6 * x6[j]
        v += a7 * x7[j]
        y[j] = v


@njit(cache=True, inline="always", error_model="numpy")
def _dot(x, y):
    """``x . y`` in index order."""
    t = 0.0
    for j in range(x.shape[0]):
        t += x[j] * y[j]
    return t


@njit(cache=True, error_model="numpy")
def symmetric_product(A, z, u):
    """``u = A z`` for a symmetric ``A`` (by rows of A: ``sum_j A[j] z_j``)."""
    for i in range(u.shape[0]):
        u[i] = 0.0
    for j in range(z.shape[0]):
        _axpy(u, A[j], z[j])


@njit(cache=True, error_model="numpy")
def quadratic_value(A, b, c, z):
    """``z'Az + b'z + c`` (``A`` symmetric)."""
    D = z.shape[0]
    u = np.empty(D)
    symmetric_product(A, z, u)
    J = c
    for i in range(D):
        J += (b[i] + u[i]) * z[i]
    return J


@njit(cache=True, error_model="numpy")
def gauss_newton_gradient(JrT, r0, ge, A, z, b, g):
    """``g = 2 Jr' r0 + ge + 2 A z + b`` (``JrT`` (M, D): row m, the derivatives of
    residual m by every variable)."""
    D = g.shape[0]
    t = np.zeros(D)
    for m in range(JrT.shape[0]):
        _axpy(t, JrT[m], r0[m])
    u = np.empty(D)
    symmetric_product(A, z, u)
    for i in range(D):
        g[i] = 2.0 * t[i] + ge[i] + 2.0 * u[i] + b[i]


@njit(cache=True, error_model="numpy")
def gauss_newton_hessian(JrT, A, H, full=True):
    """``H = 2 Jr' Jr + 2 A`` (``JrT`` (M, D)): each row's upper part as updates by the
    residuals' rows (eight at a time), then mirrored; ``full=False``: the diagonal alone
    (all that :func:`lowrank_step` reads), the same numbers to the bit."""
    M, D = JrT.shape
    if not full:
        for i in range(D):
            t = 0.0
            for m in range(M):
                t += JrT[m, i] * JrT[m, i]
            H[i, i] = 2.0 * t + 2.0 * A[i, i]
        return
    a = np.empty(8)
    for i in range(D):
        Hi = H[i, i:]
        for j in range(Hi.shape[0]):
            Hi[j] = 0.0
        m0 = 0
        while m0 + 8 <= M:  # eight residuals' rows a pass, in order (_axpy8)
            for q in range(8):
                a[q] = JrT[m0 + q, i]
            _axpy8(Hi, JrT, m0, i, a)
            m0 += 8
        for m in range(m0, M):
            _axpy(Hi, JrT[m, i:], JrT[m, i])
    for i in range(D):
        for j in range(i, D):
            H[i, j] = H[j, i] = 2.0 * H[i, j] + 2.0 * A[i, j]


@njit(cache=True, error_model="numpy")
def broyden_update(JrT, ge, H, dz, dr, de, full=True):
    """Broyden's rank-one update of the Jacobian (``JrT`` (M, D), by residual) and the
    linear term's gradient ``ge`` after the step ``dz`` that changed the residuals by
    ``dr`` and the linear term by ``de``: ``Jr += t dz'``, ``t = (dr - Jr dz) / dz'dz``
    (likewise ``ge``), and ``H = 2 Jr'Jr + 2A`` with it, in O(D M + D^2):
    ``H += 2 (u dz' + dz u' + t't dz dz')``, ``u = Jr' t`` (before the update);
    ``full=False``: H's diagonal alone (:func:`gauss_newton_hessian`)."""
    M, D = JrT.shape
    ss = _dot(dz, dz)
    if not ss > 0.0:
        return
    t = np.empty(M)
    tt = 0.0
    u = np.zeros(D)
    for m in range(M):
        t[m] = (dr[m] - _dot(JrT[m], dz)) / ss
        tt += t[m] * t[m]
        _axpy(u, JrT[m], t[m])
    for i in range(D):
        if full:
            Hi = H[i]
            _axpy(Hi, dz, 2.0 * u[i] + 2.0 * tt * dz[i])
            _axpy(Hi, u, 2.0 * dz[i])
        else:  # the same two updates of the diagonal element
            H[i, i] += (2.0 * u[i] + 2.0 * tt * dz[i]) * dz[i]
            H[i, i] += 2.0 * dz[i] * u[i]
    for m in range(M):
        _axpy(JrT[m], dz, t[m])
    v = (de - _dot(ge, dz)) / ss
    _axpy(ge, dz, v)


@njit(cache=True, error_model="numpy")
def damped_step(H, g, mu, U, dz):
    """Solve ``(H + mu diag H) dz = -g`` by Cholesky, ``U'U`` with ``U`` (D, D) upper
    triangular (scratch; the right-looking form: each pivot row updates the rows below
    it, in panels of eight pivots: a panel's rows are factored among themselves, then
    update each row below in one pass, :func:`_axpy8`; every element receives the same
    updates in the same order as one pivot at a time, so the same factor to the bit);
    False when the matrix is not positive definite (then ``dz`` is undefined)."""
    D = H.shape[0]
    for i in range(D):
        Ui = U[i]
        Hi = H[i]
        for j in range(D):
            Ui[j] = Hi[j]
        Ui[i] *= 1.0 + mu
    a = np.empty(8)
    for k0 in range(0, D, 8):
        k1 = min(k0 + 8, D)
        for k in range(k0, k1):  # the panel's pivots, on the panel's rows
            Uk = U[k]
            s = Uk[k]
            if not s > 0.0:
                return False
            d = math.sqrt(s)
            Uk[k] = d
            row = Uk[k + 1:]
            inv = 1.0 / d
            for j in range(row.shape[0]):
                row[j] *= inv
            for i in range(k + 1, k1):
                _axpy(U[i, i:], Uk[i:], -Uk[i])
        for i in range(k1, D):  # the rows below, by the whole panel
            if k1 - k0 == 8:
                for q in range(8):
                    a[q] = -U[k0 + q, i]
                _axpy8(U[i, i:], U, k0, i, a)
            else:
                for k in range(k0, k1):
                    _axpy(U[i, i:], U[k, i:], -U[k, i])
    for i in range(D):  # U' y = -g, by the rows of U
        dz[i] = -g[i]
    for k in range(D):
        dz[k] /= U[k, k]
        _axpy(dz[k + 1:], U[k, k + 1:], -dz[k])
    for i in range(D - 1, -1, -1):  # U dz = y
        dz[i] = (dz[i] - _dot(U[i, i + 1:], dz[i + 1:])) / U[i, i]
    return True


GN_LOWRANK = 2.0  # the damped steps by Woodbury (lowrank_step) when D > this times M


@njit(cache=True, error_model="numpy")
def lowrank_step(H, JT, A, stride, g, mu, WT, dz):
    """Solve ``(H + mu diag H) dz = -g`` for ``H = 2 Jr'Jr + 2A`` through the residuals'
    side (``JT`` (D, M): the Jacobian by variable, ``Jr'``), in O(M^2 D) instead of the
    Cholesky factorisation's O(D^3): ``E = 2A + mu diag H`` is, for each of the ``stride``
    offsets, a tridiagonal matrix across the move blocks (the smoothing couples a variable
    only with itself one block before and after, :func:`quadratic_terms`), so ``E^-1`` is a
    sweep down and up the blocks; then Woodbury's identity,
    ``(E + 2 Jr'Jr)^-1 = E^-1 - W (I/2 + Jr W)^-1 W'``, ``W = E^-1 Jr'`` (``WT`` (D, M),
    scratch), leaves an M x M system (:func:`damped_step` with ``mu = 0``). False when
    ``E`` or that system is not positive definite. Faster than :func:`damped_step` when
    D is well above M (:data:`GN_LOWRANK`)."""
    D, M = JT.shape
    dp = np.empty(D)  # E = L diag(dp) L', L unit lower with lo[i] at (i, i - stride)
    lo = np.zeros(D)
    for i in range(D):
        e = 2.0 * A[i, i] + mu * H[i, i]
        if i >= stride:
            lo[i] = 2.0 * A[i, i - stride] / dp[i - stride]
            e -= lo[i] * lo[i] * dp[i - stride]
        if not e > 0.0:
            return False
        dp[i] = e
    u = np.empty(D)  # u = E^-1 g, WT = E^-1 Jr'
    for i in range(D):
        WT[i] = JT[i]
        u[i] = g[i]
        if i >= stride:
            _axpy(WT[i], WT[i - stride], -lo[i])
            u[i] -= lo[i] * u[i - stride]
    for i in range(D - 1, -1, -1):
        inv = 1.0 / dp[i]
        for n in range(M):
            WT[i, n] *= inv
        u[i] *= inv
        if i + stride < D:
            _axpy(WT[i], WT[i + stride], -lo[i + stride])
            u[i] -= lo[i + stride] * u[i + stride]
    S = np.zeros((M, M))  # I/2 + Jr W: the upper part by rows, eight variables a pass
    a = np.empty(8)
    for m in range(M):
        Sm = S[m, m:]
        i0 = 0
        while i0 + 8 <= D:
            for q in range(8):
                a[q] = JT[i0 + q, m]
            _axpy8(Sm, WT, i0, m, a)
            i0 += 8
        for i in range(i0, D):
            _axpy(Sm, WT[i, m:], JT[i, m])
    for m in range(M):
        S[m, m] += 0.5
        for n in range(m + 1, M):
            S[n, m] = S[m, n]
    v = np.zeros(M)  # -Jr u
    for i in range(D):
        _axpy(v, JT[i], -u[i])
    w = np.empty(M)  # S w = Jr u
    if not damped_step(S, v, 0.0, np.empty((M, M)), w):
        return False
    for i in range(D):  # dz = -(u - W w)
        dz[i] = _dot(WT[i], w) - u[i]
    return True


@njit(cache=True, error_model="numpy")
def keep_nominal(row, trace, poses, wear, cmds, trace0, poses0, wear0, cmds0):
    """Row ``row``'s rollout (its ``trace``, ``poses``, ``wear``, ``cmds``) kept as the
    polish's nominal one (``trace0``, ``poses0``, ``wear0``, ``cmds0``): the point the
    differences are taken at (:func:`_gn_jacobian`)."""
    trace0[:] = trace[row]
    poses0[:] = poses[row]
    wear0[:] = wear[row]
    cmds0[:] = cmds[row]


def first_steps(block, stride, D):
    """The first step at which each decision variable acts (``(D,)`` int64): its block's
    first step in ``block``; a perturbation of it changes nothing before."""
    first = np.full(D, block.shape[0], dtype=np.int64)
    for k in range(block.shape[0] - 1, -1, -1):
        first[block[k] * stride:(block[k] + 1) * stride] = k
    return first


def _gn_jacobian(model, x0, ref, block, P, S, wx, wy, Q, Lw, A, upper, h, z, r, lin, Zfd,
                 poses, wear, cmds, first, trace0, poses0, wear0, cmds0, JrT, ge, H):
    """The residuals' Jacobian ``JrT`` (M, D; row m: residual m's derivatives) and the linear
    term's gradient ``ge`` at ``z`` by forward differences (backward at the upper bound),
    from the residuals ``r[0]`` and linear term ``lin[0]`` of ``z``; ``r[1]`` is scratch;
    and the Gauss-Newton Hessian ``H`` from them. Each perturbed rollout starts at its
    variable's first step (``first``, :func:`first_steps`) from the nominal rollout of
    ``z`` (``trace0``, ``poses0``, ``wear0``, ``cmds0``: :func:`keep_nominal`), not from
    ``x0`` (:func:`controller.rollout.rollout_from`: the same outputs to the bit, the
    steps before repeated no more). ``rollout`` is a global bound by :func:`_make_gn`."""
    D = z.shape[0]
    M = r.shape[1]
    for d in range(D):
        for j in range(D):
            Zfd[d, j] = z[j]
        Zfd[d, d] += h[d] if z[d] + h[d] <= upper[d] else -h[d]
    rollout(model, x0, ref, Zfd, block, P, S, wx, wy, poses, wear, cmds, first,  # noqa: F821
            trace0, poses0, wear0, cmds0, np.empty((0, 0, 0)))
    for d in range(D):
        e = residuals(poses, wear, ref, Q, Lw, d, r, 1)
        inv = 1.0 / (Zfd[d, d] - z[d])
        for m in range(M):
            JrT[m, d] = (r[1, m] - r[0, m]) * inv
        ge[d] = (e - lin[0]) * inv
    gauss_newton_hessian(JrT, A, H, not D > GN_LOWRANK * M)  # (lowrank_step: the diagonal)


def _gn_step(model, x0, ref, block, P, S, wx, wy, Q, Lw, A, b, c, stride, lower, upper, mus,
             alphas, z, J, r, lin, poses, wear, cmds, first0, trace, trace0, poses0, wear0,
             cmds0, JrT, ge, g, H, Lc, dz, Zc, JT, WT):
    """One polish step from ``z`` (cost ``J``, residuals ``r[0]``, linear term ``lin[0]``,
    Jacobian ``JrT``, ``ge``, Hessian ``H``): the candidates of the damped steps, predicted
    in one call (with their ``trace``; ``first0`` zeros); the best, if it is below ``J``,
    becomes ``z`` (with its residuals and its rollout as the nominal one,
    :func:`keep_nominal`) and updates the Jacobian and the Hessian
    (:func:`broyden_update`). Returns the cost after the step. ``rollout`` is a global
    bound by :func:`_make_gn`."""
    D = z.shape[0]
    M = r.shape[1]
    na = alphas.shape[0]
    gauss_newton_gradient(JrT, r[0], ge, A, z, b, g)
    lowrank = D > GN_LOWRANK * M
    if lowrank:
        for m in range(M):
            for j in range(D):
                JT[j, m] = JrT[m, j]
    for k in range(mus.shape[0]):
        if lowrank:
            ok = lowrank_step(H, JT, A, stride, g, mus[k], WT, dz)
        else:
            ok = damped_step(H, g, mus[k], Lc, dz)
        for a in range(na):
            for j in range(D):
                v = z[j] + alphas[a] * dz[j] if ok else z[j]
                Zc[k * na + a, j] = min(max(v, lower[j]), upper[j])
    rollout(model, x0, ref, Zc, block, P, S, wx, wy, poses, wear, cmds, first0,  # noqa: F821
            trace0, poses0, wear0, cmds0, trace)
    best = -1
    Jb = J
    for k in range(Zc.shape[0]):
        e = residuals(poses, wear, ref, Q, Lw, k, r, 1)
        Jk = e + quadratic_value(A, b, c, Zc[k])
        for m in range(M):
            Jk += r[1, m] * r[1, m]
        if Jk < Jb:
            Jb = Jk
            best = k
    if best < 0:
        return J
    e = residuals(poses, wear, ref, Q, Lw, best, r, 1)
    keep_nominal(best, trace, poses, wear, cmds, trace0, poses0, wear0, cmds0)
    for j in range(D):
        dz[j] = Zc[best, j] - z[j]
    for m in range(M):
        r[1, m] -= r[0, m]  # (the change of the residuals)
    broyden_update(JrT, ge, H, dz, r[1], e - lin[0], not lowrank)
    for m in range(M):
        r[1, m] += r[0, m]
    for m in range(M):
        r[0, m] = r[1, m]
    lin[0] = e
    for j in range(D):
        z[j] = Zc[best, j]
    return Jb


def _gn_start(model, x0, ref, block, P, S, wx, wy, Q, Lw, z, r, lin, Zfd, poses, wear, cmds,
              first0, trace, trace0, poses0, wear0, cmds0):
    """The residuals ``r[0]`` and linear term ``lin[0]`` of ``z`` (one rollout), and that
    rollout as the nominal one (:func:`keep_nominal`)."""
    for j in range(z.shape[0]):
        Zfd[0, j] = z[j]
    rollout(model, x0, ref, Zfd[:1], block, P, S, wx, wy, poses, wear, cmds,  # noqa: F821
            first0[:1], trace0, poses0, wear0, cmds0, trace[:1])
    lin[0] = residuals(poses, wear, ref, Q, Lw, 0, r, 0)
    keep_nominal(0, trace, poses, wear, cmds, trace0, poses0, wear0, cmds0)


def _gn_run(model, x0, ref, block, P, S, wx, wy, Q, Lw, A, b, c, stride, lower, upper, h, mus,
            alphas, tol, refresh, n, st, z, r, lin, Zfd, poses, wear, cmds, first, first0, trace,
            trace0, poses0, wear0, cmds0, JrT, ge, g, H, Lc, dz, Zc, JT, WT):
    """Up to ``n`` polish steps (:func:`_gn_step`) from the state ``st`` = [cost, steps
    taken, Jacobian fresh (1) or updated (0), refreshes, stopped]: a step that lowers the
    cost by less than ``tol`` of it stops the polish if the Jacobian is fresh from the
    differences or ``refresh`` refreshes are spent, and otherwise takes the differences
    again at ``z`` (:func:`_gn_jacobian`). ``gn_step`` and ``gn_jacobian`` are globals
    bound by :func:`_make_gn`."""
    J = st[0]
    fresh = st[2] > 0.0
    for _ in range(n):
        Jn = gn_step(model, x0, ref, block, P, S, wx, wy, Q, Lw, A, b, c,  # noqa: F821
                     stride, lower, upper, mus, alphas, z, J, r, lin, poses, wear, cmds,
                     first0, trace, trace0, poses0, wear0, cmds0, JrT, ge, g, H, Lc, dz, Zc,
                     JT, WT)
        st[1] += 1.0
        stalled = not Jn < J or J - Jn < tol * J
        J = min(J, Jn)
        if stalled:
            if fresh or st[3] >= refresh:
                st[4] = 1.0
                break
            # the updated Jacobian has stopped helping: differences again, at z
            gn_jacobian(model, x0, ref, block, P, S, wx, wy, Q, Lw, A,  # noqa: F821
                        upper, h, z, r, lin, Zfd, poses, wear, cmds, first, trace0, poses0,
                        wear0, cmds0, JrT, ge, H)
            st[3] += 1.0
            fresh = True
        else:
            fresh = False
    st[0] = J
    st[2] = 1.0 if fresh else 0.0


def _make_gn(rollout, fn, name: str, **bound):
    """``fn`` (:func:`_gn_start`, :func:`_gn_jacobian`, :func:`_gn_step`, :func:`_gn_run`)
    compiled with ``rollout`` (and ``bound``) as its globals (not a closure: see
    :func:`_make_iterate`)."""
    g = dict(globals(), rollout=rollout, **bound)
    f = types.FunctionType(fn.__code__, g, name, fn.__defaults__)
    f.__qualname__ = name
    f.__doc__ = fn.__doc__
    f.__module__ = __name__
    return njit(cache=True, error_model="numpy")(f)


def _gn_kernels(pred, kind: str, parallel: bool) -> tuple:
    """The polish's kernels (start, Jacobian, run) over ``pred``'s rollout of ``kind``
    (:func:`controller.rollout.rollout_from`)."""
    ro = pred.kernels[kind]["rollout_from_parallel" if parallel else "rollout_from"]
    sfx = f"_{'parallel' if parallel else 'serial'}_{kind}_{pred.name}"
    start = _make_gn(ro, _gn_start, "gn_start" + sfx)
    jac = _make_gn(ro, _gn_jacobian, "gn_jacobian" + sfx)
    step = _make_gn(ro, _gn_step, "gn_step" + sfx)
    return start, jac, _make_gn(ro, _gn_run, "gn_run" + sfx, gn_step=step, gn_jacobian=jac)


GN = {(pred.name, kind, parallel): _gn_kernels(pred, kind, parallel)
      for pred in (_ro.FAST, _ro.EXACT) for kind in _ro.KINDS for parallel in (False, True)}


class CompiledAnnealer:
    """Simulated annealing of one MPC horizon problem, with preallocated buffers.

    Parameters as the reference annealer's (``tests/annealer_reference.py``); ``model`` is a
    :class:`controller.models.PredictionModel`, ``Q, L, R`` the cost weights; ``exact``:
    predict with the math library's functions (:data:`controller.rollout.EXACT`) instead
    of the SIMD prediction.
    """

    def __init__(self, model, Q, L, R, lower, upper, sigma, *, chains: int, iterations: int,
                 sigma_final: float, t_start: float, t_end: float, parallel: bool = False,
                 restart_every: int = 10, init_spread: float = 0.5, ladder: float = 1.0,
                 adapt_up: float = 1.0, adapt_down: float = 1.0, exact: bool = False,
                 pool_seed: int = 0, proposals: int = 1, polish: int = 0):
        self.model = model
        self.Q, self.L, self.R = (np.ascontiguousarray(a, dtype=np.float64) for a in (Q, L, R))
        self.lower = np.ascontiguousarray(lower, dtype=np.float64)
        self.upper = np.ascontiguousarray(upper, dtype=np.float64)
        self.sigma = np.ascontiguousarray(sigma, dtype=np.float64)
        self.chains, self.iterations = int(chains), int(iterations)
        if self.chains < 1 or self.iterations < 1:
            raise ValueError("anneal: chains and iterations must be >= 1")
        self.log_sf = math.log(sigma_final)
        self.t_start = float(t_start)
        self.log_tr = math.log(t_end / t_start)
        self.restart_every = int(restart_every)
        self.n_restart = max(self.chains // 4, 1)
        self.init_spread = float(init_spread)
        self.ladder0 = ladder_factors(self.chains, ladder)
        self.up, self.down = float(adapt_up), float(adapt_down)
        pred = _ro.EXACT if exact else _ro.FAST
        kind = _ro.step_kind(model.model_id, model.P)
        self._evaluate = pred.kernels[kind]["evaluate_parallel" if parallel else "evaluate_serial"]
        self._iterate = ITERATE[(pred.name, kind, bool(parallel))]
        D = model.dim
        C = self.chains
        self.proposals = K = int(proposals)
        if K < 1:
            raise ValueError("anneal: proposals must be >= 1")
        self.X = np.empty((C, D))
        self.Xp = np.empty((C * K, D))
        self.J = np.empty(C)
        self.Jp = np.empty(C * K)
        self.best_x = np.empty(D)
        self.best = np.empty(2)
        tiles = (C * K + _ro.LANES - 1) // _ro.LANES
        self.ws = np.empty((tiles, _ro.workspace_size(model.n_wheels, D)))
        self.pool = noise_pool(pool_seed)
        denom = max(self.iterations - 1, 1)
        self._fixed_fracs = np.minimum(np.arange(self.iterations) / denom, 1.0)
        self.polish_steps = int(polish)
        if self.polish_steps < 0:
            raise ValueError("anneal: polish must be >= 0")
        self._gn_start, self._gn_jacobian, self._gn_run = GN[(pred.name, kind, bool(parallel))]
        Np = model.settings.N_p
        rows = max(D, GN_CANDIDATES)
        M = 6 * Np
        self._gn_out = (np.empty((rows, Np, lay.N_POSE)), np.empty((rows, Np, lay.N_WEAR)),
                        np.empty((rows, 2, model.n_wheels)))
        self._gn_r, self._gn_lin, self._gn_Zfd = np.empty((2, M)), np.empty(1), np.empty((D, D))
        nx = lay.X0_DELTA + model.n_wheels
        # the differences' first steps, the candidates' (zeros), the candidates' trace, and
        # the nominal rollout (trace, poses, wear, cmds: keep_nominal)
        self._gn_first = (first_steps(model.block, model.stride, D),
                          np.zeros(GN_CANDIDATES, dtype=np.int64),
                          np.empty((GN_CANDIDATES, Np, nx)))
        self._gn_from_x0 = np.zeros(D, dtype=np.int64)  # (differences(from_nominal=False))
        self._gn_nominal = (np.empty((Np, nx)), np.empty((Np, lay.N_POSE)),
                            np.empty((Np, lay.N_WEAR)), np.empty((2, model.n_wheels)))
        self._gn_J = (np.empty((M, D)), np.empty(D))  # JrT (by residual), ge
        self._gn_la = (np.empty(D), np.empty((D, D)), np.empty((D, D)), np.empty(D),
                       np.empty((GN_CANDIDATES, D)), np.empty((D, M)),
                       np.empty((D, M)))  # g, H, Lc, dz, Zc, JT, WT
        self._A, self._b = np.zeros((D, D)), np.zeros(D)
        self._gn_state = np.empty(5)
        self._h = GN_STEP * self.sigma / self.sigma.max()

    def differences(self, x0: np.ndarray, ref: np.ndarray, z: np.ndarray,
                    from_nominal: bool = True) -> tuple:
        """The polish's start at ``z``: its residuals and linear term (one rollout), then
        the residuals' Jacobian and the linear term's gradient by forward differences
        (:func:`_gn_jacobian`; the Gauss-Newton Hessian of the polish's current ``A`` in
        its buffer): ``(r (M,), e, JrT (M, D), ge (D,))``, views of the polish's buffers
        (valid until its next call). ``from_nominal=False``: every perturbed rollout from
        ``x0`` (all steps; the same numbers, the work before the restart:
        ``benchmarks.polish_bench``)."""
        m = self.model
        z = np.ascontiguousarray(z, dtype=np.float64)
        if z.shape != (m.dim,):
            raise ValueError(f"differences: z must have {m.dim} entries, got shape {z.shape}")
        x0 = np.ascontiguousarray(x0, dtype=np.float64)
        ref = np.ascontiguousarray(ref, dtype=np.float64)
        r, lin, Zfd = self._gn_r, self._gn_lin, self._gn_Zfd
        head = (m.model_id, x0, ref, m.block, m.P, m.S, m.wx, m.wy, self.Q, self.L)
        first, first0, trace = self._gn_first
        nom = self._gn_nominal
        self._gn_start(*head, z, r, lin, Zfd, *self._gn_out, first0, trace, *nom)
        self._gn_jacobian(*head, self._A, self.upper, self._h, z, r, lin, Zfd, *self._gn_out,
                          first if from_nominal else self._gn_from_x0, *nom, *self._gn_J,
                          self._gn_la[1])
        return r[0], float(lin[0]), self._gn_J[0], self._gn_J[1]

    def polish(self, x0: np.ndarray, ref: np.ndarray, zprev: np.ndarray, res: AnnealResult,
               deadline_s: float | None = None) -> AnnealResult:
        """Up to ``polish`` Gauss-Newton steps (module section "the Gauss-Newton polish")
        from ``res.x``, the annealing's best point, on the same horizon problem; stops
        when a step stalls with a fresh Jacobian (:func:`_gn_run`), or when the next step
        would pass ``deadline_s`` (seconds from this call, at the mean time of the steps
        so far).
        Returns ``res`` with the polished point and cost (never worse than ``res``)."""
        n = self.polish_steps
        if n == 0:
            return res
        t0 = time.perf_counter()
        m = self.model
        x0 = np.ascontiguousarray(x0, dtype=np.float64)
        ref = np.ascontiguousarray(ref, dtype=np.float64)
        zprev = np.ascontiguousarray(zprev, dtype=np.float64)
        c = quadratic_terms(m.stride, m.nsplit, self.R, zprev, self._A, self._b)
        z = np.array(res.x, dtype=np.float64)
        self.differences(x0, ref, z)
        r, lin, Zfd = self._gn_r, self._gn_lin, self._gn_Zfd
        out = self._gn_out
        head = (m.model_id, x0, ref, m.block, m.P, m.S, m.wx, m.wy, self.Q, self.L)
        nom = self._gn_nominal
        st = self._gn_state
        st[:] = (res.cost, 0.0, 1.0, 0.0, 0.0)
        run = (*head, self._A, self._b, c, m.stride, self.lower, self.upper, self._h, GN_MUS,
               GN_ALPHAS, GN_TOL, GN_REFRESH)
        bufs = (z, r, lin, Zfd, *out, *self._gn_first, *nom, *self._gn_J, *self._gn_la)
        if deadline_s is None:
            self._gn_run(*run, n, st, *bufs)
        else:  # a step at a time, while the next one fits (at the mean time of those so far)
            while st[1] < n and not st[4]:
                el = time.perf_counter() - t0
                if st[1] > 0 and el + el / st[1] > deadline_s:
                    break
                self._gn_run(*run, 1, st, *bufs)
        J, done, refreshed = float(st[0]), int(st[1]), int(st[3])
        evals = res.evaluations + 1 + (1 + refreshed) * m.dim + done * GN_CANDIDATES
        if not J < res.cost:
            return AnnealResult(res.x, res.cost, res.iterations, evals, res.accepted, done)
        return AnnealResult(z, J, res.iterations, evals, res.accepted, done)

    def solve(self, x0: np.ndarray, ref: np.ndarray, zprev: np.ndarray, warm: np.ndarray,
              rng: np.random.Generator, deadline_s: float | None = None,
              origin: np.ndarray | None = None,
              scale0: np.ndarray | None = None) -> AnnealResult:
        """Minimise the horizon cost from ``warm`` (clipped to the box); ``deadline_s``
        optional wall-clock budget; ``origin``: chain 1's start (default the zero vector:
        the pure feed-forward of the offset parametrisations); ``scale0``: the chains'
        initial step factors (default the ladder; the MPC passes the previous solve's final
        factors, :attr:`scale`). Draws exactly the random numbers the reference annealer
        (``tests/annealer_reference.py``) draws."""
        t0 = time.perf_counter()
        m = self.model
        C, D, I = self.chains, m.dim, self.iterations
        K = self.proposals
        noise, unif = draw_noise(rng, self.pool, I, C * K, D)
        x0 = np.ascontiguousarray(x0, dtype=np.float64)
        ref = np.ascontiguousarray(ref, dtype=np.float64)
        zprev = np.ascontiguousarray(zprev, dtype=np.float64)
        # (np.minimum/np.maximum: np.clip's Python layer cost ~5 us a call, a 2-axle solve ~0.9 ms)
        lo, hi = self.lower, self.upper
        w = np.minimum(np.maximum(np.asarray(warm, dtype=float), lo), hi)
        X = self.X
        scale = (self.ladder0.copy() if scale0 is None
                 else np.minimum(np.maximum(np.asarray(scale0, dtype=float), SCALE_MIN), SCALE_MAX))
        X[:] = w + (self.init_spread * self.sigma)[None, :] * scale[:, None] * noise[0, :C]
        X[0] = w
        if C > 1:
            X[1] = np.minimum(np.maximum(0.0 if origin is None else origin, lo), hi)
        np.minimum(np.maximum(X, lo, out=X), hi, out=X)
        args = (m.model_id, x0, ref, m.block, m.P, m.S, m.wx, m.wy, self.Q, self.L, self.R,
                m.nsplit, zprev)
        self._evaluate(*args[:3], X, *args[3:], self.ws, self.J)
        ib = int(np.argmin(self.J))
        self.best_x[:] = X[ib]
        self.best[0] = self.J[ib]
        self.best[1] = 0.0
        tail = (self.sigma, self.lower, self.upper, self.log_sf, self.t_start, self.log_tr,
                self.restart_every, self.n_restart, I, self.up, self.down, self.ws)
        state = (X, self.J, self.Xp, self.Jp, self.best_x, self.best, scale, noise, unif)
        if deadline_s is None:
            self._iterate(*args, *state, 0, self._fixed_fracs, *tail)
            done = I
        else:
            # anytime: iterations in chunks sized from the measured time per iteration, the
            # clock read between chunks; the cooling follows the elapsed fraction
            denom = max(I - 1, 1)
            done = 0
            while done < I:
                el = time.perf_counter() - t0
                if done == 0:
                    n = 1
                else:
                    per_it = el / done
                    n = min(int((deadline_s - el) / per_it), CHUNK, I - done)
                    if n < 1:
                        break
                    per = per_it / deadline_s
                its = np.arange(done, done + n)
                fr = its / denom if done == 0 else np.maximum(its / denom, el / deadline_s + per * (its - done))
                self._iterate(*args, *state, done, np.minimum(fr, 1.0), *tail)
                done += n
        self.scale = scale  # the chains' step factors at the end (MPC: the next solve's start)
        return AnnealResult(self.best_x.copy(), float(self.best[0]), done, C + C * K * done,
                            float(self.best[1]) / max(done * C, 1))
