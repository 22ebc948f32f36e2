"""``msagv view FILE`` and the ``--view`` options of ``msagv run``, ``msagv plant`` and
``msagv report``: the Rerun view of :mod:`experiments.viewer`.

``--view`` serves Rerun's web viewer (from the rerun-sdk wheel, no internet) on
``--view-port`` (default 9090; the data on 127.0.0.1, port 9876, or ``--view-port`` + 1)
and prints its address; ``--view-save FILE.rrd`` writes the same recording to a file
(``rerun FILE.rrd`` or ``msagv``-free tools open it). A command that served a view keeps
serving after its run until Ctrl-C (``msagv plant``: while the plant runs).
"""

from __future__ import annotations

import argparse
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


def check_view_args(a) -> bool:
    """Refuse bad view options before any work; True when a view is asked for."""
    want = bool(getattr(a, "view", False) or a.view_save)
    if not want:
        if a.view_port is not None:
            raise OptionError("--view-port needs --view")
        return False
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
    if a.view_port is not None:
        kw.update(web_port=a.view_port, grpc_port=a.view_port + 1)
    else:
        kw.update(web_port=WEB_PORT, grpc_port=GRPC_PORT)
    return kw


def announce(view, prog: str) -> None:
    if view is not None and view.url:
        print(f"{prog}: view at {view.url}", file=sys.stderr, flush=True)


def serve_until_stopped(view, prog: str) -> None:
    """Keep a served view up until Ctrl-C or SIGTERM (nothing to do for a saved one)."""
    if view is None or not view.url:
        return
    stop = threading.Event()
    old = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    print(f"{prog}: serving the view at {view.url} (Ctrl-C to stop)", file=sys.stderr,
          flush=True)
    try:
        while not stop.wait(0.5):
            pass
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        view.close()


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
