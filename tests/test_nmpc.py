"""The real-time gradient NMPC (controller/acados_rti.py: acados SQP-RTI).

* the same problem: the OCP's cost at a dynamically consistent point equals the IPOPT
  NLP's (smoothed) cost of the same decision vector, for each wear method;
* keep-best: a solve never returns a higher exact cost than its warm start, at states of a
  closed loop and from deliberately poor warm starts;
* the commands respect eq. (27)'s bounds; a short closed loop tracks;
* over Zenoh (slow): the controller process in lockstep equals the in-process run;
* ``msagv run --solver acados --json`` prints clean JSON even when the solver is built in
  that run (acados' build output must not reach stdout);
* without acados, a clear error (in Python and on the command line, exit 2).

The acados tests skip when acados is not installed (``make test`` installs it apart:
``pip install --no-deps --target .venv/acados comma-deps-acados``).
"""

from __future__ import annotations

import functools
import json
import os
import shutil
import sys

import numpy as np
import pytest

from msagv.controller import make_case
from msagv.controller.loop import closed_loop
from msagv.plant import layout as lay
from msagv.controller.models import MPCSettings
from msagv.controller.mpc import MPC, ControllerError
from msagv.plant import Plant, default_vehicle
from helpers import assert_commands_within_bounds

VEH = default_vehicle()


def _have_acados() -> bool:
    if not (shutil.which("make") and shutil.which(os.environ.get("CC", "cc"))):
        return False  # acados builds its solvers with make and a C compiler
    try:
        from msagv.controller.acados_rti import require_acados

        require_acados()
        return True
    except ControllerError:
        return False


HAVE_ACADOS = _have_acados()
needs_acados = pytest.mark.skipif(not HAVE_ACADOS, reason="acados not installed (make test "
                                  "installs comma-deps-acados into .venv/acados)")


@functools.lru_cache(maxsize=None)
def _mpc(method: str = "two", adapt: bool = False):
    from msagv.controller.mpc import MPC

    ref, _ = make_case("curve", 25.0)
    return MPC(VEH, MPCSettings(method=method, adapt=adapt), ref, solver="acados")


def _state(init, t=0.0, **over):
    st = {"t": t, **{k: init[k] for k in ("x", "y", "phi", "vx", "vy", "r")},
          "delta": [init[f"delta_{w}"] for w in VEH.wheel_names]}
    st.update(over)
    return st


def _ocp_cost(ocp, x0, R, z, zprev, extra) -> tuple[float, np.ndarray]:
    """acados' cost at the trajectory of ``z`` from ``x0`` (what each solve linearises at),
    with the stage parameters after the reference row ``extra`` (the disturbance, then with
    ``--adapt`` the tires): ``(cost, trajectory)``."""
    s0 = np.r_[x0, zprev, np.ones(3)]
    S = ocp.trajectory(s0, R, z, extra[:3], extra[3:] if ocp.adapt else None).copy()
    U = np.zeros((ocp.N, ocp.nu))
    zb = zprev
    for b, k in enumerate(ocp.starts):
        U[k] = z[b * ocp.nu:(b + 1) * ocp.nu] - zb
        zb = z[b * ocp.nu:(b + 1) * ocp.nu]
    sv = ocp.solver
    for k in range(ocp.N + 1):
        sv.set(k, "p", np.r_[R[k], extra])
        sv.set(k, "x", S[k])
        if k < ocp.N:
            sv.set(k, "u", U[k])
    return sv.get_cost(), S


@needs_acados
@pytest.mark.parametrize("method", ["two", "two-energy", "ntwo"])
def test_ocp_cost_is_the_nlp_cost(method):
    """At the trajectory of a decision vector z (what each solve linearises at), acados'
    cost equals the IPOPT NLP's cost of z with the same smoothing: the same problem."""
    from msagv.controller.ipopt import HorizonNLP, IpoptOptions

    mpc = _mpc(method)
    ocp = mpc.solver.ocp
    nlp = HorizonNLP(mpc.model, mpc.settings, IpoptOptions(eps_w=mpc.solver.options.eps_w))
    ref, init = make_case("curve", 25.0)
    rng = np.random.default_rng(3)
    mpc.reset()
    st = _state(init(VEH), t=2.0)
    mpc.step(st)  # (acados' cost evaluation reads weights that its first solve prepares)
    x0, R, zprev, warm = mpc.horizon_problem(st)
    slots = [lay.S_DIST_U, lay.S_DIST_V, lay.S_DIST_R]
    for dist in ([0.0, 0.0, 0.0], [0.3, -0.2, 0.05], [0.0, 0.0, 0.0]):
        # the offset-free disturbance: acados' stage parameter, IPOPT's NLP parameter
        mpc.model.S[slots] = dist
        z = np.clip(warm + rng.normal(0.0, 1.0, warm.size) * mpc.horizon.sigma, mpc.horizon.lower, mpc.horizon.upper)
        zprev = rng.normal(0.0, 0.1, zprev.size)
        J_ocp, _ = _ocp_cost(ocp, x0, R, z, zprev, np.asarray(dist, float))
        J_nlp = float(nlp.cost_fn(z, nlp.params(x0, R, zprev)))
        assert J_ocp == pytest.approx(J_nlp, rel=1e-10)
        # and the smoothing adds at most eps_w per wheel and term to the exact cost's powers
        assert J_nlp >= mpc.horizon.cost(x0, R, z, zprev) - 1e-9 * J_nlp


