"""The command line's shared options: one builder per group, and their conversion into a
:class:`experiments.scenario.Scenario`, MPC settings and Zenoh session options.

Argument parsing lives only here and in the commands of this package; the parts below
(plant, controller, bridge, fmu_build, experiments) take typed objects.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import logging
import math
import os
import re
import sys
import tempfile
import traceback
import warnings
from pathlib import Path

from msagv.bridge.session import DEFAULT_ID, DEFAULT_LEASE_MS, SessionOptions, check_id
from msagv.experiments.scenario import AFTER_END, Scenario

from .. import __version__


class OptionError(ValueError):
    """A malformed option value (the message names the option)."""


# ---- every command -----------------------------------------------------------------------
def add_common_args(ap: argparse.ArgumentParser) -> None:
    """``-q``, ``-v`` and ``--version``, the same on every command."""
    g = ap.add_mutually_exclusive_group()
    g.add_argument("-q", "--quiet", action="store_true",
                   help="print only results, warnings and errors (no progress or notes)")
    g.add_argument("-v", "--verbose", action="store_true",
                   help="more detail: debug logging, and the traceback of an error")
    ap.add_argument("--version", action="version", version=f"msagv {__version__}")


def fail(prog: str, err: BaseException | str, a=None, code: int = 2) -> int:
    """Report ``err`` in one line on stderr (with ``-v`` also the traceback of the
    exception being handled); returns ``code`` (2: bad options or input)."""
    if a is not None and getattr(a, "verbose", False) and sys.exc_info()[0] is not None:
        traceback.print_exc(file=sys.stderr)
    print(f"{prog}: {err}", file=sys.stderr)
    return code


# ---- warnings: one style, each once with a count -------------------------------------------
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
_LEAD = re.compile(r"^[^:]{1,40}: ")  # a short leading name: 'TWO 15 km/h: ', 'agv-3axle: '


def warning_kind(text: str) -> str:
    """What makes two warnings the same: their text with the numbers and a short leading
    name (a run's label, a vehicle's name) taken out (``'solve p99 11.6 ms ...'`` and
    ``'TWO 15 km/h: solve p99 12.1 ms ...'`` are one kind)."""
    return _NUMBER.sub("#", _LEAD.sub("", str(text), count=1))


class WarningPrinter:
    """Every warning of one command in one style, ``PROG: warning: text`` on stderr: the
    first of each kind (:func:`warning_kind`) at once, the repeats only counted; at the end
    (:meth:`finish`) one line for each kind that came more than once, with its count.

    It takes the command's own warnings (:func:`warn`), the records of the ``msagv``
    loggers at WARNING and above (:meth:`handler`; below that only with ``verbose``, as
    ``PROG: text``), and Python's warnings (:meth:`showwarning`): ours in the same style,
    third parties' (matplotlib, numba, dask, ...) only with ``verbose``."""

    def __init__(self, prog: str, verbose: bool = False):
        self.prog = prog
        self.verbose = verbose
        self.counts: dict[str, int] = {}
        self.first: dict[str, str] = {}

    def __call__(self, text: str, prog: str | None = None) -> None:
        key = warning_kind(text)
        n = self.counts.get(key, 0)
        self.counts[key] = n + 1
        if n == 0:
            self.first[key] = str(text)
            print(f"{prog or self.prog}: warning: {text}", file=sys.stderr, flush=True)

    def finish(self) -> None:
        for key, n in self.counts.items():
            if n > 1:
                print(f"{self.prog}: warning: the warning \"{self.first[key]}\" (above) came "
                      f"{n} times in all (the same but for its numbers or the run it names)",
                      file=sys.stderr, flush=True)
        self.counts.clear()

    def handler(self) -> logging.Handler:
        printer = self

        class _Handler(logging.Handler):
            def emit(self, record: logging.LogRecord) -> None:
                try:
                    msg = record.getMessage()
                except Exception:  # noqa: BLE001 - a malformed record is not worth a crash
                    return
                if record.levelno >= logging.WARNING:
                    printer(msg)
                elif printer.verbose:
                    print(f"{printer.prog}: {msg}", file=sys.stderr, flush=True)

        return _Handler(logging.DEBUG)

    def showwarning(self, message, category, filename, lineno, file=None, line=None) -> None:
        f = Path(str(filename)).resolve()
        if any(f.is_relative_to(d) for d in _package_dirs()):
            self(str(message))
        elif self.verbose:
            where = Path(str(filename)).parent.name or "python"
            self(f"{where} ({category.__name__}): {message}")


