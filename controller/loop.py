"""In-process closed loop: the MPC at 100 Hz on any plant-like object.

The plant is duck-typed (``set_inputs(omega_w, omega_s)``, ``do_step(t, h)``,
``state_message()``, ``t``), so the same loop drives the native stepping plant, an FMU
through fmpy, or anything else with that interface; the controller package itself never
imports the plant's stepping code.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field

import numpy as np

from .metrics import compute_metrics
from .mpc import MPC
from .reference import Reference


@dataclass
class RunLog:
    """Per-step log of a closed-loop run (row k: the state at t_k and the command applied
    over [t_k, t_k + T))."""

    t: list = field(default_factory=list)
    pose: list = field(default_factory=list)
    ref: list = field(default_factory=list)
    omega_w: list = field(default_factory=list)
    omega_s: list = field(default_factory=list)
    W: list = field(default_factory=list)  # (W_s, W_alpha, W_t) at t_k
    solve_ms: list = field(default_factory=list)
    cost: list = field(default_factory=list)
    W_final: tuple = (0.0, 0.0, 0.0)
    final_state: dict = field(default_factory=dict)

    def append(self, st: dict, ref_row, cmd) -> None:
        self.t.append(st["t"])
        self.pose.append((st["x"], st["y"], st["phi"]))
        self.ref.append(tuple(ref_row[:3]))
        self.omega_w.append(np.asarray(cmd.omega_w).tolist())
        self.omega_s.append(np.asarray(cmd.omega_s).tolist())
        self.W.append((st.get("W_s", 0.0), st.get("W_alpha", 0.0), st.get("W_t", 0.0)))
        self.solve_ms.append(cmd.solve_ms)
        self.cost.append(cmd.cost)

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: np.asarray(getattr(self, k)) for k in
                ("t", "pose", "ref", "omega_w", "omega_s", "W", "solve_ms", "cost")}

    def metrics(self) -> dict:
        W0 = self.W[0] if self.W else (0.0, 0.0, 0.0)
        return compute_metrics(np.asarray(self.pose), np.asarray(self.ref), W0, self.W_final,
                               self.solve_ms)

    def to_csv(self, path) -> None:
        a = self.arrays()
        nw = a["omega_w"].shape[1]
        cols = ["t", "x", "y", "phi", "x_ref", "y_ref", "phi_ref"]
        cols += [f"omega_w_{i}" for i in range(nw)] + [f"omega_s_{i}" for i in range(nw)]
        cols += ["W_s", "W_alpha", "W_t", "solve_ms", "cost"]
        data = np.column_stack([a["t"], a["pose"], a["ref"], a["omega_w"], a["omega_s"], a["W"],
                                a["solve_ms"], a["cost"]])
        np.savetxt(path, data, delimiter=",", header=",".join(cols), comments="", fmt="%.10g")


def closed_loop(plant, mpc: MPC, reference: Reference, duration: float, period: float = 0.01,
                progress: bool | None = None, on_step=None) -> RunLog:
    """Run the MPC on ``plant`` for ``duration`` seconds of vehicle time.

    The MPC is warmed up (kernels compiled) on the initial state first, so the first solve
    in the log is not a compiling one. ``progress`` shows a progress bar on stderr (default:
    when stderr is a terminal and the run is longer than 1000 steps). ``on_step(k, state,
    cmd)`` is called after each command (for recording).
    """
    n = int(round(duration / period))
    if n < 1:
        raise ValueError("closed_loop: duration must be at least one control period")
    log = RunLog()
    st = plant.state_message()
    mpc.warmup(dict(st, t=st["t"]))
    if progress is None:
        progress = sys.stderr.isatty() and n > 1000
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=n, unit="step", desc=f"{reference.name} {mpc.settings.method}",
                   file=sys.stderr, leave=False)
    t0 = plant.t
    for k in range(n):
        # t_k = t0 + k T exactly (DESIGN.md: t = seq * T, so time never drifts and a run
        # over Zenoh sees bit-identical times)
        t = t0 + k * period
        st = plant.state_message()
        st["t"] = t
        cmd = mpc.step(st, reference)
        log.append(st, reference.sample(t), cmd)
        if on_step is not None:
            on_step(k, st, cmd)
        plant.set_inputs(cmd.omega_w, cmd.omega_s)
        plant.do_step(plant.t, period)
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    st = plant.state_message()
    st["t"] = t0 + n * period
    log.W_final = (st.get("W_s", 0.0), st.get("W_alpha", 0.0), st.get("W_t", 0.0))
    log.final_state = st
    return log
