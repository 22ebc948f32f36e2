"""The paper's metrics (eq. 28-33) and solve-time percentiles.

Units as the paper reports them: wear work in J, e_x and e_y in cm, e_phi in degrees;
``e_bar`` is the plain mean of those three numbers (the paper's mixed units, eq. 32) and
``Omega`` its two-branch balance index (eq. 33).
"""

from __future__ import annotations

import math

import numpy as np

from msagv.plant.signals import WEAR_FIELDS

from .cost_terms import wrap

METRIC_KEYS = ["W_tw", "W_s", "W_alpha", "W_t", "e_x_cm", "e_y_cm", "e_phi_deg", "e_bar",
               "Omega", "e_lat_rms_cm", "e_lat_max_cm", "e_pos_max_cm", "e_phi_max_deg",
               "solve_ms", "steps", "distance_m", "W_tw_per_km"]
MIN_DISTANCE_M = 1.0  # m: a run that moved less gives no per-km figures (None)
WEAR_ROUNDING_J = 1e-6  # J: wear work above minus this is the integrator's rounding of 0


def wrap_angle(a):
    """Angle wrapped to (-pi, pi]."""
    return wrap(np.asarray(a, dtype=float))  # the cost's own (controller.cost_terms)


def omega_index(W_tw: float, e_bar: float) -> float:
    """Performance Balance Index, paper eq. (33):
    ``W_tw^0.5 e_bar^0.1`` if e_bar < 50, else ``W_tw^0.5 e_bar^0.5``."""
    if W_tw < 0 or e_bar < 0:
        raise ValueError("Omega: W_tw and e_bar must be >= 0")
    return math.sqrt(W_tw) * e_bar ** (0.1 if e_bar < 50 else 0.5)


def tracking_errors(pose: np.ndarray, ref_pose: np.ndarray) -> dict[str, float]:
    """RMSE in x, y [cm] and heading [deg] (heading error wrapped), e_bar (eq. 32), the
    RMS and largest lateral (cross-track) error [cm], and the largest distance from the
    reference's position [cm] and heading error [deg] (what the wear floor holds a motion
    to: controller.floors)."""
    pose = np.asarray(pose, dtype=float)
    ref_pose = np.asarray(ref_pose, dtype=float)
    ex = 100.0 * math.sqrt(np.mean((pose[:, 0] - ref_pose[:, 0]) ** 2))
    ey = 100.0 * math.sqrt(np.mean((pose[:, 1] - ref_pose[:, 1]) ** 2))
    ep = math.degrees(math.sqrt(np.mean(wrap_angle(pose[:, 2] - ref_pose[:, 2]) ** 2)))
    # lateral (cross-track) error: the position error across the reference's heading, the
    # physical accuracy a path-tracking engineer asks for (e_x, e_y mix along- and
    # cross-track error with the path's direction)
    c, s_ = np.cos(ref_pose[:, 2]), np.sin(ref_pose[:, 2])
    lat = -(pose[:, 0] - ref_pose[:, 0]) * s_ + (pose[:, 1] - ref_pose[:, 1]) * c
    dist = np.hypot(pose[:, 0] - ref_pose[:, 0], pose[:, 1] - ref_pose[:, 1])
    return {"e_x_cm": ex, "e_y_cm": ey, "e_phi_deg": ep, "e_bar": (ex + ey + ep) / 3.0,
            "e_lat_rms_cm": 100.0 * math.sqrt(np.mean(lat ** 2)),
            "e_lat_max_cm": 100.0 * float(np.abs(lat).max()),
            "e_pos_max_cm": 100.0 * float(dist.max()),
            "e_phi_max_deg": math.degrees(float(np.abs(wrap_angle(pose[:, 2] - ref_pose[:, 2])).max()))}


def percentiles(values, scale: float = 1.0, count: bool = False) -> dict:
    """``{"p50", "p99", "max"}`` (plus ``"n"`` with ``count``) of ``values`` times ``scale``
    (e.g. 1000 for seconds to milliseconds); None (JSON null) when there are no values."""
    v = np.asarray(values, dtype=float).reshape(-1) * scale
    if v.size == 0:
        out = {"p50": None, "p99": None, "max": None}
    else:
        out = {"p50": float(np.percentile(v, 50)), "p99": float(np.percentile(v, 99)),
               "max": float(v.max())}
    if count:
        out["n"] = int(v.size)
    return out