@functools.lru_cache(maxsize=1)
def _package_dirs() -> tuple[Path, ...]:
    """The folders of msagv and its subpackages (installed from several top-level folders)."""
    import importlib.util

    dirs = [Path(__file__).resolve().parent]
    for name in ("plant", "controller", "bridge", "fmu_build", "experiments", "benchmarks"):
        spec = importlib.util.find_spec(f"msagv.{name}")
        if spec is not None and spec.submodule_search_locations:
            dirs += [Path(d).resolve() for d in spec.submodule_search_locations]
    return tuple(dirs)


_PRINTERS: list[WarningPrinter] = []  # the running commands' printers (innermost last)


@contextlib.contextmanager
def warning_style(prog: str, verbose: bool = False, logs: bool = True):
    """Run a command with one :class:`WarningPrinter`: :func:`warn`, the ``msagv``
    loggers (with ``logs``; the Zenoh processes configure their own logging) and Python's
    warnings go through it; its counts are printed at the end."""
    printer = WarningPrinter(prog, verbose)
    lg = logging.getLogger("msagv")
    old = (lg.level, lg.propagate, warnings.showwarning)
    h = None
    if logs:
        h = printer.handler()
        lg.addHandler(h)
        lg.setLevel(logging.DEBUG if verbose else logging.WARNING)
        lg.propagate = False
    warnings.showwarning = printer.showwarning
    _PRINTERS.append(printer)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("default")  # each warning once per place
            yield printer
    finally:
        _PRINTERS.remove(printer)
        warnings.showwarning = old[2]
        if h is not None:
            lg.removeHandler(h)
            lg.setLevel(old[0])
            lg.propagate = old[1]
        printer.finish()


def warn(prog: str, warnings, a=None) -> None:
    """Each warning as one line on stderr, ``PROG: warning: text`` (``-q`` does not hide
    warnings); within a command each kind once, counted (:class:`WarningPrinter`)."""
    for w in warnings:
        if _PRINTERS:
            _PRINTERS[-1](w, prog)
        else:
            print(f"{prog}: warning: {w}", file=sys.stderr)


def note(a, text: str) -> None:
    """An informational line on stderr, unless ``-q``."""
    if not getattr(a, "quiet", False):
        print(text, file=sys.stderr)


PLOT_SUFFIXES = (".png", ".pdf", ".svg", ".jpg", ".jpeg", ".eps", ".ps", ".tif", ".tiff",
                 ".webp")


def _cannot_create_in(directory: Path) -> str | None:
    """None when a file can be created in ``directory``, else the system's reason. Tries it
    for real (an anonymous temporary file, gone when closed): permission bits do not tell
    the whole story (root, read-only mounts, /proc and /sys, full quotas)."""
    try:
        with tempfile.TemporaryFile(dir=directory):
            pass
    except OSError as e:
        return e.strerror or str(e)
    return None


