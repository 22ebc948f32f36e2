"""What a controller measures: the plant's state with the noise of a real vehicle's sensors.

A simulated plant hands the controller its exact state; a real AGV's odometry does not. Its
body velocities (wheel odometry fused with an IMU) carry noise of about 0.5-2 cm/s, its yaw
rate a gyro's 1-5 mrad/s, its pose a localisation's centimetres. The estimators of the
controller (the offset-free disturbance, the online tire adaptation) read exactly these
signals, so a run with noise shows what they do on a real vehicle.

:class:`MeasurementNoise` adds independent zero-mean Gaussian noise, white from one control
period to the next, to a copy of the state message the controller receives; the plant, its
log and the metrics keep the true state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

# name in a scenario's [measurement_noise] table: (what it perturbs, unit)
FIELDS = {"v": ("the body's velocity, along and across the body, each", "m/s"),
          "r": ("the yaw rate", "rad/s"),
          "pos": ("the position x and y, each", "m"),
          "phi": ("the heading", "rad")}


@dataclass
class MeasurementNoise:
    """Standard deviations of the noise on the measured state (:data:`FIELDS`), and the
    seed of its random stream (the same seed, the same noise)."""

    v: float = 0.0
    r: float = 0.0
    pos: float = 0.0
    phi: float = 0.0
    seed: int = 0
    _rng: np.random.Generator = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        for k in FIELDS:
            val = getattr(self, k)
            if isinstance(val, bool) or not isinstance(val, (int, float)) or not (
                    math.isfinite(val) and val >= 0):
                raise ValueError(f"measurement_noise.{k}: must be a finite standard deviation "
                                 f">= 0 {FIELDS[k][1]}, got {val!r}")
            setattr(self, k, float(val))
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"measurement_noise.seed: must be an integer >= 0, got {self.seed!r}")
        self._rng = np.random.default_rng(self.seed)

    @classmethod
    def from_mapping(cls, d) -> "MeasurementNoise | None":
        """From a scenario's table (``{v, r, pos, phi, seed}``, each optional); None when
        every deviation is 0 (no noise)."""
        if d is None:
            return None
        if not isinstance(d, dict):
            raise ValueError(f"measurement_noise: expected a table of {', '.join(FIELDS)}, seed; "
                             f"got {d!r}")
        unknown = sorted(set(d) - set(FIELDS) - {"seed"})
        if unknown:
            raise ValueError(f"measurement_noise: unknown {', '.join(unknown)} (known: "
                             f"{', '.join(FIELDS)}, seed)")
        noise = cls(**d)
        return noise if noise.active else None

    @classmethod
    def parse(cls, text: str, seed: int = 0) -> "MeasurementNoise | None":
        """From ``V,R[,POS,PHI]`` (the command line's form)."""
        parts = [p.strip() for p in str(text).split(",")]
        if not 2 <= len(parts) <= 4:
            raise ValueError(f"expected V,R[,POS,PHI] (m/s, rad/s, m, rad), got '{text}'")
        try:
            vals = [float(p) for p in parts]
        except ValueError:
            raise ValueError(f"expected numbers V,R[,POS,PHI], got '{text}'") from None
        noise = cls(**dict(zip(FIELDS, vals)), seed=seed)
        return noise if noise.active else None

    @property
    def active(self) -> bool:
        return any(getattr(self, k) > 0 for k in FIELDS)

    def as_dict(self) -> dict:
        return {k: getattr(self, k) for k in (*FIELDS, "seed")}

    def __call__(self, state: dict) -> dict:
        """A copy of the state message with the noise added (the next draws of the stream).
        The velocity's noise is the body frame's (wheel odometry and an IMU measure the
        twist in the body): added to the body-frame velocity of the true heading, then
        turned into the message's frame with the measured heading, so that the heading's
        noise does not reach the body velocity a reader recovers with it."""
        e = self._rng.standard_normal(6)
        out = dict(state)
        phi = state["phi"]
        c, s = math.cos(phi), math.sin(phi)
        u = c * state["vx"] + s * state["vy"] + self.v * e[0]
        w = -s * state["vx"] + c * state["vy"] + self.v * e[1]
        out["phi"] = phi + self.phi * e[5]
        cm, sm = math.cos(out["phi"]), math.sin(out["phi"])
        out["vx"] = cm * u - sm * w
        out["vy"] = sm * u + cm * w
        out["r"] = state["r"] + self.r * e[2]
        out["x"] = state["x"] + self.pos * e[3]
        out["y"] = state["y"] + self.pos * e[4]
        return out
