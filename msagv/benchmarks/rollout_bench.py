"""Batch-rollout throughput: the numba kernels against a single-thread C reference.

What is timed is one call of the batch rollout of the paper's model (MODEL_MF: Magic
Formula tires, linearly implicit trapezoidal step) on one batch of candidate decision
vectors, as the annealer makes once per iteration: ``batch`` = the default
:class:`controller.MPCSettings` chain count, its ``N_p`` and ``dt``. Implementations:

* ``numba_simd``: :data:`controller.rollout.FAST`'s ``rollout_batch``, the controller's
  prediction (tiles of ``LANES`` candidates in structure-of-arrays form, SIMD across them,
  the vectorisable transcendentals of :mod:`controller.approx`), one thread;
* ``numba_simd_parallel``: the same, its tiles over numba's threads (the cores available);
* ``numba_serial``: :data:`controller.rollout.EXACT`'s ``rollout_batch``, the same kernels
  on the math library's functions (scalar calls: no SIMD), one thread;
* ``c_fast``: ``controller/mirrors/rollout_ref.c`` (the same prediction, operation for
  operation; its indices from a header generated from :mod:`plant.layout`),
  ``gcc -O3 -march=native -ffast-math`` (numba compiles these kernels with fastmath and
  for the host CPU);
* ``c_strict``: the same source, ``gcc -O3 -march=native -ffp-contract=off`` (IEEE order:
  reproduces the numba results to rounding, see tests/test_rollout_ref.py).

The C library is compiled into a temporary directory when the benchmark runs and loaded
with ctypes (:mod:`numpy.ctypeslib`). Every implementation is called from Python, one
call per batch, so each time includes that call's dispatch: numba's dispatcher (typing
its 12 arguments, ~1.5 us), and for C a ctypes call given the arrays' addresses, resolved
once like the buffers the controller reuses (the numpy.ctypeslib-checked call costs
~40 us per call here, mostly ``ndpointer.from_param``, and is reported separately as
``overhead_us_ndpointer``). ``overhead_us`` is the same call on an empty batch;
``call - overhead`` is the compute.

Inputs are realistic: the reference and the state of ``controller.make_case('curve', 25)``
at ``T0`` s into the run (on a bend, the state slightly off the reference), decision
vectors drawn like the annealer's proposals (normal, sigma_w = 0.3 rad/s on wheel speeds,
sigma_d = 0.02 rad on steering angles, clipped to the offset box), cycled over a pool so
no two consecutive calls see the same batch. Implementations are timed in interleaved
rounds (a shared machine's load hits all of them alike), after warm-up.

Throughput is in predicted wheel-steps per second, ``batch * N_p * 2n / t_call`` (at the
p50 call time). Ratios are throughput ratios (= inverse time ratios), > 1: the first named
is faster.

Run ``python benchmarks/rollout_bench.py [--axles 2,4,6] [--repeats 2000]``; it prints the
result of :func:`bench_rollout` as JSON. Without gcc (or ``$CC``) the C entries are
``null`` with a reason.
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import json
import math
import os
import platform
import shutil
import subprocess
import tempfile
import time
from functools import partial
from pathlib import Path

import numba
import numpy as np
from numpy.ctypeslib import ndpointer

from msagv.controller import MPCSettings, make_case
from msagv.controller import rollout as _ro
from msagv.controller.mirrors import C_REFERENCE
from msagv.controller.models import MagicFormulaModel
from msagv.plant import default_vehicle, n_axle_vehicle
from msagv.plant import layout as lay

SOURCE = C_REFERENCE
HEADER = "msagv_layout.h"  # generated next to the build from plant.layout.c_header()
SYMBOL = "rollout_batch_mf"
COMMON_FLAGS = ["-std=c99", "-O3", "-march=native", "-fPIC"]
VARIANTS = {
    "fast": COMMON_FLAGS + ["-ffast-math"],
    "strict": COMMON_FLAGS + ["-ffp-contract=off"],
}
T0 = 4.0  # s into the 25 km/h curve case: on a bend
OFFSET = (0.1, -0.05, 0.02)  # x [m], y [m], phi [rad]: state off the reference
POOL = 16  # distinct batches cycled through in the timings
SIGMA_W, SIGMA_D = 0.3, 0.02  # as MPCSettings' proposal scales


# ---- the C reference: build and load ----------------------------------------------------
class CBuildError(RuntimeError):
    """The C reference could not be built or loaded (the message says why)."""


def find_compiler() -> str | None:
    """Path of the C compiler (``$CC``, else gcc), or None."""
    return shutil.which(os.environ.get("CC", "gcc"))


class CRollout:
    """The C reference loaded with ctypes; calls like :func:`controller.rollout.rollout_batch`
    for model 0 (without the model argument)."""

    def __init__(self, lib: ctypes.CDLL, variant: str, flags: list[str], compiler: str,
                 version: str):
        self.variant = variant
        self.flags = flags
        self.compiler = compiler
        self.compiler_version = version
        self._lib = lib  # keeps the library loaded
        f64 = ndpointer(np.float64, flags="C_CONTIGUOUS")
        fw = ndpointer(np.float64, flags="C_CONTIGUOUS,WRITEABLE")
        i64 = ndpointer(np.dtype(ctypes.c_long), flags="C_CONTIGUOUS")
        fn = getattr(lib, SYMBOL)
        fn.restype = None
        fn.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int, f64, f64, f64, ctypes.c_int,
                       i64, f64, f64, f64, f64, fw, fw, fw]
        #: the ctypes function: fn(B, nw, Np, x0, ref, Z, D, block, P, S, wx, wy, poses,
        #: wear, cmds), arrays checked by numpy.ctypeslib (dtype, contiguity only)
        self.fn = fn
        raw = lib[SYMBOL]  # a second function object on the same symbol
        raw.restype = None
        vp = ctypes.c_void_p
        raw.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int, vp, vp, vp, ctypes.c_int,
                        vp, vp, vp, vp, vp, vp, vp, vp]
        #: the same with the arrays as addresses (``a.ctypes.data``), unchecked: what a
        #: caller that resolves its buffers once pays per call
        self.raw = raw

    def __call__(self, x0, ref, Z, block, P, S, wx, wy, poses, wear, cmds) -> None:
        """Checked call: shapes as the numba kernel expects them, outputs written in place."""
        B, D = Z.shape
        nw, Np = wx.shape[0], block.shape[0]
        if (x0.shape != (lay.x0_size(nw),) or ref.shape[0] < Np
                or ref.shape[1:] != (lay.N_REF,) or P.shape != (lay.N_PARAMS,)
                or S.shape != (lay.N_SETTINGS,) or wy.shape != (nw,)
                or poses.shape != (B, Np, lay.N_POSE) or wear.shape != (B, Np, lay.N_WEAR)
                or cmds.shape != (B, 2, nw) or D % (2 * nw)
                or (Np and not 0 <= block.min() <= block.max() < D // (2 * nw))):
            raise ValueError("rollout_ref: inconsistent shapes or block indices")
        self.fn(B, nw, Np, x0, ref, Z, D, np.ascontiguousarray(block, dtype=ctypes.c_long),
                P, S, wx, wy, poses, wear, cmds)


def build_c_rollout(variant: str = "strict", workdir: str | Path | None = None) -> CRollout:
    """Compile ``rollout_ref.c`` with the flags of ``variant`` ('fast' or 'strict') into
    ``workdir`` (default: a temporary directory, removed once the library is loaded) and
    load it. Raises :class:`CBuildError` (no compiler, compile error, load error)."""
    if variant not in VARIANTS:
        raise ValueError(f"variant: expected one of {sorted(VARIANTS)}, got {variant!r}")
    cc = find_compiler()
    if cc is None:
        raise CBuildError(f"no C compiler: {os.environ.get('CC', 'gcc')!r} not found on PATH")
    flags = VARIANTS[variant]
    try:
        version = subprocess.run([cc, "--version"], capture_output=True, text=True,
                                 timeout=30).stdout.splitlines()[0]
    except (OSError, subprocess.SubprocessError, IndexError):
        version = "unknown"
    tmp = None
    if workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="rollout_ref_")
        workdir = tmp.name
    try:
        lib_path = Path(workdir) / f"librollout_ref_{variant}.so"
        obj_path = Path(workdir) / f"rollout_ref_{variant}.o"
        # compile with the variant's flags, link without them: gcc links crtfastmath.o into
        # a shared library linked with -ffast-math, which sets flush-to-zero and
        # denormals-are-zero for the whole process when the library is loaded
        # the layout's indices: a header generated from plant/layout.py for this build
        (Path(workdir) / HEADER).write_text(lay.c_header())
        for cmd in ([cc, *flags, "-I", str(workdir), "-c", "-o", str(obj_path), str(SOURCE)],
                    [cc, "-shared", "-o", str(lib_path), str(obj_path), "-lm"]):
            try:
                res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
            except (OSError, subprocess.SubprocessError) as e:
                raise CBuildError(f"{' '.join(cmd)}: {e}") from None
            if res.returncode != 0:
                raise CBuildError(f"{' '.join(cmd)} failed:\n{res.stderr.strip()}")
        try:
            lib = np.ctypeslib.load_library(lib_path.name, str(lib_path.parent))
        except OSError as e:
            raise CBuildError(f"loading {lib_path}: {e}") from None
        return CRollout(lib, variant, flags, cc, version)
    finally:
        if tmp is not None:
            tmp.cleanup()  # the loaded mapping stays valid after the unlink


# ---- inputs -----------------------------------------------------------------------------
def _vehicle(n: int):
    return default_vehicle() if n == 2 else n_axle_vehicle(n)


def case_inputs(vehicle, settings: MPCSettings, t0: float = T0,
                offset=OFFSET) -> tuple[np.ndarray, np.ndarray]:
    """``(x0, ref)`` of the controller at ``t0`` on the 25 km/h curve case: the reference
    sampled over the horizon, the state on the reference shifted by ``offset``, moving
    with it, every wheel steered kinematically (as Reference.initial_state at t0)."""
    reference, _ = make_case("curve", 25.0)
    ref = np.ascontiguousarray(reference.sample(t0 + settings.dt * np.arange(settings.N_p + 1)))
    x, y, phi, vx, vy, r = ref[0]
    c, s = math.cos(phi), math.sin(phi)
    ub, vb = c * vx + s * vy, -s * vx + c * vy
    lim = vehicle.limits
    delta = []
    for xw, yw in zip(vehicle.wheel_x, vehicle.wheel_y):
        wvx, wvy = ub - r * yw, vb + r * xw
        d = math.atan2(wvy, wvx) if math.hypot(wvx, wvy) > 1e-9 else 0.0
        delta.append(min(max(d, lim.delta_min), lim.delta_max))
    x0 = np.array([x + offset[0], y + offset[1], phi + offset[2], vx, vy, r, *delta])
    return x0, ref


def proposal_batches(model, settings: MPCSettings, batch: int, count: int,
                     seed: int = 0) -> list[np.ndarray]:
    """``count`` batches (batch, D) of decision vectors like the annealer's proposals."""
    rng = np.random.default_rng(seed)
    nw, nb = model.n_wheels, len(settings.blocks)
    sigma = np.tile(np.r_[np.full(nw, SIGMA_W), np.full(nw, SIGMA_D)], nb)
    hi = np.tile(np.r_[np.full(nw, settings.offset_w_max), np.full(nw, settings.offset_d_max)], nb)
    return [np.ascontiguousarray(np.clip(rng.standard_normal((batch, model.dim)) * sigma, -hi, hi))
            for _ in range(count)]