def check_output(path, option: str, directory: bool = False, suffixes=None) -> None:
    """Refuse an output path that cannot be written, before any work is done: a missing
    or unwritable parent directory, a directory where a file is expected (or a file
    where a directory is), an existing file that cannot be written, an unknown file type.
    Writability is tried, not guessed from permission bits (:func:`_cannot_create_in`);
    nothing is left behind."""
    if path is None:
        return
    p = Path(path)
    if suffixes is not None and p.suffix.lower() not in suffixes:
        raise OptionError(f"{option} {path}: the file name must end in one of "
                          f"{', '.join(suffixes)}")
    if directory:
        if p.exists() and not p.is_dir():
            raise OptionError(f"{option} {path}: exists and is not a directory")
        q = p.absolute()
        while not q.exists() and q != q.parent:  # the nearest existing ancestor
            q = q.parent
        if not q.is_dir():
            raise OptionError(f"{option} {path}: {q} is not a directory")
        why = _cannot_create_in(q)
        if why:
            raise OptionError(f"{option} {path}: cannot write in {q} ({why})")
        return
    if p.is_dir():
        raise OptionError(f"{option} {path}: is a directory, expected a file name")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise OptionError(f"{option} {path}: directory {parent} does not exist")
    if p.exists():
        if p.is_file():  # opening for appending changes nothing
            try:
                with open(p, "ab"):
                    pass
            except OSError as e:
                raise OptionError(f"{option} {path}: cannot be written "
                                  f"({e.strerror or e})") from None
        elif not os.access(p, os.W_OK):  # a device or a pipe: never opened to try
            raise OptionError(f"{option} {path}: not writable")
        return
    why = _cannot_create_in(parent)
    if why:
        raise OptionError(f"{option} {path}: cannot write in {parent} ({why})")


def check_distinct(*outputs) -> None:
    """Refuse two output options naming the same file (``("--log", path), ("--json-out",
    path), ...``; None: not given): the second would overwrite the first."""
    seen: dict[Path, str] = {}
    for option, path in outputs:
        if path is None:
            continue
        key = Path(path).absolute().resolve()
        if key in seen:
            raise OptionError(f"{option} {path}: the same file as {seen[key]} (one would "
                              f"overwrite the other)")
        seen[key] = option


def parse_assignments(text: str | None, what: str = "--initial") -> dict[str, float]:
    """``name=value,name=value`` -> ``{name: value}`` (values must be finite numbers)."""
    out: dict[str, float] = {}
    if not text:
        return out
    for part in str(text).split(","):
        part = part.strip()
        if not part:
            continue
        if "=" not in part:
            raise OptionError(f"{what}: expected name=value, got '{part}'")
        k, v = (s.strip() for s in part.split("=", 1))
        try:
            val = float(v)
        except ValueError:
            raise OptionError(f"{what}: {k}: '{v}' is not a number") from None
        if not math.isfinite(val):
            raise OptionError(f"{what}: {k}: must be finite, got {v}")
        out[k] = val
    return out


# ---- the scenario ------------------------------------------------------------------------
def add_case_args(ap: argparse.ArgumentParser, default_case: str = "curve") -> None:
    ap.add_argument("--scenario", metavar="FILE",
                    help="a scenario TOML (docs/SCENARIOS.md); the options below override it")
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--case", choices=["curve", "line"], default=None,
                   help=f"the paper's Case 1 (curve) or Case 2 (line) (default: {default_case})")
    g.add_argument("--trajectory", metavar="FILE",
                   help="a t,x,y,phi CSV to track instead (t in s from the run's start, x, y "
                        "in m, phi in rad; docs/SCENARIOS.md)")
    ap.add_argument("--speed", metavar="KMH",
                    help="speed in km/h, or a profile 't:kmh,t:kmh,...' (default: 15 curve, 10 line)")
    ap.add_argument("--mass", type=float, metavar="KG", help="override the vehicle's mass [kg]")
    ap.add_argument("--vehicle", metavar="FILE", help="vehicle TOML (default: built-in paper-2axle)")
    ap.add_argument("--duration", type=float, metavar="S",
                    help="vehicle time to run (default: the whole reference)")
    ap.add_argument("--after-end", choices=list(AFTER_END), default=None,
                    help="past the reference's end the reference goes on straight at its last "
                         "heading and speed: 'continue' runs the whole --duration (warning "
                         "past the end; the default), 'stop' ends the run at the end")
    ap.add_argument("--initial", metavar="name=value,...",
                    help="override initial-state values (default: start on the reference); "
                         "vx, vy are global, u= is the forward speed in the body frame")


