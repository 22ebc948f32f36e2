"""Offset-free tracking: a constant body-frame disturbance estimated from the measured states
and carried by the prediction.

With tires (or a mass, a floor, a slope) that the model does not know, the prediction of
every MPC is wrong by a force that changes slowly, and the closed loop settles into a steady
tracking bias. The remedy of offset-free MPC (Pannocchia and Rawlings 2003; Maeder, Borrelli
and Morari 2009) is a disturbance model with as many integrating states as tracked outputs,
estimated from the measurements, that the prediction carries. Here it is a body-frame
disturbance ``d = (d_u, d_v, d_r)``:

- dynamic models (mf, dugoff, tct): accelerations [m/s^2, m/s^2, rad/s^2] added to the body's
  equations of motion (eq. 17: ``u' = F_x / m + r v + d_u``, ``v' = F_y / m - r u + d_v``,
  ``r' = M_z / I_z + d_r``), constant over the horizon;
- the kinematic model: a twist offset [m/s, m/s, rad/s] added to the body twist the wheels
  command.

The estimate (:class:`DisturbanceObserver`) compares, each control period ``T``, the body
velocity measured at ``t`` with the model's one-period prediction from the state measured at
``t - T`` under the command sent then and the current ``d`` (the controller's own kernels at
step ``T``; the predicted velocity is read off the predicted pose exactly, by inverting the
trapezoidal update). The prediction error ``e`` (body frame of the measured heading) updates

    dynamic:    d <- d + e / tau              (e / T is the acceleration the model missed)
    kinematic:  d <- d + (T / tau) e          (e is the twist the model missed)

a first-order filter with time constant ``tau`` (``MPCSettings.disturbance_tau``) on the
disturbance that explains the last period: the steady-state Kalman filter of a random-walk
disturbance with no measurement noise model. A constant model error then leaves no steady
tracking error: at a steady state the prediction with ``d`` reproduces the measured motion,
and the MPC's optimum puts that motion on the reference. ``|d|`` is bounded
(``disturbance_max``) so that a state jump (a reset, a teleport) cannot wind it up; a period
that is not one control period after the last (a lost or repeated state) skips the update.
"""

from __future__ import annotations

import math

import numpy as np

from msagv.plant import layout as lay

from . import rollout as _ro

SLOTS = [lay.S_DIST_U, lay.S_DIST_V, lay.S_DIST_R]


class OnePeriod:
    """The prediction model's step over one control period ``T`` from a measured state under
    the commands sent (the kernels' raw-command policy, one block of one step): what the
    observer and the online adaptation compare the measurements with."""

    def __init__(self, model, period: float):
        nw = model.n_wheels
        self.model = model
        self.period = float(period)
        self.kinematic = model.model_id == _ro.MODEL_KINEMATIC
        self.S = model.S.copy()
        self.S[lay.S_DT] = self.period
        self.S[lay.S_POLICY] = lay.POLICY_RAW
        self.S[lay.S_STRIDE] = 2 * nw
        self._block = np.zeros(1, dtype=np.int64)
        self.poses = np.empty((1, 1, lay.N_POSE))
        self._wear = np.empty((1, 1, lay.N_WEAR))
        self._cmds = np.empty((1, 2, nw))
        self._ref = np.zeros((2, lay.N_REF))

    def predict(self, x0: np.ndarray, z: np.ndarray, P: np.ndarray, d, ref=None
                ) -> tuple[float, float, float, float]:
        """``(phi, vx, vy, r)`` one period after ``x0`` under the raw commands ``z``
        (omega_w, then omega_s) with the parameters ``P`` and the disturbance ``d``. The
        velocity is read off the predicted pose exactly: the trapezoidal update ``x1 = x0 +
        T (v0 + v1) / 2`` inverted (the kinematic model's forward Euler ``x1 = x0 + T v1``)."""
        self.S[SLOTS] = d
        if ref is not None:
            self._ref[:] = ref[:2]
        x0 = np.ascontiguousarray(x0, dtype=float)
        zz = np.ascontiguousarray(z, dtype=float).reshape(1, -1)
        _ro.EXACT.rollout_batch(self.model.model_id, x0, self._ref, zz, self._block, P, self.S,
                                self.model.wx, self.model.wy, self.poses, self._wear,
                                self._cmds)
        T = self.period
        x1, y1, phi1 = self.poses[0, 0]
        if self.kinematic:
            return (phi1, (x1 - x0[lay.X0_X]) / T, (y1 - x0[lay.X0_Y]) / T,
                    (phi1 - x0[lay.X0_PHI]) / T)
        return (phi1, 2.0 * (x1 - x0[lay.X0_X]) / T - x0[lay.X0_VX],
                2.0 * (y1 - x0[lay.X0_Y]) / T - x0[lay.X0_VY],
                2.0 * (phi1 - x0[lay.X0_PHI]) / T - x0[lay.X0_R])


