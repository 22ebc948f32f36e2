"""msagv bench: the dispatcher runs its sections and reports their structure (never timing:
the figures themselves are only reported, see docs/PERFORMANCE.md)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from msagv.benchmarks.suite import SECTIONS
from msagv.cli import bench_main as main


@pytest.mark.timeout(300)
def test_quick_plant_and_controller_json(capsys):
    assert main(["--quick", "--json", "plant", "controller"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["machine"]["cores"] >= 1
    assert set(d["plant"]["rtf"]) == {"2", "4", "6"}
    assert all(v > 0 for v in d["plant"]["rtf"].values())
    for n in ("2", "4", "6"):
        sm = d["controller"][n]["solve_ms"]
        assert 0 < sm["p50"] <= sm["p99"] <= sm["max"]
        # the timed controller is the working one
        assert d["controller"][n]["detail"]["e_bar"]["max"] < 2.0


def test_unknown_section_exits_2(capsys):
    assert main(["warp"]) == 2
    assert "unknown section" in capsys.readouterr().err
    assert set(SECTIONS) == {"plant", "rollout", "controller", "optimality", "nmpc", "transport",
                             "fmu"}


@pytest.mark.timeout(300)
def test_controller_bench_takes_a_vehicle_file(capsys):
    """``--vehicle FILE`` measures that vehicle (labelled by its name, its wheel count from
    the file); a missing file or no vehicle at all is a one-line usage error."""
    from pathlib import Path

    from msagv.benchmarks.controller_bench import main as cb

    f = Path(__file__).resolve().parents[1] / "scenarios" / "vehicles" / "agv-3axle.toml"
    assert cb(["--axles", "", "--vehicle", str(f), "--seconds", "0.1", "--repeats", "1"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert list(d["axles"]) == ["agv-3axle"]
    r = d["axles"]["agv-3axle"]
    assert r["n_wheels"] == 6 and r["solves"] == 10
    assert 0 < r["solve_ms"]["p50"] <= r["solve_ms"]["max"]
    for bad in (["--vehicle", "no-such.toml"], ["--axles", ""]):
        with pytest.raises(SystemExit) as e:
            cb(bad)
        assert e.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert "error:" in err[-1] and len([x for x in err if "error" in x]) == 1


@pytest.mark.timeout(600)
def test_polish_bench_parts_and_variants():
    """polish_bench: each part of a solve is timed inside the solve (their sum at most the
    solve's time at the median), the steps and refreshes counted; the variants are solved
    on the same states, the default's cost over itself exactly 1 (the solve is
    deterministic) and every variant restores the polish's settings."""
    from msagv.benchmarks.polish_bench import PARTS, VARIANTS, bench_polish, bench_variants
    from msagv.controller import sa_kernel as sk
    from msagv.plant import default_vehicle

    v = default_vehicle()
    r = bench_polish(v, n_states=2, repeats=1)
    assert (r["D"], r["M"], r["solves"]) == (24, 60, 2)
    assert sum(r[p + "_ms"]["mean"] for p in PARTS) <= r["solve_ms"]["mean"]
    assert sum(r[p + "_cpu_ms"]["mean"] for p in PARTS) <= r["solve_cpu_ms"]["mean"]
    # No part's CPU time is compared with its wall time: they are two clocks (the thread's
    # CPU clock and the monotonic one), and on CI's machine a part of 0.1 ms once took more
    # of the first than of the second. The two sums above compare one clock with itself.
    assert all(r[p + "_cpu_ms"]["mean"] >= 0 for p in PARTS)
    assert all(r[p + "_ms"]["p50"] > 0 for p in ("anneal", "jacobian", "steps"))
    assert r["polish_steps_mean"] >= 1 and 0 <= r["refreshes_mean"] <= sk.GN_REFRESH
    assert all(t > 0 for t in r["linear_algebra"].values())
    assert set(r["differences_cpu_us"]) == {"from_nominal", "from_x0"}
    assert all(t > 0 for t in r["differences_cpu_us"].values())
    before = (sk.GN_MUS.copy(), sk.GN_ALPHAS.copy(), sk.GN_REFRESH)
    w = bench_variants(v, n_states=2, repeats=1)
    assert set(VARIANTS) <= set(w)
    assert w["default"]["cost_over_default"] == {"p50": 1.0, "p90": 1.0, "max": 1.0, "min": 1.0}
    assert np.array_equal(sk.GN_MUS, before[0]) and np.array_equal(sk.GN_ALPHAS, before[1])
    assert sk.GN_REFRESH == before[2]


def test_front_anatomy_finds_the_dear_step_of_a_blind_front(tmp_path, capsys):
    """benchmarks/front_anatomy.py over hand-made stored runs: the blind front is 80 kJ up to
    0.4 cm and 44 kJ from there (a step of 1.8x its cheapest run), so the step's share of the
    log grid is the share of grid points below 0.4 cm; the ratio there is 40/80; an unknown
    plant is one line and exit 2."""
    import json as _json

    import numpy as np

    from msagv.benchmarks import front_anatomy as fa

    runs = tmp_path / "runs"
    runs.mkdir()
    made = [("TWO", True, 0.2, 40e3), ("TWO", True, 1.0, 30e3),
            ("NTWO", False, 0.2, 80e3), ("NTWO-wheel", False, 0.4, 44e3),
            ("NTWO-wheel", False, 1.0, 44e3)]
    for i, (fam, aware, e, w) in enumerate(made):
        doc = {"status": "ok", "metrics": {"W_tw": w, "e_lat_rms_cm": e},
               "spec": {"tags": {"family": fam, "level": None, "model": "wrong",
                                 "plant": "tires x0.9", "aware": aware,
                                 "scenario": "mismatch random-1-15kmh, tires x0.9"}}}
        (runs / f"{i}.json").write_text(_json.dumps(doc))
    rows = fa.load(str(tmp_path), "tires x0.9")
    assert len(rows) == 5 and fa.load(str(tmp_path), "tires x1.1") == []
    d = fa.anatomy(rows)
    grid = np.geomspace(d["lo"], d["hi"], fa.GRID)
    assert d["lo"] == 0.2 and d["share"] == pytest.approx(np.mean(grid < 0.4))
    assert d["on"] == pytest.approx(0.5)
    assert fa.main([str(tmp_path), "--plant", "tires x0.9"]) == 0
    assert "random-1-15kmh" in capsys.readouterr().out
    with pytest.raises(SystemExit) as ex:
        fa.main([str(tmp_path), "--plant", "tires x1.1"])
    assert ex.value.code == 2