def add_plant_vehicle_arg(ap: argparse.ArgumentParser) -> None:
    """``--plant-vehicle FILE``: where a plant is simulated, its own vehicle (a model error
    of the controller, as a real vehicle's would be)."""
    ap.add_argument("--plant-vehicle", metavar="FILE",
                    help="the plant's own vehicle TOML (tires, mass, inertia, lags), while the "
                         "controller keeps --vehicle as its belief (default: the same vehicle)")


def add_measurement_noise_arg(ap: argparse.ArgumentParser) -> None:
    """``--measurement-noise V,R[,POS,PHI]``: where a plant is simulated, the noise of what
    the controller measures (``Scenario.measurement_noise``)."""
    ap.add_argument("--measurement-noise", metavar="V,R[,POS,PHI]",
                    help="noise on the state the controller receives, as a real vehicle's "
                         "odometry has: standard deviations of the body's velocity along "
                         "and across it [m/s], the yaw rate [rad/s], x and y [m], the "
                         "heading [rad] (white, Gaussian, seeded by --seed where there is "
                         "one; the plant itself stays exact; docs/SCENARIOS.md); e.g. "
                         "0.01,0.002")


def _choices_help(table: dict, default: str, lead: str = "") -> str:
    """``lead``, then ``name: what it is`` for each entry of a table, the default marked."""
    items = [f"{k}: {v}{' (default)' if k == default else ''}" for k, v in table.items()]
    return lead + "; ".join(items)


def add_mpc_args(ap: argparse.ArgumentParser) -> None:
    """The controller's options; their choices and help come from the tables of methods,
    policies, prediction models and solvers (controller.models, controller.solvers)."""
    from msagv.controller import solvers
    from msagv.controller.models import METHODS, MODELS, POLICIES, MPCSettings

    d = MPCSettings()
    ap.add_argument("--method", choices=list(METHODS), default=None,
                    help=_choices_help(METHODS, d.method, "the wear term of the cost: "))
    ap.add_argument("--policy", choices=list(POLICIES), default=None,
                    help=_choices_help({k: v[1] for k, v in POLICIES.items()}, d.policy,
                                       "decision parametrisation: "))
    ap.add_argument("--model", choices=list(MODELS), default=None,
                    help=_choices_help({k: m.summary for k, m in MODELS.items()}, d.model,
                                       "prediction model: "))
    ap.add_argument("--offset-free", action=argparse.BooleanOptionalAction, default=None,
                    help="carry a disturbance estimated from the measured states in the "
                         "prediction, so that tires or a mass the model does not know leave no "
                         "steady tracking error (default: on for the mf, dugoff and tct models, "
                         "off for kinematic; docs/CONTROLLER.md)")
    ap.add_argument("--adapt", action="store_true", default=None,
                    help="re-estimate the prediction's tires (cornering and longitudinal "
                         "stiffness, friction) while driving: for a vehicle whose tires are "
                         "not known to 10 %% (the mf, dugoff or tct model with the annealer; "
                         "mf with ipopt or acados; on noisy odometry it measures the noise "
                         "and follows it, --set adapt_noise=fixed to keep adapt_sigma_v and "
                         "adapt_window; docs/CONTROLLER.md)")
    ap.add_argument("--seed", type=int, default=None, help=f"annealer seed (default {d.seed})")
    ap.add_argument("--iterations", type=int, help="annealing iterations per solve")
    ap.add_argument("--chains", type=int, help="annealing chains")
    ap.add_argument("--deadline-ms", type=float,
                    help="wall-clock budget per solve (anytime); default: fixed iterations only")
    ap.add_argument("--threads", type=int, help=f"numba threads for the rollout (default {d.threads})")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="any MPCSettings field, e.g. --set L=0.05,0.05,0.05 --set N_p=12")
    ap.add_argument("--solver", choices=list(solvers.SOLVERS), default=None,
                    help=_choices_help({k: e.help for k, e in solvers.SOLVERS.items()},
                                       solvers.DEFAULT_SOLVER, "horizon solver: "))


