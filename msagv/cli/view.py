"""``msagv view FILE`` and the ``--view`` options of ``msagv run``, ``msagv plant`` and
``msagv report``: the Rerun view of :mod:`experiments.viewer`.

``--view`` serves Rerun's web viewer (from the rerun-sdk wheel, no internet) on
``--view-port`` (default 9090; the data on port 9876, or ``--view-port`` + 1), both on
loopback (127.0.0.1: this machine only) unless ``--view-host`` says otherwise (with a
warning: the view has no authentication), and prints its address and where it listens;
``--view-save FILE.rrd`` writes the same recording to a file (``rerun FILE.rrd`` or
``msagv``-free tools open it). A command that served a view keeps serving after its run
until Ctrl-C (``msagv plant``: while the plant runs).
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading

from .args import OptionError, add_common_args, check_output, fail


def add_view_args(ap: argparse.ArgumentParser, serve_flag: bool = True) -> None:
    if serve_flag:
        ap.add_argument("--view", action="store_true",
                        help="show the run live in Rerun's web viewer (needs msagv[viewer]); "
                             "prints its address")
    ap.add_argument("--view-save", metavar="FILE.rrd",
                    help="write the Rerun view to FILE.rrd (replay it with the rerun viewer)")
    ap.add_argument("--view-port", type=int, metavar="PORT",
                    help="the web viewer's port (default 9090; the data on PORT + 1, "
                         "default 9876)")
    ap.add_argument("--view-host", metavar="ADDRESS",
                    help="the address the served view listens on (default 127.0.0.1: this "
                         "machine only; 0.0.0.0: every interface, with a warning: anyone who "
                         "reaches the machine sees the view)")


def check_view_args(a) -> bool:
    """Refuse bad view options before any work; True when a view is asked for."""
    want = bool(getattr(a, "view", False) or a.view_save)
    serve = bool(getattr(a, "view", False))
    if not serve:
        for opt, v in (("--view-port", a.view_port), ("--view-host", a.view_host)):
            if v is not None:
                raise OptionError(f"{opt} applies to a served view (--view; msagv view serves "
                                  f"unless --no-serve)")
    if not want:
        return False
    if a.view_host is not None:
        import ipaddress

        try:
            ipaddress.ip_address(a.view_host)
        except ValueError:
            raise OptionError(f"--view-host: expected an IP address (127.0.0.1, 0.0.0.0, "
                              f"::1, ...), got '{a.view_host}'") from None
    check_output(a.view_save, "--view-save", suffixes=(".rrd",))
    if a.view_port is not None and not 1024 <= a.view_port <= 65534:
        raise OptionError(f"--view-port must be 1024..65534, got {a.view_port}")
    from msagv.experiments.viewer import ViewerError, require_rerun

    try:
        require_rerun()
    except ViewerError as e:
        raise OptionError(str(e)) from None
    return True


def view_kwargs(a) -> dict:
    from msagv.experiments.viewer import GRPC_PORT, WEB_PORT

    serve = bool(getattr(a, "view", False))
    kw: dict = {"save": a.view_save, "serve": serve}
    if serve and a.view_host is not None:
        kw["host"] = a.view_host
    if a.view_port is not None:
        kw.update(web_port=a.view_port, grpc_port=a.view_port + 1)
    else:
        kw.update(web_port=WEB_PORT, grpc_port=GRPC_PORT)
    return kw


def exposure_warning(view) -> list[str]:
    """A warning when a served view listens beyond this machine (not on loopback)."""
    import ipaddress

    if view is None or not view.url or ipaddress.ip_address(view.host).is_loopback:
        return []
    return [f"--view-host {view.host}: the view listens on {', '.join(view.listening)}: "
            f"anyone who can reach this machine there sees it (no authentication)"]


def announce(view, prog: str) -> None:
    if view is not None and view.url:
        from .args import warn

        warn(prog, exposure_warning(view))
        print(f"{prog}: view at {view.url} (listening on {', '.join(view.listening)})",
              file=sys.stderr, flush=True)


def serve_until_stopped(view, prog: str) -> None:
    """Keep a served view up until Ctrl-C or SIGTERM (nothing to do for a saved one)."""
    if view is None or not view.url:
        return
    stop = threading.Event()
    old = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    print(f"{prog}: serving the view at {view.url} (listening on "
          f"{', '.join(view.listening)}; Ctrl-C to stop)", file=sys.stderr, flush=True)
    try:
        while not stop.wait(0.5):
            pass
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        close_within(view, CLOSE_S, prog)


CLOSE_S = 10.0  # how long a stopping view waits for Rerun's sinks to finish


def close_within(view, seconds: float, prog: str) -> None:
    """``view.close()``, but at most ``seconds`` long: once (a CI machine at load 5) the
    served viewer's flush never returned after SIGTERM with a browser connected, and the
    process hung. What was logged is served or saved already; if the close hangs, say so
    and end the process."""
    done = threading.Event()
    err: list[BaseException] = []

    def close():
        try:
            view.close()
        except BaseException as e:  # noqa: BLE001 - reported below
            err.append(e)
        finally:
            done.set()

    threading.Thread(target=close, name="view-close", daemon=True).start()
    if not done.wait(seconds):
        print(f"{prog}: warning: the viewer did not stop within {seconds:g} s; exiting "
              "without waiting for it", file=sys.stderr, flush=True)
        sys.stdout.flush()
        os._exit(0)
    if err:
        raise err[0]


def main(argv: list[str]) -> int:
    """``msagv view FILE``: a recording (MCAP or the first format) in Rerun."""
    prog = "msagv view"
    ap = argparse.ArgumentParser(
        prog=prog, description="Show a recording (msagv plant/controller --record) in Rerun: "
                               "the vehicle, each wheel coloured by its wear power, the "
                               "reference and the driven path, errors and wear over time.")
    ap.add_argument("recording", metavar="FILE")
    ap.add_argument("--run", type=int, default=-1,
                    help="which plant run of the recording, 0 = first (default: the last)")
    ap.add_argument("--no-serve", action="store_true",
                    help="only write --view-save, do not serve the web viewer")
    add_view_args(ap, serve_flag=False)
    add_common_args(ap)
    a = ap.parse_args(argv)
    a.view = not a.no_serve
    from msagv.bridge.recording import RecordingError
    from msagv.experiments.recorded import ReportError
    from msagv.experiments.viewer import ViewerError, view_recording

    try:
        if a.no_serve and not a.view_save:
            raise OptionError("--no-serve needs --view-save FILE.rrd")
        check_view_args(a)
        view, n = view_recording(a.recording, view_kwargs(a), a.run)
        if a.view:
            from .args import warn

            warn(prog, exposure_warning(view))
    except (OptionError, RecordingError, ReportError, ViewerError, KeyError, TypeError,
            OSError) as e:
        return fail(prog, e, a)
    if a.view_save:
        print(f"{prog}: {n} states of {a.recording} -> {a.view_save}", file=sys.stderr)
    if a.view:
        serve_until_stopped(view, prog)
    else:
        view.close()
    return 0
