"""What a run is asked to do, checked before it starts and its solve times after it ends.

A request no vehicle can meet is refused (:class:`ScenarioError`,
one line naming the problem: the command exits 2 before anything runs); a request that
runs but whose result needs a caveat gives a warning, a one-line string that the command
prints on stderr and lists under ``warnings`` in its JSON. The cases (docs/SCENARIOS.md):

* a reference faster than the wheels can roll (``omega_w_max * r_w``): refused; outer
  wheels that only exceed it in turns: warning;
* a path whose lateral acceleration exceeds the tires' ``mu g``: warning;
* a reference no wheel can roll along (every wheel would have to point outside its
  steering range, e.g. driving backwards: the wheels cannot roll backwards,
  ``omega_w >= 0``): refused, naming where on the path; some wheels outside their range
  (a turn too tight for the steering limits): warning;
* a run longer than the reference: warning (the reference continues at its last heading
  and speed, or the run stops at its end with ``after_end = "stop"``);
* a trajectory whose first row is not at t = 0: warning;
* a vehicle whose numbers no wheeled vehicle has (a unit slip: tonnes typed as kg,
  millimetres as metres, ...; :func:`plant.vehicle.plausibility_warnings`): warning;
* solves longer than the control period (more than 5 % of them): warning (after the run).

Headings that jump or look like degrees are refused when a trajectory CSV is read
(:func:`controller.reference.check_headings`).
"""

from __future__ import annotations

import math

import numpy as np

G = 9.81  # m/s^2
KMH = 3.6  # km/h per m/s


class ScenarioError(ValueError):
    """A scenario that cannot be built or run (the message names the field). Defined here,
    below :mod:`experiments.scenario` (which re-exports it), so the checks need not import
    the scenario."""


def reference_checks(vehicle, reference, duration: float, after_end: str = "continue",
                     speed_option: str = "speed") -> list[str]:
    """Warnings for running ``reference`` for ``duration`` s with ``vehicle``; raises
    :class:`ScenarioError` for a speed no wheel can reach.
    ``speed_option`` names the option or key the user set the speed with."""
    from msagv.controller.reference import wheel_velocities

    warnings = []
    t0 = float(reference.t[0])
    end = reference.end_time
    if t0 > 1e-9:
        warnings.append(f"the trajectory starts at t = {t0:g} s but the run starts at t = 0: "
                        f"until then the reference is its first row (a CSV's t is vehicle "
                        f"time from the start of the run)")
    t_last = min(duration, end) if after_end == "stop" else duration
    times, wx, wy = wheel_velocities(reference, vehicle, 0.0, max(t_last, 0.01))
    speeds = np.hypot(wx, wy)
    R = reference.sample(times)
    warnings += steering_checks(vehicle, reference, times, wx, wy, R)
    body = np.hypot(R[:, 3], R[:, 4])
    limit = vehicle.limits.omega_w_max * vehicle.wheel_radius
    if body.max() > limit * (1 + 1e-9):
        k = int(np.argmax(body))
        raise ScenarioError(
            f"{speed_option}: the reference moves at up to {body[k] * KMH:.1f} km/h (t = "
            f"{times[k]:.2f} s) but the wheels roll at most omega_w_max x r_w = "
            f"{vehicle.limits.omega_w_max:g} rad/s x {vehicle.wheel_radius:g} m = "
            f"{limit * KMH:.1f} km/h ({vehicle.name}): no controller can follow it")
    if speeds.max() > limit * (1 + 1e-9):
        k, w = np.unravel_index(int(np.argmax(speeds)), speeds.shape)
        frac = float(np.mean(np.any(speeds > limit, axis=1)))
        warnings.append(
            f"wheel {vehicle.wheel_names[w]} would have to roll at {speeds[k, w] * KMH:.1f} km/h "
            f"at t = {times[k]:.2f} s (the turn adds to the body's speed), above omega_w_max x "
            f"r_w = {limit * KMH:.1f} km/h, over {100 * frac:.0f} % of the run: expect "
            f"tracking errors there")
    a_lat = np.abs(body * R[:, 5])
    mu = vehicle.tire_lateral.mu
    if a_lat.max() > mu * G:
        k = int(np.argmax(a_lat))
        warnings.append(
            f"the path needs a lateral acceleration of {a_lat[k]:.1f} m/s^2 at t = "
            f"{times[k]:.2f} s, more than the tires' mu g = {mu * G:.1f} m/s^2: the vehicle "
            f"will slide off it")
    if duration > end + 1e-9:
        if after_end == "stop":
            warnings.append(
                f"the run stops at t = {end:g} s, the end of {reference.name}, before the "
                f"requested {duration:g} s (after_end stop)")
        else:
            warnings.append(
                f"the run goes {duration - end:g} s past the end of {reference.name} (t = "
                f"{end:g} s): after it the reference continues straight on at its last "
                f"heading and speed (after_end continue; 'stop' ends the run there)")
    return warnings