class StreamPercentiles:
    """The p50, p99, largest value and count of a stream of values, in bounded memory (a
    long-running process adds one every period: a list would grow without end).

    The first ``exact`` values are kept: up to that many the figures are
    :func:`percentiles`'s, exactly. Beyond, the values are counted in buckets of relative
    width ``rel`` (a log-scale histogram, as DDSketch: bucket ``i`` holds the values in
    ``(gamma**(i-1), gamma**i]``, ``gamma = (1 + rel) / (1 - rel)``, negative values mirrored,
    values of magnitude below ``TINY`` in one bucket at 0) and p50 and p99 come from the
    buckets: np.percentile's linear interpolation between the two order statistics around
    rank ``q (n - 1)``, each taken as its bucket's centre, which is within ``rel`` (relative)
    of it, so the percentile is within ``rel`` times the interpolation of the two order
    statistics' magnitudes (plus ``TINY``) of the exact one. The largest value and the count
    stay exact. Memory: ``exact`` floats and at most one bucket per factor ``gamma`` of the
    values' range (about 2,300 for durations from 1 us to 100 s at ``rel`` = 0.5 %).
    Non-finite values are not counted."""

    TINY = 1e-9
    HUGE = 1e12  # magnitudes beyond count in the last bucket (the largest value is exact)

    def __init__(self, exact: int = 4096, rel: float = 0.005):
        if exact < 0 or not 0 < rel < 0.5:
            raise ValueError(f"exact >= 0 and 0 < rel < 0.5, got {exact}, {rel}")
        self.exact, self.rel = exact, rel
        self._lg = math.log((1 + rel) / (1 - rel))
        self._top = math.ceil(math.log(self.HUGE) / self._lg)
        self._bot = math.floor(math.log(self.TINY) / self._lg)
        self._values: list[float] | None = []
        self._buckets: dict[int, int] = {}  # signed bucket (0: |v| < TINY) -> count
        self.n = 0
        self.max = -math.inf

    def _bucket(self, v: float) -> int:
        a = abs(v)
        if a < self.TINY:
            return 0
        i = min(max(math.ceil(math.log(a) / self._lg), self._bot + 1), self._top) - self._bot
        return i if v > 0 else -i

    def _centre(self, b: int) -> float:
        if b == 0:
            return 0.0
        i = abs(b) + self._bot
        c = 2.0 * math.exp(i * self._lg) / (1.0 + math.exp(self._lg))
        return c if b > 0 else -c

    def add(self, v: float) -> None:
        v = float(v)
        if not math.isfinite(v):
            return
        self.n += 1
        if v > self.max:
            self.max = v
        b = self._bucket(v)
        self._buckets[b] = self._buckets.get(b, 0) + 1
        if self._values is not None:
            if self.n <= self.exact:
                self._values.append(v)
            else:
                self._values = None  # from now on the buckets answer

    @property
    def exact_now(self) -> bool:
        """Whether :meth:`percentiles` is exact (at most ``exact`` values came)."""
        return self._values is not None

    def __len__(self) -> int:
        """The memory held: values kept plus buckets (bounded, whatever ``n``)."""
        return (len(self._values) if self._values is not None else 0) + len(self._buckets)

    def _order_stat(self, order: list[tuple[int, int]], r: int) -> float:
        seen = 0
        for b, c in order:
            seen += c
            if r < seen:
                return self._centre(b)
        return self._centre(order[-1][0])

    def percentiles(self, scale: float = 1.0, count: bool = False) -> dict:
        """As :func:`percentiles` of the values (approximate beyond ``exact``: see above)."""
        if self._values is not None:
            return percentiles(self._values, scale=scale, count=count)
        order = sorted(self._buckets.items(), key=lambda bc: self._centre(bc[0]))
        out = {}
        for name, q in (("p50", 0.5), ("p99", 0.99)):
            r = q * (self.n - 1)
            lo, hi = math.floor(r), math.ceil(r)
            a, b = self._order_stat(order, lo), self._order_stat(order, hi)
            v = min(a + (r - lo) * (b - a), self.max)
            out[name] = float(v * scale)
        out["max"] = float(self.max * scale)
        if count:
            out["n"] = self.n
        return out