class LastPeriod:
    """The last control period as an estimator sees it: the state measured at ``t`` (and
    the actual wheel speeds measured with it, where the state carries them), then the raw
    command sent for it (omega_w, then omega_s) and that solve's first two reference rows.
    The disturbance observer and the online adaptation each keep one."""

    def __init__(self, period: float):
        self.period = float(period)
        self.clear()

    def clear(self) -> None:
        self.t = self.x0 = self.omega_w = self.z = self.ref = None

    def measured(self, t: float, x0: np.ndarray, omega_w=None):
        """Take the state measured at ``t`` (``omega_w``: the actual wheel speeds, or None):
        the last period's ``(x0, z, ref, omega_w)`` if it was commanded and ended one period
        (within a quarter) before ``t``, else None."""
        done = (self.z is not None and abs((t - self.t) - self.period) <= 0.25 * self.period)
        out = (self.x0, self.z, self.ref, self.omega_w) if done else None
        self.t, self.x0, self.z, self.ref = t, x0.copy(), None, None
        self.omega_w = None if omega_w is None else np.array(omega_w, dtype=float).reshape(-1)
        return out

    def commanded(self, om_w: np.ndarray, om_s: np.ndarray, ref: np.ndarray | None) -> None:
        """The command sent for the last measured state, held over T (and ``ref``'s first
        two rows, for TCT, which holds the forward speed at the reference's)."""
        if self.x0 is not None:
            self.z = np.r_[om_w, om_s].astype(float)
            self.ref = None if ref is None else np.array(ref[:2], dtype=float)


def body_frame(phi: float, vx: float, vy: float, r: float) -> np.ndarray:
    """A global-frame velocity ``(vx, vy, r)`` in the body frame of heading ``phi``."""
    c, s = math.cos(phi), math.sin(phi)
    return np.array([c * vx + s * vy, -s * vx + c * vy, r])


class DisturbanceObserver:
    """The offset-free disturbance of one prediction model (module docstring).

    Parameters
    ----------
    model : the controller's prediction model (:mod:`controller.models`); its ``S`` carries
        the estimate into every solver's prediction (slots ``S_DIST_*``).
    period : the control period T [s].
    tau : the filter's time constant [s] (> 0).
    limit : bounds of ``|d|`` per component: (translational, rotational), in the units of
        the model's disturbance.
    """

    def __init__(self, model, period: float, tau: float, limit: tuple[float, float]):
        if not (tau > 0 and period > 0):
            raise ValueError("disturbance observer: tau and period must be > 0")
        self.model = model
        self.period = float(period)
        self.tau = float(tau)
        self.kinematic = model.model_id == _ro.MODEL_KINEMATIC
        # TCT holds the forward speed at the reference's: no longitudinal disturbance
        self.lateral_only = model.model_id == _ro.MODEL_TCT
        self.limit = np.array([limit[0], limit[0], limit[1]], dtype=float)
        self.step = OnePeriod(model, period)
        self.last = LastPeriod(period)
        self.reset()

    def reset(self) -> None:
        """Forget the estimate and the last state (d = 0)."""
        self.d = np.zeros(3)
        self.model.S[SLOTS] = 0.0
        self.last.clear()
        self.updates = 0

    def update(self, t: float, x0: np.ndarray) -> np.ndarray:
        """Take the state measured at ``t`` (the MPC's state vector): compare it with the
        prediction from the last period's state and command, update ``d`` and put it into
        the model's ``S``. Returns ``d``."""
        last = self.last.measured(t, x0)
        if last is not None:
            xp, z, ref, _ = last
            _, vx, vy, r = self.step.predict(xp, z, self.model.P, self.d, ref)
            e = body_frame(x0[lay.X0_PHI], x0[lay.X0_VX] - vx, x0[lay.X0_VY] - vy,
                           x0[lay.X0_R] - r)
            if self.lateral_only:
                e[0] = 0.0
            gain = (self.period / self.tau) if self.kinematic else (1.0 / self.tau)
            self.d = np.clip(self.d + gain * e, -self.limit, self.limit)
            self.updates += 1
        self.model.S[SLOTS] = self.d
        return self.d

    def commanded(self, om_w: np.ndarray, om_s: np.ndarray, ref: np.ndarray | None = None
                  ) -> None:
        """The command sent for the state of the last :meth:`update` (held over T), and the
        reference rows of that solve (``R[:2]``)."""
        self.last.commanded(om_w, om_s, ref)

    def as_dict(self) -> dict:
        """The estimate for reports: ``d_u``, ``d_v``, ``d_r`` and the number of updates."""
        return {"d_u": float(self.d[0]), "d_v": float(self.d[1]), "d_r": float(self.d[2]),
                "updates": int(self.updates)}
