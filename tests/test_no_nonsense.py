"""No silent nonsense, second round (issue 21): what a new user trips on is refused in one
line with exit 2 before any work, or run with a warning in one style; nothing is run before
every output path is known to be writable; a recording's report names what was run; the
viewer listens on loopback unless told otherwise.

Most commands run through the dispatcher in this process (``msagv.cli.main``); the
processes (``msagv plant``, ``msagv controller``, ``msagv view``) as subprocesses."""

from __future__ import annotations

import csv
import re
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


# ---- references no vehicle can drive, files in the wrong units --------------------------------
def forward_then_back(path, metres=10.0, kmh=8.0, dt=0.1):
    """Forward ``metres`` along x, then back again, the heading kept at 0 (the issue's)."""
    v = kmh / 3.6
    n = int(round(metres / v / dt))
    rows = [(round(k * dt, 6), (k if k <= n else 2 * n - k) * v * dt, 0.0, 0.0)
            for k in range(2 * n + 1)]
    return write_csv(path, rows)


def circle(path, radius, kmh, seconds, dt=0.1):
    """A left turn on a circle of ``radius`` from the origin, heading along the path."""
    v = kmh / 3.6
    rows = []
    for k in range(int(round(seconds / dt)) + 1):
        a = v * k * dt / radius
        rows.append((round(k * dt, 6), radius * math.sin(a), radius * (1 - math.cos(a)), a))
    return write_csv(path, rows)


def test_a_path_that_drives_backwards_is_refused_saying_where(tmp_path, capsys):
    csv_ = forward_then_back(tmp_path / "back.csv")
    log = tmp_path / "log.csv"
    rc, out, err = run(capsys, "run", "--trajectory", csv_, "--log", log)
    assert rc == 2 and out == "" and not log.exists()
    line, = err.strip().splitlines()
    # 10 m at 8/3.6 m/s: the turnaround row is at t = 4.5 s; the reference's velocity is a
    # central difference, so it points backwards from the next sample on
    assert "back: the reference drives the vehicle backwards" in line
    m = re.search(r"from t = ([\d.]+) s \(x = ([\d.]+) m", line)
    assert 4.45 <= float(m.group(1)) <= 4.6 and float(m.group(2)) == pytest.approx(10.0, abs=0.2)
    assert "omega_w >= 0" in line and "[-90, 90] deg" in line
    # the forward half alone is a fine run (the check looks only as far as the run goes)
    rc, out, err = run(capsys, "run", "--trajectory", csv_, "--duration", "0.3", "--json")
    assert rc == 0 and not [w for w in json.loads(out)["warnings"] if "steer" in w]


def test_a_turn_too_tight_for_the_steering_range_warns_naming_the_wheel(tmp_path, capsys):
    # radius 0.8 m, wheels 1 m out and 3 m ahead/behind: the inner wheels' velocity is
    # (v (1 - 1/0.8), +-3 v/0.8) in the body frame: 93.8 deg off the axis, past the 90 deg
    # stops (and the outer wheels' 68.2 deg is within them)
    csv_ = circle(tmp_path / "tight.csv", 0.8, 3.0, 5.0)
    rc, out, err = run(capsys, "run", "--trajectory", csv_, "--duration", "0.2", "--json",
                       "--iterations", "5")
    doc = json.loads(out)
    w, = [w for w in doc["warnings"] if "would have to steer" in w]
    angle = math.degrees(math.atan2(3.0 / 0.8, 1 - 1 / 0.8))
    # the two inner (left) wheels need +-93.8 deg: the warning names one of them
    m = re.match(r"wheel (11|21) would have to steer to (-?\d+) deg \(that is, rolling "
                 r"backwards\)", w)
    assert rc == 0 and m and abs(int(m.group(2))) == round(angle), w
    assert (int(m.group(2)) > 0) == (m.group(1) == "11")  # front wheel left, rear right
    assert "outside its range [-90, 90] deg" in w
    assert f"msagv run: warning: {w}" in err


def test_t_in_milliseconds_is_refused_naming_the_unit(tmp_path, capsys):
    rows = [(1000.0 * k * 0.1, k * 0.1 * 8 / 3.6, 0.0, 0.0) for k in range(200)]
    ms = write_csv(tmp_path / "ms.csv", rows)
    rc, out, err = run(capsys, "run", "--trajectory", ms, "--duration", "1")
    # 44.2 m in 19 900 "s": 0.008 km/h read as seconds, 8.0 km/h read as milliseconds
    assert rc == 2 and f"{ms}: t looks like milliseconds" in err and "8.0 km/h" in err
    assert len(err.strip().splitlines()) == 1
    # the same path in seconds runs; a slow creep shorter than 10 minutes is not ms
    s = write_csv(tmp_path / "s.csv", [(r[0] / 1000.0, *r[1:]) for r in rows])
    creep = write_csv(tmp_path / "creep.csv", [(k * 5.0, k * 0.1, 0.0, 0.0) for k in range(100)])
    for ok in (s, creep):
        rc, out, err = run(capsys, "run", "--trajectory", ok, "--duration", "0.1", "--json")
        assert rc == 0, err


@pytest.mark.parametrize("sep, name", [(";", "semicolons"), ("\t", "tabs")])
def test_a_csv_separated_otherwise_is_refused_naming_the_separator(sep, name, tmp_path,
                                                                     capsys):
    f = write_csv(tmp_path / "semi.csv", [(0, 0, 0, 0), (0.1, 0.2, 0, 0), (0.2, 0.4, 0, 0)],
                  sep=sep)
    rc, out, err = run(capsys, "run", "--trajectory", f, "--duration", "0.1")
    assert rc == 2 and f"{f}:1: the columns are separated by {name}" in err
    assert len(err.strip().splitlines()) == 1