def path_length(xy) -> float:
    """The length [m] of the polyline through the points ``xy`` (N, >= 2 columns x, y)."""
    xy = np.asarray(xy, dtype=float)
    if xy.ndim != 2 or len(xy) < 2:
        return 0.0
    return float(np.sum(np.hypot(np.diff(xy[:, 0]), np.diff(xy[:, 1]))))


def work_per_km(work_J, distance_m) -> float | None:
    """Wear work per kilometre driven [J/km]: ``work_J / (distance_m / 1000)``; None when
    the work is unknown or the vehicle moved less than :data:`MIN_DISTANCE_M` (no
    figure rather than a huge one). The study's and the case tables' per-km column."""
    if work_J is None or distance_m is None or not distance_m >= MIN_DISTANCE_M:
        return None
    return float(work_J) / (float(distance_m) / 1000.0)


def compute_metrics(pose, ref_pose, W_start, W_end, solve_ms=(), distance_m=None) -> dict:
    """All metrics of a run.

    ``pose``/``ref_pose``: (N, 3) at the control instants; ``W_start``/``W_end``: the
    plant's integrated wear work (W_s, W_alpha, W_t) at the start and end (eq. 28-30 are
    the sampled sums of the powers; the plant integrates the powers exactly, which is
    their limit). ``solve_ms``: solve times for the percentiles. ``distance_m``: the
    distance the body travelled [m] (default: along ``pose``); with it ``W_tw_per_km``,
    the wear work per km driven [J/km] (:func:`work_per_km`).
    """
    W = np.asarray(W_end, dtype=float) - np.asarray(W_start, dtype=float)
    # Dormand-Prince's 5th-order weights are not all positive, so the integral of a wear
    # power that is (nearly) zero can come out a hair below zero: that is zero
    W = np.where((W < 0) & (W > -WEAR_ROUNDING_J), 0.0, W)
    out = {"W_s": float(W[0]), "W_alpha": float(W[1]), "W_t": float(W[2])}
    out["W_tw"] = out["W_s"] + out["W_alpha"] + out["W_t"]  # eq. (31)
    out.update(tracking_errors(pose, ref_pose))
    out["Omega"] = omega_index(out["W_tw"], out["e_bar"])
    out["solve_ms"] = percentiles(solve_ms)
    out["steps"] = int(len(pose))
    out["distance_m"] = float(path_length(pose) if distance_m is None else distance_m)
    out["W_tw_per_km"] = work_per_km(out["W_tw"], out["distance_m"])
    return {k: out[k] for k in METRIC_KEYS}


def format_table(m: dict, title: str = "") -> str:
    """A small human-readable table of one run's metrics."""
    lines = [title] if title else []
    if m["W_tw"] is None:  # a plant without the optional wear fields
        lines.append("  Omega      n/a (no wear work recorded)")
        lines.append("  W_tw [J]   n/a (no wear work recorded)")
    else:
        lines.append(f"  Omega      {m['Omega']:.4g}")
        lines.append(f"  W_tw [J]   {m['W_tw']:.4g}   (W_s {m['W_s']:.3g}, W_alpha "
                     f"{m['W_alpha']:.3g}, W_t {m['W_t']:.3g})")
    lines.append(f"  e_bar      {m['e_bar']:.3f}   (e_x {m['e_x_cm']:.2f} cm, e_y {m['e_y_cm']:.2f} cm, "
                 f"e_phi {m['e_phi_deg']:.2f} deg)")
    sm = m["solve_ms"]
    if sm.get("p50") is not None:
        lines.append(f"  solve [ms] p50 {sm['p50']:.2f}  p99 {sm['p99']:.2f}  max {sm['max']:.2f}")
    lines.append(f"  steps      {m['steps']}")
    return "\n".join(lines)


WHEEL_WEAR_KEYS = WEAR_FIELDS  # the rows of a per-wheel wear array