# ---- timing -----------------------------------------------------------------------------
def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _time_thunks(thunks, n: int) -> np.ndarray:
    """Wall time [s] of ``n`` calls, cycling over the prepared zero-argument calls."""
    clock = time.perf_counter_ns
    t = np.empty(n)
    m = len(thunks)
    for i in range(n):
        f = thunks[i % m]
        t0 = clock()
        f()
        t[i] = clock() - t0
    return t * 1e-9


def _rel_diff(a: np.ndarray, b: np.ndarray) -> float:
    """max |a - b| / max |b| (one scale per quantity)."""
    if a.size == 0:
        return 0.0
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


def _outputs(rows: int, Np: int, nw: int):
    return (np.empty((rows, Np, 3)), np.empty((rows, Np, 3)), np.empty((rows, 2, nw)))


def bench_rollout(axles=(2, 4, 6, 8), batch: int | None = None, repeats: int = 2000,
                  warmup: int = 200, rounds: int = 5, seed: int = 0) -> dict:
    """Time one batch-rollout call for each axle count and implementation.

    ``batch`` defaults to MPCSettings().chains (``msagv bench`` uses 32). ``repeats`` timed calls per
    implementation, in ``rounds`` interleaved rounds, after ``warmup`` calls each.
    Returns ``{"settings": ..., "c_build": ..., "axles": {n: result}}``; each result holds,
    per implementation, ``call_us`` (p50, p99, min over the timed calls), ``overhead_us``
    (p50 of the same call on an empty batch), ``wheel_steps_per_s`` and
    ``ns_per_wheel_step`` (at the p50 call time), ``compute_ns_per_wheel_step`` (p50 minus
    overhead; None when the overhead is over half the call); plus ``ratios`` (throughput ratios at the p50 and p99 call times, and of the
    compute alone) and ``agreement`` (max relative difference of poses, wear and first
    commands to numba serial, one scale per quantity). The C entries are timed through
    their address-argument ctypes function (buffers resolved once, as numba's dispatcher
    is given the same arrays); ``overhead_us_ndpointer`` is the empty-batch call through
    the numpy.ctypeslib-checked one. A C implementation that could not be built is
    ``null``, its reason in ``c_build``.
    """
    settings = MPCSettings()
    batch = settings.chains if batch is None else int(batch)
    if batch < 1 or repeats < 1 or rounds < 1:
        raise ValueError("batch, repeats and rounds must be >= 1")
    cores = _cores()
    threads = min(cores, numba.config.NUMBA_NUM_THREADS)
    numba.set_num_threads(threads)
    c_impls, c_build = _build_c_impls()
    out = {"settings": {"model": "mf (MODEL_MF)", "batch": batch, "N_p": settings.N_p,
                        "dt": settings.dt, "blocks": list(settings.blocks),
                        "case": "curve 25 km/h", "t0_s": T0, "state_offset": list(OFFSET),
                        "sigma_w": SIGMA_W, "sigma_d": SIGMA_D, "batch_pool": POOL,
                        "repeats": repeats, "warmup": warmup, "rounds": rounds,
                        "numba_threads_parallel": threads, "cores": cores,
                        "numba": numba.__version__, "numpy": np.__version__,
                        "python": platform.python_version(), "machine": platform.machine(),
                        "cpu": _cpu_name(),
                        "timed": "one Python call per batch (numba dispatcher / ctypes), "
                                 "perf_counter_ns"},
           "c_build": c_build, "axles": {}}
    for n in axles:
        out["axles"][str(n)] = _bench_axles(n, settings, batch, c_impls, repeats, warmup,
                                            rounds, seed)
    try:
        out["settings"]["numba_threading_layer"] = numba.threading_layer()
    except ValueError:  # no parallel kernel ran (no axles)
        out["settings"]["numba_threading_layer"] = None
    return out


