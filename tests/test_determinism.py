"""Bit-identical reruns (issue 29, item 4): an experiment gives the same bytes whether its
kernels were compiled in the process or loaded from numba's on-disk cache.

The mechanism this guards against (controller/approx.py's docstring): a kernel that is not
inlined (the prediction's ``tile``, ``wheel_loop``) is compiled into every kernel that
calls it, each copy optimised with the code around it, and numba's JIT binds every call to
the first copy loaded into the process: the standalone kernel in a process that compiled
it, a caller's own copy in a process that loaded the caller from the cache. With fastmath
flags the copies rounded differently (Case 1, 35 km/h, TWO: e_bar 1.7816685525470328 cold,
1.781668548591469 warm); the kernels are IEEE arithmetic now, so every copy gives the same
bits.

The test runs a short Case 1 (TWO, 1 s) in a subprocess with a fresh ``NUMBA_CACHE_DIR``
twice: first cold (every kernel compiled in the process), then warm (every kernel loaded),
and compares the run's record and trajectory byte for byte (the clock fields aside). It
failed this way before the fix (e_bar and every wear figure differed). Two workers racing
on a cold cache (``make test -n 2``) are the same case: each process runs either the copy
it compiled or one it loaded, and those no longer differ. The cold compile costs about
half a minute of one core.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

# a run record's fields that are clocks, not results (and the solver's times in its metrics
# and its trajectory's columns)
CLOCK_FIELDS = {"cpu_s", "wall_s", "finished"}
CLOCK_METRICS = {"solve_ms"}
# the controller's time-budget warning (controller.mpc: a solve-time percentile over the period)
BUDGET_WARNING = re.compile(r"solve p99 .* exceeds the control period")


def _case1(out: Path, env: dict) -> dict:
    r = subprocess.run(
        [sys.executable, "-m", "msagv", "experiment", "case1", "--duration", "1", "--speeds",
         "35", "--methods", "TWO", "--out", str(out), "--json", "--force", "--no-progress",
         "--jobs", "1"],
        env=env, capture_output=True, text=True, timeout=1200)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout)


def _without_clock_columns(text: str) -> list[list[str]]:
    """The trajectory's rows as written (strings, not parsed numbers), clock columns dropped."""
    rows = [line.split(",") for line in text.splitlines()]
    keep = [i for i, name in enumerate(rows[0]) if name not in CLOCK_METRICS]
    return [[row[i] for i in keep] for row in rows]


def _records(out: Path) -> dict:
    """Each run's record and trajectory (clock fields dropped), by run key."""
    runs = {}
    for p in sorted((out / "runs").glob("*.json")):
        rec = json.loads(p.read_text())
        rec["metrics"] = {k: v for k, v in rec["metrics"].items() if k not in CLOCK_METRICS}
        rec["warnings"] = [w for w in rec["warnings"] if not BUDGET_WARNING.search(w)]
        runs[p.stem] = ({k: v for k, v in rec.items() if k not in CLOCK_FIELDS},
                        _without_clock_columns(p.with_suffix(".csv").read_text()))
    return runs


@pytest.mark.timeout(2400)
def test_cold_and_warm_cache_give_identical_bytes(tmp_path):
    cache = tmp_path / "numba"
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    cold = _case1(tmp_path / "cold", env)
    assert cold["runs"]["executed"] == 1
    assert any(cache.rglob("*.nbc"))  # the first run compiled into the empty cache
    warm = _case1(tmp_path / "warm", env)
    assert warm["runs"]["executed"] == 1
    a, b = _records(tmp_path / "cold"), _records(tmp_path / "warm")
    assert len(a) == 1 and a.keys() == b.keys()
    for key in a:
        assert a[key][0]["status"] == "ok", a[key][0].get("error")
        assert a[key][0] == b[key][0]  # config, metrics, warnings, log
        assert len(a[key][1]) == 101 and len(a[key][1][0]) > 40
        assert a[key][1] == b[key][1]  # the trajectory, every sample as written
    assert [r["metrics"] for r in cold["rows"]] == [r["metrics"] for r in warm["rows"]]