def add_fmu_args(ap: argparse.ArgumentParser, positional: bool) -> None:
    """The options that choose an FMU as the plant: the FMU (``msagv fmu simulate FILE``
    or ``msagv plant --fmu FILE``), its name mapping file and its parameters."""
    if positional:
        ap.add_argument("fmu", metavar="FILE.fmu", help="an FMI 2.0 co-simulation FMU")
    else:
        ap.add_argument("--fmu", metavar="FILE", help="host this FMI 2.0 co-simulation FMU "
                                                      "instead of the built-in plant")
    ap.add_argument("--map", metavar="FILE", dest="fmu_map",
                    help="the FMU's name mapping (TOML: [map] our_name = \"their_name\", "
                         "optional prefix); see docs/FMU.md")
    ap.add_argument("--param", metavar="name=value,...", dest="fmu_params",
                    help="FMU parameters by our names, e.g. mass=16000,tire_lateral_mu=0.6")


def settings_from_args(a) -> dict:
    """The MPC settings the options ask for, as MPCSettings fields (checked by the
    Scenario when it builds them)."""
    from msagv.controller.models import MPCSettings

    kw = {}
    for k in ("method", "model", "policy", "seed", "iterations", "chains", "threads",
              "offset_free", "adapt"):
        if getattr(a, k, None) is not None:
            kw[k] = getattr(a, k)
    if getattr(a, "deadline_ms", None) is not None:
        kw["deadline_ms"] = a.deadline_ms
    try:
        kw.update(MPCSettings.parse_assignments(getattr(a, "set", []) or []))
    except ValueError as e:
        raise OptionError(f"--set: {e}") from None
    MPCSettings(**kw)  # a bad value is named now, before anything is built
    return kw


def scenario_from_args(a, default_case: str = "curve") -> Scenario:
    """The :class:`Scenario` of the case, MPC and FMU options present on ``a``: the
    scenario file's (``--scenario FILE``) with the options given on top."""
    has = lambda k: getattr(a, k, None)  # noqa: E731 - options a command may lack
    settings = settings_from_args(a) if hasattr(a, "method") else {}
    given = {"vehicle": has("vehicle"), "mass_kg": has("mass"), "speed": has("speed"),
             "duration": has("duration"), "after_end": has("after_end"),
             "solver": has("solver"), "fmu": has("fmu"), "fmu_map": has("fmu_map"),
             "plant_vehicle": has("plant_vehicle")}
    given = {k: v for k, v in given.items() if v is not None}
    if has("from_rest"):
        given["from_rest"] = True
    initial = parse_assignments(has("initial"))
    params = parse_assignments(has("fmu_params"), "--param")
    if has("scenario"):
        base = Scenario.from_file(has("scenario"))
        if has("trajectory") or has("case"):  # the option's reference replaces the file's
            base.case = base.trajectory = None
            if has("trajectory"):
                base.speed = None
        merged = {f.name: getattr(base, f.name) for f in dataclasses.fields(Scenario)}
        merged.update(given)
        merged["settings"] = dict(base.settings, **settings)
        merged["initial"] = dict(base.initial, **initial)
        merged["fmu_params"] = dict(base.fmu_params, **params)
    else:
        merged = dict(given, settings=settings, initial=initial, fmu_params=params)
    merged["trajectory"] = has("trajectory") or merged.get("trajectory")
    merged["case"] = has("case") or merged.get("case")
    if merged["trajectory"] is None and merged["case"] is None:
        merged["case"] = default_case
    if has("measurement_noise") is not None:
        from msagv.plant.sensors import MeasurementNoise

        try:
            noise = MeasurementNoise.parse(has("measurement_noise"), seed=has("seed") or 0)
        except ValueError as e:
            raise OptionError(f"--measurement-noise: {e}") from None
        merged["measurement_noise"] = {} if noise is None else noise.as_dict()
    pv = has("plant_vehicle")
    if pv is not None and not Path(pv).is_file():
        raise OptionError(f"--plant-vehicle: no such file {pv}")
    sc = Scenario(**merged)
    if pv is not None:
        sc.actual_vehicle(sc.resolve_vehicle())  # loads it and checks its wheels now
    return sc