def wear_by_wheel(dW, n_wheels: int | None = None) -> dict:
    """Each wheel's and each axle's wear work over a run, from ``dW``: the per-wheel wear
    work at the end minus at the start, shape (3, 2n) with rows W_s, W_alpha, W_t in the
    wheel order 11, 12, 21, ... Returns ``{"wheels": {"11": {"W_s", "W_alpha", "W_t",
    "W_tw"}, ...}, "axles": {"1": {...}, ...}}`` [J]; an axle's values are the sums over
    its two wheels, and the sums over all wheels are the run's W_s ... W_tw."""
    dW = np.asarray(dW, dtype=float)
    nw = dW.shape[1] if n_wheels is None else n_wheels
    if dW.shape != (3, nw) or nw % 2:
        raise ValueError(f"wear_by_wheel: expected (3, 2n) per-wheel wear, got {dW.shape}")

    def entry(cols) -> dict:
        w = dW[:, cols].sum(axis=1)
        return {"W_s": float(w[0]), "W_alpha": float(w[1]), "W_t": float(w[2]),
                "W_tw": float(w.sum())}

    wheels = {f"{k // 2 + 1}{k % 2 + 1}": entry([k]) for k in range(nw)}
    axles = {str(i + 1): entry([2 * i, 2 * i + 1]) for i in range(nw // 2)}
    return {"wheels": wheels, "axles": axles}


def format_wheel_wear(wear: dict | None) -> list[str]:
    """Lines for a run's table: W_tw per axle and per wheel [J] with each one's share."""
    if not wear:
        return ["  per wheel  n/a (no per-wheel wear work recorded)"]
    total = sum(a["W_tw"] for a in wear["axles"].values())

    def share(x):
        return f" ({100.0 * x / total:.0f} %)" if total > 0 else ""

    axles = ", ".join(f"{i}: {a['W_tw']:.4g}{share(a['W_tw'])}" for i, a in wear["axles"].items())
    wheels = ", ".join(f"{k}: {w['W_tw']:.4g}" for k, w in wear["wheels"].items())
    return [f"  per axle   W_tw [J] {axles}", f"  per wheel  W_tw [J] {wheels}"]


# ---- per kilometre and tire life (docs/WEAR.md) -------------------------------------------
def _life(E_per_km: float, k_a: float, V_usable: float, band_mm2: float, price):
    """One tire's figures at ``E_per_km`` J/km: tread loss per 1000 km [mm], life [km]
    (None: it does not wear), cost per km (None without a price)."""
    vol_per_km = k_a * E_per_km  # mm^3/km, Archard: V = k_a W
    loss = 1000.0 * vol_per_km / band_mm2  # mm per 1000 km
    life = V_usable / vol_per_km if vol_per_km > 0 else None
    cost = None if price is None else (price / life if life else 0.0)
    return {"tread_loss_mm_per_1000km": loss, "life_km": life, "cost_per_km": cost}


def wear_per_km(wear: dict | None, distance_m: float, calibration=None,
                wheel_radius: float | None = None, price: float | None = None) -> dict | None:
    """A run's ``wear`` block (:func:`wear_by_wheel`) with what a fleet engineer budgets in:
    ``distance_m``, the distance the body travelled, and ``per_km``: for each wheel, axle
    and the whole vehicle the wear work per km driven ``W_tw_per_km`` [J/km]; with a tire
    wear ``calibration`` (:class:`plant.vehicle.TireWear`, ``wheel_radius`` [m]) also each
    tire's tread loss per 1000 km [mm], projected life [km] and, with ``price`` per tire,
    cost per km, by Archard's law ``V = k_a W`` (docs/WEAR.md):

    * tread loss per km = ``k_a E / (pi D w)``, E the tire's J/km, D = 2 r_w, w the
      tread's width;
    * life = usable depth / tread loss per km = ``V_usable / (k_a E)``;
    * cost per km = price / life.

    An axle's J/km and cost per km are its two tires' sums, its life the shorter and its
    tread loss the faster; the vehicle's likewise over every tire (its life: the first tire
    to reach its limit; its cost per km: each tire replaced at its own life). Without a
    calibration only the J/km; below :data:`MIN_DISTANCE_M` driven, ``per_km`` is None.
    ``calibration`` in the result says where ``k_a`` came from (None: uncalibrated)."""
    if wear is None:
        return None
    out = dict(wear, distance_m=float(distance_m), per_km=None, calibration=None)
    if work_per_km(1.0, distance_m) is None:
        return out
    cal = None
    if calibration is not None:
        k_a = calibration.k_a(wheel_radius)
        V = calibration.usable_volume(wheel_radius)
        band = math.pi * 2000.0 * wheel_radius * calibration.tread_width  # mm^2 per mm depth
        src = ("abradability" if calibration.abradability is not None else
               f"reference life {calibration.reference_life_km:g} km at "
               f"{calibration.reference_work_per_km:g} J/km per tire")
        cal = {"abradability_mm3_per_J": k_a, "from": src,
               "tread_width_mm": calibration.tread_width,
               "usable_depth_mm": calibration.usable_depth, "usable_volume_mm3": V,
               "price_per_tire": price}
    wheels = {}
    for k, w in wear["wheels"].items():
        e = {"W_tw_per_km": work_per_km(w["W_tw"], distance_m)}
        if cal is not None:
            e.update(_life(e["W_tw_per_km"], k_a, V, band, price))
        wheels[k] = e

    def group(keys) -> dict:
        es = [wheels[k] for k in keys]
        g = {"W_tw_per_km": sum(e["W_tw_per_km"] for e in es)}
        if cal is not None:
            lives = [e["life_km"] for e in es if e["life_km"] is not None]
            g.update({"tread_loss_mm_per_1000km": max(e["tread_loss_mm_per_1000km"] for e in es),
                      "life_km": min(lives) if lives else None,
                      "cost_per_km": None if price is None else sum(e["cost_per_km"] for e in es)})
        return g

    names = list(wheels)
    axles = {a: group(names[2 * i:2 * i + 2]) for i, a in enumerate(wear["axles"])}
    vehicle = group(names)
    if cal is not None:
        lives = {k: e["life_km"] for k, e in wheels.items() if e["life_km"] is not None}
        vehicle["first_worn"] = min(lives, key=lives.get) if lives else None
    out["per_km"] = {"wheels": wheels, "axles": axles, "vehicle": vehicle}
    out["calibration"] = cal
    return out


def format_per_km(wear: dict | None) -> list[str]:
    """Lines for a run's table: the wear work per km per axle, and with a calibration each
    axle's tire life, tread loss and cost per km (docs/WEAR.md)."""
    if not wear or wear.get("per_km") is None:
        if wear and "distance_m" in wear:
            return [f"  per km     n/a (the vehicle moved {wear['distance_m']:.2f} m, less than "
                    f"{MIN_DISTANCE_M:g} m)"]
        return []
    pk, d = wear["per_km"], wear["distance_m"]
    ax = ", ".join(f"{a}: {e['W_tw_per_km']:.4g}" for a, e in pk["axles"].items())
    lines = [f"  per km     W_tw [J/km] {ax}; vehicle {pk['vehicle']['W_tw_per_km']:.4g} "
             f"(over {d:.1f} m driven)"]
    cal = wear.get("calibration")
    if cal is None:
        lines.append("  tire life  n/a: the vehicle file has no [tire.wear] calibration "
                     "(docs/WEAR.md)")
        return lines

    def km(v):
        return "no wear" if v is None else (f"{v:,.0f}" if v >= 100 else f"{v:.3g}")

    v = pk["vehicle"]
    life = ", ".join(f"{a}: {km(e['life_km'])}" for a, e in pk["axles"].items())
    loss = ", ".join(f"{a}: {e['tread_loss_mm_per_1000km']:.3g}" for a, e in pk["axles"].items())
    lines.append(f"  tire life  [km] {life}; first tire worn: {v['first_worn']} at "
                 f"{km(v['life_km'])} km (k_a {cal['abradability_mm3_per_J']:.3g} mm^3/J, "
                 f"from {cal['from']})")
    lines.append(f"  tread loss [mm/1000 km] {loss}")
    if v.get("cost_per_km") is not None:
        lines.append(f"  tire cost  {v['cost_per_km']:.4g} per km (all tires, "
                     f"{cal['price_per_tire']:g} per tire)")
    return lines