def _build_c_impls() -> tuple[dict, dict]:
    """The C reference in each of VARIANTS: ``({name: CRollout or None}, {name: build})``."""
    c_impls: dict[str, CRollout | None] = {}
    c_build: dict[str, dict] = {}
    for variant in VARIANTS:
        try:
            c = build_c_rollout(variant)
            c_impls[f"c_{variant}"] = c
            c_build[f"c_{variant}"] = {"ok": True, "compiler": c.compiler,
                                       "version": c.compiler_version,
                                       "flags": " ".join(c.flags)}
        except CBuildError as e:
            c_impls[f"c_{variant}"] = None
            c_build[f"c_{variant}"] = {"ok": False, "reason": str(e),
                                       "flags": " ".join(VARIANTS[variant])}
    return c_impls, c_build


class _Case:
    """One axle count's inputs and the thunks that call each implementation on them."""

    def __init__(self, n: int, settings, batch: int, seed: int):
        vehicle = _vehicle(n)
        model = MagicFormulaModel(vehicle, settings)
        self.nw, self.Np, self.D = model.n_wheels, settings.N_p, model.dim
        self.x0, self.ref = case_inputs(vehicle, settings)
        self.Zs = proposal_batches(model, settings, batch, POOL, seed)
        self.empty = [np.empty((0, self.D))]
        self.P, self.S, self.wx, self.wy = model.P, model.S, model.wx, model.wy
        self.block = model.block
        self.cblock = np.ascontiguousarray(model.block, dtype=ctypes.c_long)
        self.keepalive = []  # arrays passed to C by address live as long as this case

    def outputs(self, batch: int):
        return _outputs(batch, self.Np, self.nw)

    def numba_thunks(self, fn, Zlist, outs):
        return [partial(fn, _ro.MODEL_MF, self.x0, self.ref, Z, self.block, self.P, self.S,
                        self.wx, self.wy, *outs) for Z in Zlist]

    def c_thunks(self, c, Zlist, outs):
        # addresses only: keep the arrays alive for as long as the thunks
        self.keepalive.append((Zlist, outs))
        ad = [a.ctypes.data for a in (self.x0, self.ref)]
        fixed = [a.ctypes.data for a in (self.cblock, self.P, self.S, self.wx, self.wy, *outs)]
        return [partial(c.raw, Z.shape[0], self.nw, self.Np, *ad, Z.ctypes.data, self.D,
                        *fixed) for Z in Zlist]

    def c_checked_thunks(self, c, Zlist, outs):
        return [partial(c.fn, Z.shape[0], self.nw, self.Np, self.x0, self.ref, Z, self.D,
                        self.cblock, self.P, self.S, self.wx, self.wy, *outs) for Z in Zlist]

    def makers(self, c_impls: dict) -> dict:
        """name -> (Zlist, outs) -> thunks, for every implementation available."""
        kind = _ro.step_kind(_ro.MODEL_MF, self.P)  # the compiled kernels, called directly
        fast, exact = _ro.FAST.kernels[kind], _ro.EXACT.kernels[kind]
        makers = {"numba_serial": partial(self.numba_thunks, exact["rollout_batch"]),
                  "numba_simd": partial(self.numba_thunks, fast["rollout_batch"]),
                  "numba_simd_parallel": partial(self.numba_thunks,
                                                 fast["rollout_batch_parallel"])}
        for name, c in c_impls.items():
            if c is not None:
                makers[name] = partial(self.c_thunks, c)
        return makers