@needs_acados
def test_the_adapted_tires_are_stage_parameters():
    """With ``--adapt`` the tires the online adaptation moves are acados' stage parameters
    (after the reference row and the disturbance): with the model's tires scaled as the
    adaptation scales them, the OCP's cost at a decision vector's trajectory is IPOPT's NLP
    cost with the same tires, and differs from the cost with the file's tires."""
    from msagv.controller import adaptation as ad
    from msagv.controller.ipopt import HorizonNLP, IpoptOptions

    mpc = _mpc("ntwo", adapt=True)
    ocp = mpc.solver.ocp
    nlp = HorizonNLP(mpc.model, mpc.settings, IpoptOptions(eps_w=mpc.solver.options.eps_w))
    ref, init = make_case("curve", 25.0)
    rng = np.random.default_rng(5)
    mpc.reset()
    st = _state(init(VEH), t=2.0)
    mpc.step(st)
    x0, R, zprev, warm = mpc.horizon_problem(st)
    dist = np.array([0.1, -0.2, 0.03])
    mpc.model.S[[lay.S_DIST_U, lay.S_DIST_V, lay.S_DIST_R]] = dist
    file_tires = ad.values(mpc.model)
    costs = []
    try:
        for theta in ((1.0, 1.0, 1.0), (1.44, 0.8, 1.2), (0.64, 1.3, 0.8)):
            mpc.adaptation._apply(np.array(theta), mpc.model.P)  # as an update does
            mpc.model.S[list(ad.TIRE_S)] = file_tires[len(ad.TIRE_P):] / theta[0]
            tires = ad.values(mpc.model)
            z = np.clip(warm + rng.normal(0.0, 0.5, warm.size) * mpc.horizon.sigma,
                        mpc.horizon.lower, mpc.horizon.upper)
            J_ocp, S = _ocp_cost(ocp, x0, R, z, zprev, np.r_[dist, tires])
            J_nlp = float(nlp.cost_fn(z, nlp.params(x0, R, zprev)))
            assert J_ocp == pytest.approx(J_nlp, rel=1e-10), theta
            # the file's tires give another trajectory: the parameters were taken
            S_file = ocp.trajectory(np.r_[x0, zprev, np.ones(3)], R, z, dist, file_tires)
            costs.append(np.abs(S_file[:, :3] - S[:, :3]).max())
    finally:
        mpc.reset()
        mpc.model.S[[lay.S_DIST_U, lay.S_DIST_V, lay.S_DIST_R]] = 0.0
    assert costs[0] == 0.0 and min(costs[1:]) > 1e-4, costs


@needs_acados
def test_never_above_the_warm_start():
    """With keep_best (the default) the answer's exact cost is at most the warm start's
    (the better of the shifted previous solution and zero offsets), and Command.cost is
    that exact cost; at closed-loop states and from poor warm starts."""
    mpc = _mpc()
    ref, init = make_case("curve", 25.0)
    mpc.reset()
    plant = Plant(VEH, initial=init(VEH))
    seen = []
    rng = np.random.default_rng(11)

    def check(state, z_before, cmd):
        t, x0 = mpc._state_vector(state)
        s = mpc.settings
        R = np.ascontiguousarray(ref.sample(t + s.dt * np.arange(s.N_p + 1)))
        zprev = z_before[: mpc.model.stride]
        warm = np.clip(mpc.horizon.shifted(z_before), mpc.horizon.lower, mpc.horizon.upper)
        Jw = min(mpc.horizon.cost(x0, R, warm, zprev),
                 mpc.horizon.cost(x0, R, np.zeros_like(warm), zprev))
        assert cmd.cost == pytest.approx(mpc.horizon.cost(x0, R, mpc.z, zprev), rel=1e-12)
        assert cmd.cost <= Jw * (1 + 1e-12), (t, cmd.cost, Jw)
        seen.append(cmd.cost < Jw * (1 - 1e-9))

    mpc.on_solve = check
    try:
        closed_loop(plant, mpc, ref, 0.5)
        # poor warm starts: random offsets over the whole box
        st = _state(init(VEH), t=0.5)
        for _ in range(5):
            mpc.z = rng.uniform(mpc.horizon.lower, mpc.horizon.upper)
            mpc.step(st)
    finally:
        mpc.on_solve = None
    assert len(seen) == 55
    assert sum(seen) > 40  # it improves, not only keeps


