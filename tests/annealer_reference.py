"""The generic, readable simulated annealer: the reference the compiled one is tested against.

:class:`controller.sa_kernel.CompiledAnnealer` runs this algorithm on the MPC's cost inside
one numba kernel; ``tests/test_controller.py`` checks that both return the same answer for
the same seed (same random draws), and tests this one on small known problems. Only tests
call it, so it lives here. The algorithm is described in :mod:`controller.sa_kernel` and
docs/CONTROLLER.md ("Simulated annealing").
"""

from __future__ import annotations

import math
import time
from typing import Callable

import numpy as np

from msagv.controller.sa_kernel import SCALE_MAX, SCALE_MIN, AnnealResult, ladder_factors


def anneal(cost: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, lower: np.ndarray,
           upper: np.ndarray, sigma: np.ndarray, rng: np.random.Generator, *, chains: int = 32,
           iterations: int = 30, deadline_s: float | None = None, sigma_final: float = 0.1,
           t_start: float = 1e-2, t_end: float = 1e-4, restart_every: int = 10,
           init_spread: float = 0.5, include_origin: bool = True, ladder: float = 1.0,
           adapt_up: float = 1.0, adapt_down: float = 1.0,
           pool: np.ndarray | None = None, proposals: int = 1) -> AnnealResult:
    """Minimise ``cost`` over the box [lower, upper] by simulated annealing.

    Parameters
    ----------
    cost : callable
        ``cost(X) -> J`` with X of shape (chains, D) and J of shape (chains,).
    x0 : (D,) warm start. lower, upper : (D,) box. sigma : (D,) initial proposal scale.
    rng : numpy Generator (the only source of randomness).
    chains, iterations : the fixed budget (iterations > 0).
    deadline_s : optional wall-clock budget in seconds; the loop stops at whichever of the
        two budgets comes first.
    ladder, adapt_up, adapt_down : the per-chain step factors (module docstring).
    proposals : moves proposed per chain and iteration; the chain's Metropolis test takes
        the best of them.
    pool : optional pool of standard normals the proposals' normals are a window of
        (as the compiled annealer's: ``controller.sa_kernel.draw_noise``); None: fresh.
    """
    x0 = np.clip(np.asarray(x0, dtype=float), lower, upper)
    D = x0.size
    if chains < 1 or iterations < 1:
        raise ValueError("anneal: chains and iterations must be >= 1")
    if lower.shape != (D,) or upper.shape != (D,) or sigma.shape != (D,):
        raise ValueError("anneal: lower, upper and sigma must have the shape of x0")
    t0 = time.perf_counter()
    # all random numbers of a solve drawn at once: same seed -> same sequence, whatever
    # the deadline cuts off
    K = int(proposals)
    n = (iterations + 1) * chains * K * D
    if pool is not None and n <= pool.shape[0]:
        off = int(rng.integers(0, pool.shape[0] - n + 1))
        noise = pool[off:off + n].reshape(iterations + 1, chains * K, D)
    else:
        noise = rng.standard_normal((iterations + 1, chains * K, D))
    unif = rng.random((iterations, chains))
    scale = ladder_factors(chains, ladder)
    X = x0 + (init_spread * sigma)[None, :] * scale[:, None] * noise[0, :chains]
    X[0] = x0
    if include_origin and chains > 1:
        X[1] = np.clip(0.0, lower, upper)
    np.clip(X, lower, upper, out=X)
    J = np.asarray(cost(X), dtype=float).copy()
    ib = int(np.argmin(J))
    best_x, best_J = X[ib].copy(), float(J[ib])
    evals = chains
    acc = 0
    done = 0
    log_sf = math.log(sigma_final)
    log_tr = math.log(t_end / t_start)
    denom = max(iterations - 1, 1)
    n_restart = max(chains // 4, 1)
    for it in range(iterations):
        if deadline_s is not None:
            el = time.perf_counter() - t0
            frac = max(it / denom, el / deadline_s)
            if it > 0 and el + el / it > deadline_s:
                break
        else:
            frac = it / denom
        frac = min(frac, 1.0)
        step = sigma * math.exp(log_sf * frac)
        Xp = np.repeat(X, K, axis=0) + step[None, :] * np.repeat(scale, K)[:, None] * noise[it + 1]
        np.clip(Xp, lower, upper, out=Xp)
        Jp = np.asarray(cost(Xp), dtype=float)
        evals += chains * K
        pick = np.arange(chains) * K + np.argmin(Jp.reshape(chains, K), axis=1)
        Xp, Jp = Xp[pick], Jp[pick]
        temp = max(best_J, 1e-12) * t_start * math.exp(log_tr * frac)
        dJ = Jp - J
        ok = (dJ <= 0) | (unif[it] < np.exp(-np.maximum(dJ, 0.0) / temp))
        acc += int(ok.sum())
        X[ok] = Xp[ok]
        J[ok] = Jp[ok]
        scale = np.clip(np.where(ok, scale * adapt_up, scale * adapt_down), SCALE_MIN, SCALE_MAX)
        ib = int(np.argmin(J))
        if J[ib] < best_J:
            best_J = float(J[ib])
            best_x = X[ib].copy()
        if restart_every and (it + 1) % restart_every == 0 and it + 1 < iterations:
            worst = np.argsort(J, kind="mergesort")[-n_restart:]  # stable: ties reproducible
            X[worst] = best_x
            J[worst] = best_J
        done += 1
    return AnnealResult(best_x, best_J, done, evals, acc / max(done * chains, 1))


def gauss_newton_polish(residuals: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
                        A: np.ndarray, b: np.ndarray, c: float, z: np.ndarray, J: float,
                        lower: np.ndarray, upper: np.ndarray, h: np.ndarray, *, steps: int,
                        mus, alphas, tol: float,
                        refresh: int) -> tuple[np.ndarray, float, int, int]:
    """The Gauss-Newton polish of :meth:`controller.sa_kernel.CompiledAnnealer.polish`,
    written plainly for ``J(z) = |r(z)|^2 + e(z) + z'Az + b'z + c`` with
    ``residuals(Z) -> (r, e)`` for a batch of rows: the Jacobian of ``r`` and ``e`` by
    forward differences (steps ``h``, backward at the upper bound) once, then per step the
    Levenberg-Marquardt steps ``(H + mu diag H) dz = -g`` (``H = 2 Jr'Jr + 2A``,
    ``g = 2 Jr'r + grad e + 2Az + b``) for each ``mu`` at each length ``alpha``, clipped to
    the box; the best is taken if it lowers the cost, and the Jacobian follows it by
    Broyden's update. A step that lowers the cost by less than ``tol`` of it ends the
    polish if the Jacobian is fresh from differences (or ``refresh`` refreshes are
    spent), and otherwise the differences are taken again. Returns ``(z, J, steps,
    refreshes)``."""
    z = np.asarray(z, dtype=float).copy()
    D = z.size
    r0, e0 = (a[0] for a in residuals(z[None, :]))

    def differences(z, r0, e0):
        hd = np.where(z + h <= upper, h, -h)
        r, e = residuals(z[None, :] + np.diag(hd))
        return ((r - r0) / hd[:, None]).T, (e - e0) / hd  # (M, D), (D,)

    Jr, ge = differences(z, r0, e0)
    done = refreshed = 0
    fresh = True
    while done < steps:
        g = 2.0 * Jr.T @ r0 + ge + 2.0 * A @ z + b
        H = 2.0 * Jr.T @ Jr + 2.0 * A
        cands = []
        for mu in mus:
            try:
                np.linalg.cholesky(H + mu * np.diag(np.diag(H)))
                dz = np.linalg.solve(H + mu * np.diag(np.diag(H)), -g)
            except np.linalg.LinAlgError:
                dz = np.zeros(D)
            cands += [np.clip(z + a * dz, lower, upper) for a in alphas]
        C = np.array(cands)
        r, e = residuals(C)
        Jc = np.sum(r * r, axis=1) + e + np.einsum("ij,jk,ik->i", C, A, C) + C @ b + c
        done += 1
        k = int(np.argmin(Jc))
        stalled = not Jc[k] < J or J - Jc[k] < tol * J
        if Jc[k] < J:
            s = C[k] - z
            Jr += np.outer(r[k] - r0 - Jr @ s, s) / (s @ s)
            ge += (e[k] - e0 - ge @ s) * s / (s @ s)
            z, J, r0, e0 = C[k], float(Jc[k]), r[k], e[k]
        if stalled:
            if fresh or refreshed >= refresh:
                break
            Jr, ge = differences(z, r0, e0)
            refreshed += 1
            fresh = True
        else:
            fresh = False
    return z, J, done, refreshed
