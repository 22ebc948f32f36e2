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

from msagv.plant.signals import (BODY_FIELDS, CONTROL_PERIOD, WEAR_FIELDS, WHEEL_WEAR_FIELDS,
                                 wheel_suffixes)

from .interface import Controller
from .metrics import compute_metrics
from .reference import Reference


# state-message fields that are not signals (DESIGN.md's envelope)
_NOT_SIGNALS = {"t", "seq", "v", "end"}
def _signal_row(st: dict, ref_row, outputs) -> dict:
    """The columns of one log row beyond pose, reference pose, commands and wear work,
    named as the signals (plant.stepping.signal_names): the body velocities, the
    reference's velocities, ``delta_ij``, the actual wheel speeds ``omega_w_act_ij``, any
    other field of the state message (per wheel: ``name_ij``), then the plant's outputs
    (slips, forces, powers, ...; the actual rates as ``omega_w_act_ij``/``omega_s_act_ij``,
    as the FMU names them)."""
    row: dict = {}
    for k in ("vx", "vy", "r"):
        if k in st:
            row[k] = float(st[k])
    if len(ref_row) >= 6:
        for k, v in zip(("vx_ref", "vy_ref", "r_ref"), ref_row[3:6]):
            row[k] = float(v)
    nw = len(st.get("delta", ()))
    wheels = wheel_suffixes(nw)
    for k, v in zip(wheels, st.get("delta", ())):
        row[f"delta_{k}"] = float(v)
    for k, v in zip(wheels, st.get("omega_w", ())):
        row[f"omega_w_act_{k}"] = float(v)
    for name, v in st.items():
        if name in _NOT_SIGNALS or name in BODY_FIELDS or name in WEAR_FIELDS or name in ("delta", "omega_w"):
            continue
        if isinstance(v, (list, tuple)) and len(v) == nw:
            base = name[:-3] if name.endswith("_ij") else name  # W_s_ij -> W_s_11, ...
            for k, x in zip(wheels, v):
                row[f"{base}_{k}"] = float(x)
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            row[name] = float(v)
    for name, v in (outputs or {}).items():
        for rate in ("omega_w_", "omega_s_"):
            if name.startswith(rate) and not name.startswith(rate + "act_"):
                name = rate + "act_" + name[len(rate):]
        if name in row or name in BODY_FIELDS or name in WEAR_FIELDS:
            continue
        row[name] = float(v)
    return row