def _agreement(case: _Case, makers: dict, c_impls: dict, batch: int,
               n_over: int) -> tuple[dict, dict]:
    """Each implementation against numba serial on the first batch (which also compiles or
    loads the kernels), the C library's outputs through its checked entry point too:
    ``(agreement, {C name: p50 of the checked call on an empty batch [s]})``."""
    results = {}
    for name, make in makers.items():
        o = case.outputs(batch)
        make(case.Zs[:1], o)[0]()
        results[name] = o
    base = results["numba_serial"]
    agreement = {name: {q: _rel_diff(o[i], base[i])
                        for i, q in enumerate(("poses", "wear", "cmds"))}
                 for name, o in results.items() if name != "numba_serial"}
    ndp_over = {}
    for name, c in c_impls.items():
        if c is not None:
            o = case.outputs(batch)
            c(case.x0, case.ref, case.Zs[0], case.block, case.P, case.S, case.wx, case.wy, *o)
            agreement[name]["checked_call_identical"] = bool(
                all(np.array_equal(a, b) for a, b in zip(o, results[name])))
            th = case.c_checked_thunks(c, case.empty, case.outputs(0))
            _time_thunks(th, n_over)
            ndp_over[name] = float(np.median(_time_thunks(th, 5 * n_over)))
    return agreement, ndp_over


