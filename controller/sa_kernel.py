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

from . import approx as _approx
from . import rollout as _ro

CHUNK = 16  # iterations per kernel call under a deadline (the clock is read between calls)
SCALE_MIN, SCALE_MAX = 1e-4, 10.0  # bounds of the adaptive per-chain step factors

# stale-cache guard (plant.layout): the layout and the kernels compiled into these
_STAMP = lay.kernel_stamp(_ro.__file__, _tire.__file__, _approx.__file__)


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
                 pool_seed: int = 0, proposals: int = 1):
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
