"""msagv fmu simulate gives the same metrics as msagv run (same seed, same scenario)."""

from __future__ import annotations

import json

from helpers import run_msagv


def _json(args, cwd):
    """The metrics and the scenario of the result (but the solve times, which are wall
    time, and the plant's name, which is what differs)."""
    out = run_msagv(*args, "--json", timeout=600, cwd=cwd)
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout)
    doc["metrics"].pop("solve_ms")  # wall time differs, everything else must not
    doc["scenario"].pop("plant")
    return doc["metrics"], doc["scenario"]


def test_fmu_simulate_matches_run(tmp_path):
    fmu = tmp_path / "plant.fmu"
    b = run_msagv("fmu", "build", "-o", fmu, timeout=300, cwd=tmp_path)
    assert b.returncode == 0, b.stderr
    opts = ["--case", "curve", "--speed", "30", "--duration", "0.4", "--seed", "5"]
    assert _json(["fmu", "simulate", str(fmu), *opts], tmp_path) == _json(["run", *opts], tmp_path)
    bad = run_msagv("fmu", "simulate", tmp_path / "missing.fmu", cwd=tmp_path)
    assert bad.returncode == 2 and "not found" in bad.stderr