@needs_acados
def test_commands_within_bounds():
    mpc = _mpc()
    mpc.reset()
    assert_commands_within_bounds(mpc, VEH)


@needs_acados
def test_closed_loop_tracks():
    """One second on the Case 1 curve at 25 km/h: it tracks, and no worse than twice the
    annealer's error on the same run."""
    ref, init = make_case("curve", 25.0)
    mpc = _mpc()
    mpc.reset()
    log = closed_loop(Plant(VEH, initial=init(VEH)), mpc, ref, 1.0)
    m = log.metrics()
    assert m["steps"] == 100 and m["W_tw"] > 0
    assert np.all(np.isfinite(log.cost))
    sa = closed_loop(Plant(VEH, initial=init(VEH)), MPC(VEH, MPCSettings(), ref), ref,
                     1.0).metrics()
    assert m["e_bar"] < 0.5 and m["e_bar"] < 2.0 * sa["e_bar"], (m, sa)


@needs_acados
def test_msagv_run_solver_acados_json_with_a_fresh_build(capfd, tmp_path, monkeypatch):
    """``msagv run --solver acados --json`` builds the solver into an empty cache and still
    prints one clean JSON document on stdout (capfd: file-descriptor level)."""
    from msagv.cli import run as run_cmd

    monkeypatch.setenv("MSAGV_ACADOS_CACHE", str(tmp_path))
    argv = ["--case", "curve", "--speed", "15", "--duration", "0.5", "--json",
            "--solver", "acados"]
    assert run_cmd.main(argv) == 0
    out = capfd.readouterr()
    doc = json.loads(out.out)
    assert doc["scenario"]["solver"] == "acados"
    assert doc["metrics"]["steps"] == 50 and doc["metrics"]["e_bar"] < 0.5
    assert any(p.name == "ok" for p in tmp_path.rglob("ok"))  # built there


def test_without_acados_a_clear_error(monkeypatch, capsys, tmp_path):
    import msagv.controller.acados_rti as ar
    from msagv.cli import run as run_cmd

    monkeypatch.setattr(ar, "_acados", None)
    monkeypatch.setattr(ar, "_acados_error", None)
    monkeypatch.setenv(ar.ACADOS_ENV, str(tmp_path))
    monkeypatch.setattr(sys, "prefix", str(tmp_path))
    monkeypatch.setitem(sys.modules, "acados", None)  # import acados -> ImportError
    ref, _ = make_case("curve", 15.0)
    with pytest.raises(ControllerError, match="comma-deps-acados"):
        MPC(VEH, MPCSettings(), ref, solver="acados")
    rc = run_cmd.main(["--case", "curve", "--duration", "0.1", "--solver", "acados", "--json"])
    out = capsys.readouterr()
    assert rc == 2 and out.out == ""
    assert "comma-deps-acados" in out.err and "--solver sa" in out.err


def test_acados_rejects_baseline_models(capsys):
    from msagv.cli import run as run_cmd
    from msagv.controller.mpc import MPC

    with pytest.raises(ControllerError, match="'mf' only"):
        MPC(VEH, MPCSettings(model="dugoff"), solver="acados")
    rc = run_cmd.main(["--case", "curve", "--duration", "0.1", "--solver", "acados",
                       "--model", "kinematic", "--json"])
    out = capsys.readouterr()
    assert rc == 2 and out.out == "" and "'mf' only" in out.err


@needs_acados
@pytest.mark.slow
def test_controller_process_acados_lockstep_equals_in_process(capfd):
    """``msagv controller --solver acados`` over Zenoh in lockstep gives the run of
    ``msagv run --solver acados`` in-process (same commands, so the same metrics)."""
    from msagv.cli import run as run_cmd
    from msagv.cli.demo import run_demo

    r = run_demo(duration=1.0, speed="15", run_mode="lockstep", deadline_ms=None,
                 extra_controller=["--solver", "acados"])
    assert r["controller"]["solver"] == "acados" and r["controller"]["answered"] == 100
    assert run_cmd.main(["--case", "curve", "--speed", "15", "--duration", "1", "--solver",
                         "acados", "--json"]) == 0
    m = json.loads(capfd.readouterr().out)["metrics"]
    for k in ("W_tw", "W_s", "W_alpha", "W_t", "e_x_cm", "e_y_cm", "e_phi_deg"):
        assert r["metrics"][k] == pytest.approx(m[k], rel=1e-12, abs=1e-15), k