STEER_TOLERANCE = math.radians(1.0)  # rad past a steering limit that still counts as within
MOVING = 0.1  # m/s: a wheel slower than this is not asked to point anywhere


def _where(times, R, k: int) -> str:
    return f"t = {times[k]:.2f} s (x = {R[k, 0]:.1f} m, y = {R[k, 1]:.1f} m)"


def steering_checks(vehicle, reference, times, wx, wy, R) -> list[str]:
    """The steering angle each wheel needs to roll along the reference, ``atan2(wy, wx)``
    in the body frame, against its range ``[delta_min, delta_max]`` (the wheels never roll
    backwards: ``omega_w >= 0``). When no wheel that has to move can point where it must
    (driving backwards, or crabbing past every wheel's range) the reference cannot be
    driven: :class:`ScenarioError`, naming where. Some wheels past their range (a turn too
    tight for the limits): a warning naming the worst wheel and where."""
    lim = vehicle.limits
    angle = np.arctan2(wy, wx)
    moving = np.hypot(wx, wy) > MOVING
    excess = np.maximum(angle - lim.delta_max, lim.delta_min - angle)
    out = moving & (excess > STEER_TOLERANCE)
    rng = (f"[{math.degrees(lim.delta_min):.0f}, {math.degrees(lim.delta_max):.0f}] deg")
    blocked = moving.any(axis=1) & np.all(out | ~moving, axis=1)
    if blocked.any():
        k = int(np.argmax(blocked))
        share = float(np.mean(blocked)) * 100.0
        c, s = math.cos(R[k, 2]), math.sin(R[k, 2])
        beta = math.degrees(math.atan2(-s * R[k, 3] + c * R[k, 4], c * R[k, 3] + s * R[k, 4]))
        how = (f"drives the vehicle backwards (its velocity {abs(beta):.0f} deg from its "
               f"heading; the wheels cannot roll backwards, omega_w >= 0)" if abs(beta) > 90.0
               else f"moves the vehicle at {abs(beta):.0f} deg to its heading")
        raise ScenarioError(
            f"{reference.name}: the reference {how} from {_where(times, R, k)}, over "
            f"{share:.0f} % of the run: every wheel would have to steer outside its range "
            f"{rng}, so {vehicle.name} cannot drive it (turn the vehicle round in the path, "
            f"or keep the heading within {math.degrees(lim.delta_max):.0f} deg of the "
            f"direction of travel)")
    if not out.any():
        return []
    k, w = np.unravel_index(int(np.argmax(np.where(out, excess, -np.inf))), out.shape)
    share = float(np.mean(out.any(axis=1))) * 100.0
    backwards = " (that is, rolling backwards)" if abs(angle[k, w]) > math.pi / 2 else ""
    return [f"wheel {vehicle.wheel_names[w]} would have to steer to "
            f"{math.degrees(angle[k, w]):.0f} deg{backwards} at {_where(times, R, k)}, outside "
            f"its range {rng}; some wheel is past its range over {share:.0f} % of the run: "
            f"expect tracking errors there (a turn too tight for the steering limits)"]


def initial_checks(vehicle, initial: dict) -> list[str]:
    """A warning when the run starts faster than the wheels can roll (``--initial vx=...``,
    ``u=...``): the vehicle starts sliding, whatever the controller does."""
    v = math.hypot(float(initial.get("vx", 0.0)), float(initial.get("vy", 0.0)))
    limit = vehicle.limits.omega_w_max * vehicle.wheel_radius
    if v <= limit * (1 + 1e-9):
        return []
    return [f"initial: the vehicle starts at {v * KMH:.4g} km/h, faster than its wheels roll "
            f"(omega_w_max x r_w = {limit * KMH:.1f} km/h): it starts sliding (vx, vy are "
            f"m/s)"]


def solve_time_warnings(solve_ms, period: float) -> list[str]:
    """A warning when at least 3 and more than 5 % of the solves took longer than the
    control period (an in-process run waits for them; a real vehicle, or a real-time plant,
    would not). A few slow solves on a busy machine are not worth a warning."""
    v = np.asarray([s for s in solve_ms if s is not None and math.isfinite(s)], dtype=float)
    if v.size == 0:
        return []
    limit = 1000.0 * period
    over = int(np.count_nonzero(v > limit))
    if over < 3 or over <= 0.05 * v.size:
        return []
    return [f"{over} of {v.size} solves ({100 * over / v.size:.0f} %) took longer than the "
            f"control period of {limit:g} ms (p50 {np.percentile(v, 50):.1f} ms, max "
            f"{v.max():.1f} ms): in real time this controller would miss its periods on this "
            f"machine (fewer iterations, --deadline-ms or fewer axles)"]