@dataclass
class RunLog:
    """Per-step log of a closed-loop run (row k: the state at t_k and the command applied
    over [t_k, t_k + T)). ``signals`` holds each row's further columns (the full state,
    the reference's velocities and, in process, the plant's outputs under the command),
    named as the signals; :meth:`to_csv` writes them all."""

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
    signals: list = field(default_factory=list)
    #: per-wheel wear work (W_s_ij, W_alpha_ij, W_t_ij) at t_k, (3, 2n) per row; None for a
    #: row whose state did not carry it
    W_ij: list = field(default_factory=list)
    #: the run was cut short (Ctrl-C): the rows so far, W_final from the last row
    interrupted: bool = False

    def append(self, st: dict, ref_row, cmd, outputs: dict | None = None) -> None:
        self.t.append(st["t"])
        self.pose.append((st["x"], st["y"], st["phi"]))
        self.ref.append(tuple(ref_row[:3]))
        self.omega_w.append(np.asarray(cmd.omega_w).tolist())
        self.omega_s.append(np.asarray(cmd.omega_s).tolist())
        self.W.append((st.get("W_s", 0.0), st.get("W_alpha", 0.0), st.get("W_t", 0.0)))
        self.solve_ms.append(cmd.solve_ms)
        self.cost.append(cmd.cost)
        self.signals.append(_signal_row(st, ref_row, outputs))
        self.W_ij.append([list(st[k]) for k in WHEEL_WEAR_FIELDS] if all(k in st for k in WHEEL_WEAR_FIELDS)
                         else None)

    def wheel_wear(self) -> dict | None:
        """Each wheel's and axle's wear work over the run
        (:func:`controller.metrics.wear_by_wheel`): the per-wheel wear work at the end (the
        final state; the last row if the run was cut short) minus at the first row. None
        when a state lacked the per-wheel fields (a plant that does not send them)."""
        from .metrics import wear_by_wheel

        if not self.W_ij or any(w is None for w in self.W_ij):
            return None
        fs = self.final_state
        if not self.interrupted and all(k in fs for k in WHEEL_WEAR_FIELDS):
            end = np.array([fs[k] for k in WHEEL_WEAR_FIELDS], dtype=float)
        else:
            end = np.asarray(self.W_ij[-1], dtype=float)
        start = np.asarray(self.W_ij[0], dtype=float)
        if end.shape != start.shape:
            return None
        return wear_by_wheel(end - start)

    def cut_short(self) -> None:
        """Mark the run as interrupted: the metrics cover the rows logged so far (the wear
        work up to the last row's state). A row that a Ctrl-C cut in the middle of
        :meth:`append` (some of its lists appended, not the rest) is dropped whole, so every
        list keeps the same rows."""
        self.interrupted = True
        rows = ("t", "pose", "ref", "omega_w", "omega_s", "W", "solve_ms", "cost", "signals",
                "W_ij")
        n = min(len(getattr(self, k)) for k in rows)
        for k in rows:
            del getattr(self, k)[n:]
        if self.W:
            self.W_final = tuple(self.W[-1])

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: np.asarray(getattr(self, k)) for k in
                ("t", "pose", "ref", "omega_w", "omega_s", "W", "solve_ms", "cost")}

    def distance(self) -> float:
        """The distance the body travelled [m]: along the logged poses to the final state's
        (the last row's if the run was cut short)."""
        from .metrics import path_length

        xy = [p[:2] for p in self.pose]
        fs = self.final_state
        if not self.interrupted and "x" in fs and "y" in fs:
            xy.append((fs["x"], fs["y"]))
        return path_length(xy)

    def metrics(self) -> dict:
        W0 = self.W[0] if self.W else (0.0, 0.0, 0.0)
        return compute_metrics(np.asarray(self.pose), np.asarray(self.ref), W0, self.W_final,
                               self.solve_ms, distance_m=self.distance())

    def columns(self) -> tuple[list[str], np.ndarray]:
        """``(names, data)`` of the per-step log: ``t``, the pose and the reference's pose,
        the body velocities and the reference's, ``delta_ij``, the actual wheel speeds
        ``omega_w_act_ij``, the commands ``omega_w_ij``, ``omega_s_ij`` (the plant's
        inputs, so the CSV replays with ``msagv plant replay --inputs``), the further
        signals, the wear work ``W_s, W_alpha, W_t``, ``solve_ms`` and ``cost``."""
        a = self.arrays()
        n = len(self.t)
        nw = a["omega_w"].shape[1] if a["omega_w"].ndim == 2 else 0
        wheels = wheel_suffixes(nw)
        extra: list[str] = []
        for row in self.signals:
            for k in row:
                if k not in extra:
                    extra.append(k)
        front = [k for k in extra if k in ("vx", "vy", "r", "vx_ref", "vy_ref", "r_ref")
                 or k.startswith(("delta_", "omega_w_act_"))]
        rest = [k for k in extra if k not in front]
        sig = np.full((n, len(extra)), np.nan)
        index = {k: i for i, k in enumerate(front + rest)}
        for i, row in enumerate(self.signals):
            for k, v in row.items():
                sig[i, index[k]] = v
        cols = ["t", "x", "y", "phi", "x_ref", "y_ref", "phi_ref"] + front
        cols += [f"omega_w_{k}" for k in wheels] + [f"omega_s_{k}" for k in wheels]
        cols += rest + list(WEAR_FIELDS) + ["solve_ms", "cost"]
        parts = [a["t"].reshape(n, -1), a["pose"].reshape(n, -1), a["ref"].reshape(n, -1),
                 sig[:, :len(front)], a["omega_w"].reshape(n, -1), a["omega_s"].reshape(n, -1),
                 sig[:, len(front):], a["W"].reshape(n, -1), a["solve_ms"].reshape(n, -1),
                 a["cost"].reshape(n, -1)]
        return cols, np.column_stack(parts) if n else np.zeros((0, len(cols)))

    def to_csv(self, path) -> None:
        """The per-step log as CSV, one column per signal (:meth:`columns`)."""
        cols, data = self.columns()
        np.savetxt(path, data, delimiter=",", header=",".join(cols), comments="", fmt="%.10g")


def closed_loop(plant, mpc: Controller, reference: Reference, duration: float, period: float = CONTROL_PERIOD,
                progress: bool | None = None, on_step=None, log: RunLog | None = None,
                outputs: bool = True, measure=None) -> RunLog:
    """Run the MPC on ``plant`` for ``duration`` seconds of vehicle time.

    The MPC is warmed up (kernels compiled) on the initial state first, so the first solve
    in the log is not a compiling one. ``progress`` shows a progress bar on stderr (default:
    when stderr is a terminal and the run is longer than 1000 steps). ``on_step(k, state,
    cmd)`` is called after each command (for recording). ``log``: a :class:`RunLog` to fill
    (so a caller interrupted mid-run keeps the rows so far). ``outputs``: also log the
    plant's outputs under each command (slips, forces, powers: ``PlantInterface.outputs``).
    ``measure``: what the controller receives of each state message (e.g.
    :class:`plant.sensors.MeasurementNoise`; default the state itself); the log keeps the
    true state.
    """
    n = int(round(duration / period))
    if n < 1:
        raise ValueError("closed_loop: duration must be at least one control period")
    log = RunLog() if log is None else log
    plant_outputs = plant.outputs if outputs else None
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
        cmd = mpc.step(st if measure is None else measure(st), reference)
        plant.set_inputs(cmd.omega_w, cmd.omega_s)
        log.append(st, reference.sample(t), cmd,
                   plant_outputs() if plant_outputs is not None else None)
        if on_step is not None:
            on_step(k, st, cmd)
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