def _timed(case: _Case, makers: dict, batch: int, warmup: int, rounds: int, per_round: int,
           n_over: int) -> tuple[dict, dict]:
    """Call times of every implementation in interleaved rounds (the garbage collector
    off): ``({name: [arrays of batch calls]}, {name: [arrays of empty calls]})``."""
    work = {name: make(case.Zs, case.outputs(batch)) for name, make in makers.items()}
    idle = {name: make(case.empty, case.outputs(0)) for name, make in makers.items()}
    for name in makers:
        _time_thunks(work[name], warmup)
        _time_thunks(idle[name], max(10, warmup // 4))
    samples = {name: [] for name in makers}
    over = {name: [] for name in makers}
    gc_was = gc.isenabled()
    gc.collect()
    gc.disable()
    try:
        for _ in range(rounds):
            for name in makers:
                samples[name].append(_time_thunks(work[name], per_round))
                over[name].append(_time_thunks(idle[name], n_over))
    finally:
        if gc_was:
            gc.enable()
    return samples, over


def _summary(times, idle, wheel_steps: int) -> dict:
    """One implementation's call-time percentiles and throughput (see bench_rollout)."""
    t = np.concatenate(times)
    p50, p99 = (float(v) for v in np.percentile(t, [50, 99]))
    o50 = float(np.median(np.concatenate(idle)))
    return {
        "call_us": {"p50": p50 * 1e6, "p99": p99 * 1e6, "min": float(t.min()) * 1e6},
        "overhead_us": o50 * 1e6,
        "wheel_steps_per_s": wheel_steps / p50,
        "ns_per_wheel_step": p50 / wheel_steps * 1e9,
        # None when the empty call takes over half the call (then the difference is
        # scheduling noise, e.g. numba's parallel launch on busy cores)
        "compute_ns_per_wheel_step": ((p50 - o50) / wheel_steps * 1e9
                                      if o50 < 0.5 * p50 else None),
        "calls": int(t.size),
    }


def _ratios(impls: dict) -> dict:
    """Throughput ratios at the p50 and p99 call times, and of the compute alone."""
    def ratio(a, b):
        if impls.get(a) is None or impls.get(b) is None:
            return None
        ta, tb = impls[a]["call_us"], impls[b]["call_us"]
        ca, cb = impls[a]["compute_ns_per_wheel_step"], impls[b]["compute_ns_per_wheel_step"]
        return {"p50": tb["p50"] / ta["p50"], "p99": tb["p99"] / ta["p99"],
                "compute_p50": cb / ca if ca and cb else None}

    return {f"{a}/{b}": ratio(a, b) for a, b in (
        ("numba_simd", "c_strict"), ("numba_simd", "c_fast"), ("numba_simd", "numba_serial"),
        ("numba_simd_parallel", "numba_simd"), ("c_fast", "numba_serial"),
        ("c_strict", "numba_serial"), ("c_fast", "c_strict"))}


def _bench_axles(n: int, settings, batch: int, c_impls: dict, repeats: int, warmup: int,
                 rounds: int, seed: int) -> dict:
    """:func:`bench_rollout`'s result for ``n`` axles."""
    per_round = max(1, repeats // rounds)
    n_over = max(20, per_round // 10)
    case = _Case(n, settings, batch, seed)
    makers = case.makers(c_impls)
    agreement, ndp_over = _agreement(case, makers, c_impls, batch, n_over)
    samples, over = _timed(case, makers, batch, warmup, rounds, per_round, n_over)
    wheel_steps = batch * case.Np * case.nw
    impls: dict[str, dict | None] = {}
    for name in ("numba_simd", "numba_simd_parallel", "numba_serial", *c_impls):
        if name not in makers:
            impls[name] = None
            continue
        impls[name] = _summary(samples[name], over[name], wheel_steps)
        if name in ndp_over:
            impls[name]["overhead_us_ndpointer"] = ndp_over[name] * 1e6
    return {"n_wheels": case.nw, "dim": case.D, "wheel_steps_per_call": wheel_steps,
            "impls": impls, "ratios": _ratios(impls), "agreement": agreement}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="rollout_bench", description=__doc__.splitlines()[0])
    ap.add_argument("--axles", default="2,4,6,8", help="comma-separated axle counts")
    ap.add_argument("--repeats", type=int, default=2000, help="timed calls per implementation")
    ap.add_argument("--batch", type=int, default=None, help="candidates per call "
                    "(default: MPCSettings().chains)")
    ap.add_argument("--warmup", type=int, default=200)
    ap.add_argument("--rounds", type=int, default=5, help="interleaved timing rounds")
    a = ap.parse_args(argv)
    axles = tuple(int(s) for s in a.axles.split(",") if s.strip())
    print(json.dumps(bench_rollout(axles, a.batch, a.repeats, a.warmup, a.rounds), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
