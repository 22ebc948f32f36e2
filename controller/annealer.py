"""Simulated annealing over a box, with several chains evaluated together.

Each iteration proposes one move per chain and evaluates all proposals in ONE call of
the batch cost function (for the MPC: one batch rollout). Design choices (see
docs/CONTROLLER.md, which also gives what each choice bought on the MPC's problem):

* **Chains**: ``chains`` Metropolis chains; chain 0 starts at the warm start, chain 1 at
  the origin (the pure feed-forward for the MPC), the rest at the warm start plus a
  Gaussian spread.
* **Proposals**: Gaussian steps with a per-coordinate scale ``sigma``, times a per-chain
  factor, shrinking geometrically to ``sigma_final`` of their start over the budget, and
  clipped to the box (so no candidate is ever outside the bounds). The per-chain factors
  start on a geometric ladder from ``ladder`` to 1 (some chains search near, some far)
  and adapt: x ``adapt_up`` after an accepted move, x ``adapt_down`` after a rejected one
  (the classic success rule of evolution strategies), kept within [1e-4, 10].
* **Acceptance**: Metropolis, ``exp(-(J' - J) / T)`` with a temperature relative to the
  best cost so far (scale-free: the same settings work for any weights),
  ``T_i = J_best * t_start (t_end / t_start)^(i / (I - 1))`` (geometric cooling).
* **Exploitation**: every ``restart_every`` iterations the worst quarter of the chains
  (at least one) restarts from the best point found.
* **Budgets**: a fixed iteration count (deterministic: same seed, same result) and/or a
  wall-clock deadline (anytime: the best point so far is returned when time runs out; the
  cooling then follows the elapsed fraction of the deadline).
* **Seeding**: all randomness comes from the ``numpy.random.Generator`` passed in.

``ladder = 1`` and ``adapt_up = adapt_down = 1`` give plain annealing with a fixed
proposal schedule.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np


@dataclass
class AnnealResult:
    x: np.ndarray  # best point (D,)
    cost: float  # its cost
    iterations: int  # iterations run
    evaluations: int  # candidate evaluations (incl. the initial ones)
    accepted: float  # fraction of proposals accepted


SCALE_MIN, SCALE_MAX = 1e-4, 10.0  # bounds of the adaptive per-chain step factors


def ladder_factors(chains: int, ladder: float) -> np.ndarray:
    """Initial per-chain step factors: geometric from ``ladder`` (chain 0) to 1."""
    if not 0.0 < ladder <= 1.0:
        raise ValueError(f"anneal: ladder must be in (0, 1], got {ladder}")
    return np.geomspace(ladder, 1.0, chains) if chains > 1 else np.ones(1)


def anneal(cost: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, lower: np.ndarray,
           upper: np.ndarray, sigma: np.ndarray, rng: np.random.Generator, *, chains: int = 32,
           iterations: int = 30, deadline_s: float | None = None, sigma_final: float = 0.1,
           t_start: float = 1e-2, t_end: float = 1e-4, restart_every: int = 10,
           init_spread: float = 0.5, include_origin: bool = True, ladder: float = 1.0,
           adapt_up: float = 1.0, adapt_down: float = 1.0) -> AnnealResult:
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
    noise = rng.standard_normal((iterations + 1, chains, D))
    unif = rng.random((iterations, chains))
    scale = ladder_factors(chains, ladder)
    X = x0 + (init_spread * sigma)[None, :] * scale[:, None] * noise[0]
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
        Xp = X + step[None, :] * scale[:, None] * noise[it + 1]
        np.clip(Xp, lower, upper, out=Xp)
        Jp = np.asarray(cost(Xp), dtype=float)
        evals += chains
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