# ---- tire life ----------------------------------------------------------------------------
def add_tire_price_arg(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--tire-price", type=float, metavar="PRICE",
                    help="price of one tire (any currency): the cost per km of the tires, "
                         "with the vehicle file's [tire.wear] calibration (overrides its "
                         "price; docs/WEAR.md)")


def check_tire_price(a, vehicle) -> None:
    """Refuse ``--tire-price`` that is not a price, or that cannot be used: a cost per km
    needs a tire life, which needs the vehicle's ``[tire.wear]`` calibration."""
    price = getattr(a, "tire_price", None)
    if price is None:
        return
    if not (math.isfinite(price) and price >= 0):
        raise OptionError(f"--tire-price: must be a finite number >= 0, got {price:g}")
    if vehicle.tire_wear is None:
        raise OptionError(f"--tire-price: {vehicle.name} has no [tire.wear] calibration, so no "
                          f"tire life and no cost per km (docs/WEAR.md: the abradability, or a "
                          f"known life on a known duty)")


def tire_price(a, vehicle) -> float | None:
    """The price per tire: ``--tire-price``, else the vehicle file's ``[tire.wear] price``."""
    price = getattr(a, "tire_price", None)
    if price is not None:
        return float(price)
    return None if vehicle.tire_wear is None else vehicle.tire_wear.price


# ---- the Zenoh session -------------------------------------------------------------------
def add_session_args(ap: argparse.ArgumentParser, router: bool = False) -> None:
    g = ap.add_argument_group("Zenoh session")
    if not router:
        g.add_argument("--id", default=DEFAULT_ID,
                       help=f"vehicle id: keys msagv/ID/... (default {DEFAULT_ID}); several "
                            f"vehicles share one bus by id")
        g.add_argument("--mode", choices=["peer", "client"], default="peer",
                       help="zenoh session mode (client: through a router, e.g. msagv router)")
    g.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)")
    g.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to listen on, e.g. tcp/127.0.0.1:7448 (repeatable)")
    g.add_argument("--zenoh-config", metavar="FILE",
                   help="a zenoh JSON5 config file, merged with the defaults (loopback, "
                        "scouting off): what it sets explicitly wins; the options above win "
                        "over it")
    g.add_argument("--secure", metavar="DIR",
                   help="mutual TLS and access control with the certificates of DIR "
                        "(msagv certs DIR); endpoints become tls/... (docs/SECURITY.md). "
                        "Without it, on the plain bus, identities are taken on trust: any "
                        "peer can answer the params or hold a token as any identity, so a "
                        "lone liar is not told from the plant; set MSAGV_REQUIRE_SECURE=1 "
                        "in production")
    g.add_argument("--lease-ms", type=int, default=DEFAULT_LEASE_MS,
                   help=f"transport lease [ms]: how soon a dead process is noticed "
                        f"(default {DEFAULT_LEASE_MS})")
    if not router:
        g.add_argument("--rt-priority", type=int, default=0, metavar="N",
                       help="run under SCHED_FIFO priority N (1-99; needs CAP_SYS_NICE), so "
                            "a loaded machine delays the periods less (default 0: off)")


def options_from_args(a, router: bool = False) -> SessionOptions:
    """The session's options; a ``--zenoh-config`` file or a ``--secure`` directory that
    is not there is an :class:`OptionError` before any session starts."""
    if a.zenoh_config and not Path(a.zenoh_config).is_file():
        raise OptionError(f"--zenoh-config {a.zenoh_config}: no such file")
    sec = getattr(a, "secure", None)
    if sec and not Path(sec).is_dir():
        raise OptionError(f"--secure {sec}: not a directory (create it with msagv certs {sec})")
    return SessionOptions(id=check_id(getattr(a, "id", DEFAULT_ID)), connect=list(a.connect),
                          listen=list(a.listen),
                          mode="router" if router else a.mode,
                          config_file=a.zenoh_config, lease_ms=a.lease_ms,
                          secure_dir=getattr(a, "secure", None))
