"""No silent nonsense, second round (issue 21): what a new user trips on is refused in one
line with exit 2 before any work, or run with a warning in one style; nothing is run before
every output path is known to be writable; a recording's report names what was run; the
viewer listens on loopback unless told otherwise.

Most commands run through the dispatcher in this process (``msagv.cli.main``); the
processes (``msagv plant``, ``msagv controller``, ``msagv view``) as subprocesses."""

from __future__ import annotations

import csv
import json
import math
import os
import time
from pathlib import Path

import pytest

from helpers import ROOT, msagv, run_msagv

from msagv.cli import main

SCEN = ROOT / "scenarios"
# No file can be created in /proc, for root neither (permission bits and os.access say it
# can: only trying tells)
NOWHERE = Path("/proc")
needs_proc = pytest.mark.skipif(not (NOWHERE / "self").is_dir(), reason="needs Linux's /proc")


def run(capsys, *args):
    """``msagv ARGS`` through the dispatcher: (exit code, stdout, stderr)."""
    rc = main([str(a) for a in args])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def write_csv(path, rows, header=("t", "x", "y", "phi"), sep=","):
    with open(path, "w", newline="") as f:
        w = csv.writer(f, delimiter=sep)
        w.writerow(header)
        w.writerows(rows)
    return path


# ---- output paths: tried before anything runs ---------------------------------------------
# (command line, option as the error names it); every output option of every command
IN_PROCESS_OUTPUTS = [
    (["run", "--duration", "30", "--log", "{out}.csv"], "--log"),
    (["run", "--duration", "30", "--json-out", "{out}.json"], "--json-out"),
    (["run", "--duration", "30", "--plot", "{out}.png"], "--plot"),
    (["run", "--duration", "30", "--wear-plot", "{out}.png"], "--wear-plot"),
    (["run", "--duration", "30", "--view-save", "{out}.rrd"], "--view-save"),
    (["fmu", "simulate", "{fmu}", "--duration", "30", "--log", "{out}.csv"], "--log"),
    (["fmu", "build", "-o", "{out}.fmu"], "-o"),
    (["experiment", "case1", "--duration", "1", "-o", "{out}"], "--out"),
    (["experiment", "case1", "--duration", "1", "-o", "{tmp}/e", "--json-out", "{out}.json"],
     "--json-out"),
    (["report", "{rec}", "--json-out", "{out}.json"], "--json-out"),
    (["report", "{rec}", "--log", "{out}.csv"], "--log"),
    (["report", "{rec}", "--plot", "{out}.png"], "--plot"),
    (["report", "{rec}", "--wear-plot", "{out}.png"], "--wear-plot"),
    (["bench", "plant", "--quick", "--json-out", "{out}.json"], "--json-out"),
    (["plant", "replay", "--inputs", "{rec}", "--out", "{out}.csv"], "--out"),
    (["demo", "--plot", "{out}.png"], "--plot"),
    (["demo", "--json-out", "{out}.json"], "--json-out"),
    (["demo", "--out", "{out}"], "--out"),
    (["certs", "{out}"], "DIR"),
    (["view", "{rec}", "--no-serve", "--view-save", "{out}.rrd"], "--view-save"),
]


@needs_proc
@pytest.mark.parametrize("args, option", IN_PROCESS_OUTPUTS,
                         ids=[" ".join(a[:2]) + " " + o for a, o in IN_PROCESS_OUTPUTS])
def test_every_output_path_is_tried_before_any_work(args, option, tmp_path, capsys,
                                                    monkeypatch):
    monkeypatch.chdir(tmp_path)
    fill = {"out": str(NOWHERE / "msagv-out"), "tmp": str(tmp_path),
            "rec": str(tmp_path / "missing.mcap"), "fmu": str(tmp_path / "missing.fmu")}
    t0 = time.perf_counter()
    rc, out, err = run(capsys, *[a.format(**fill) for a in args])
    assert rc == 2 and out == "", err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and f": {option} {NOWHERE}/msagv-out" in lines[0], err
    assert "cannot write in /proc" in lines[0]
    assert list(tmp_path.iterdir()) == []  # nothing run, nothing written
    assert time.perf_counter() - t0 < 60  # refused at once, not after the work


@needs_proc
@pytest.mark.parametrize("cmd", ["plant", "controller"])
def test_the_processes_try_their_recording_path_first(cmd, tmp_path):
    extra = ["--duration", "1"] if cmd == "plant" else ["--exit-at-end"]
    r = run_msagv(cmd, "--record", NOWHERE / "msagv-rec.mcap", *extra, timeout=60)
    assert r.returncode == 2 and "--record" in r.stderr and "/proc" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_an_existing_read_only_file_is_tried_too(tmp_path, capsys):
    from msagv.args import OptionError, check_output

    f = tmp_path / "old.json"
    f.write_text("keep me")
    check_output(f, "--json-out")  # writable: fine, and unchanged
    assert f.read_text() == "keep me"
    f.chmod(0o444)
    if os.geteuid() == 0:  # root writes read-only files: the try says so, and it is right
        check_output(f, "--json-out")
    else:
        with pytest.raises(OptionError, match="cannot be written"):
            check_output(f, "--json-out")
    assert f.read_text() == "keep me"
