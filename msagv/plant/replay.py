"""Open-loop replay: a CSV of held commands through the stepping plant, signals to CSV."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Mapping

import numpy as np

from .signals import foreign_separator, input_names
from .stepping import Plant
from .vehicle import Vehicle


class ReplayError(ValueError):
    """A malformed input CSV; the message names the file, line and column."""


def read_inputs(path: str | Path, vehicle: Vehicle) -> tuple[np.ndarray, np.ndarray]:
    """Read ``U.csv``: column ``t`` and ``omega_w_ij``, ``omega_s_ij`` for every wheel.

    Returns ``(t (K,), U (K, 4n))`` with U's columns in :func:`input_names` order. Row k is
    held until row k+1. Rejects a missing column, an empty file, a non-number, NaN/inf,
    a negative wheel speed or a non-increasing ``t``, naming the line.
    """
    path = Path(path)
    if not path.is_file():
        raise ReplayError(f"{path}: no such file")
    need = ["t"] + input_names(vehicle)
    with path.open(newline="") as f:
        reader = csv.reader(f)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise ReplayError(f"{path}: empty file (expected a header with {', '.join(need)})") from None
        missing = [c for c in need if c not in header]
        if missing:
            sep = foreign_separator(header, ["t"] + missing[:1])
            if sep is not None and len(header) == 1:
                raise ReplayError(f"{path}:1: the columns are separated by {sep}: msagv "
                                  f"reads comma-separated files (decimal points, not commas)")
            raise ReplayError(f"{path}:1: missing column(s) {', '.join(missing)}")
        idx = [header.index(c) for c in need]
        ts, rows = [], []
        for lineno, row in enumerate(reader, start=2):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != len(header):
                raise ReplayError(f"{path}:{lineno}: expected {len(header)} fields, got {len(row)}")
            vals = []
            for c, i in zip(need, idx):
                try:
                    v = float(row[i])
                except ValueError:
                    raise ReplayError(f"{path}:{lineno}: column {c}: '{row[i]}' is not a number") from None
                if not math.isfinite(v):
                    raise ReplayError(f"{path}:{lineno}: column {c}: value must be finite, got {row[i]}")
                if c.startswith("omega_w_") and v < 0:
                    raise ReplayError(f"{path}:{lineno}: column {c}: wheel speed must be >= 0, got {v}")
                vals.append(v)
            if ts and not vals[0] > ts[-1]:
                raise ReplayError(f"{path}:{lineno}: t must increase strictly ({vals[0]} after {ts[-1]})")
            ts.append(vals[0])
            rows.append(vals[1:])
    if not ts:
        raise ReplayError(f"{path}: no data rows")
    return np.array(ts), np.array(rows)


def replay(vehicle: Vehicle, t: np.ndarray, U: np.ndarray,
           initial: Mapping[str, float] | None = None, **plant_kw) -> tuple[list[str], np.ndarray]:
    """Run the plant over held inputs; returns ``(names, S)`` with S[k] the signals at t[k].

    The plant starts at ``t[0]`` in its initial state. Row k's inputs apply on
    [t[k], t[k+1]); the outputs in row k (slips, forces, powers) are those with row k's
    inputs applied at t[k]. Wear work W is integrated from t[0].
    """
    nw = vehicle.n_wheels
    plant = Plant(vehicle, initial=initial, **plant_kw)
    names = ["t"] + plant.signal_names
    S = np.empty((len(t), len(names)))
    for k in range(len(t)):
        plant.set_inputs(U[k, :nw], U[k, nw:])
        S[k, 0] = t[k]
        S[k, 1:] = plant.output_vector()
        if k + 1 < len(t):
            plant.do_step(plant.t, float(t[k + 1] - t[k]))
    return names, S


def write_signals(path: str | Path, names: list[str], S: np.ndarray) -> None:
    with Path(path).open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(names)
        for row in S:
            w.writerow([repr(float(v)) for v in row])
