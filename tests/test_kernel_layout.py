"""plant/layout.py, the kernels' array layouts: the names are consistent, the kernels use
them, and the stale-cache guard makes a changed layout reach numba's cached kernels.

Numba's on-disk cache is keyed on each kernel file's own source; the integers a kernel
imports from another file are frozen into it. Without the guard a changed layout (or a
changed tire function a kernel inlines) would leave the old compiled code in use:
``test_guard_refreshes_a_kernel_whose_import_changed`` shows both behaviours on a toy
package, ``test_swapped_layout_reaches_the_cached_plant_kernel`` on a copy of the plant.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from msagv.plant import default_vehicle, n_axle_vehicle
from msagv.plant import dynamics as dyn
from msagv.plant import layout as lay

ROOT = Path(__file__).resolve().parents[1]
KERNELS = ["plant/dynamics.py", "controller/rollout.py", "controller/sa_kernel.py",
           "controller/models.py", "controller/mirrors/casadi_rollout.py"]


def test_every_vector_is_named_once():
    lay.check()
    for prefix, size in (("P_", lay.N_PARAMS), ("S_", lay.N_SETTINGS), ("AUX_", lay.N_AUX)):
        assert sorted(lay.names(prefix).values()) == list(range(size)), prefix
    nw = 6
    assert lay.state_size(nw) == 9 + 6 * nw
    assert lay.y_wear(nw) == 6 + nw
    assert lay.y_omega_w(nw) == 9 + nw
    assert lay.y_omega_s(nw) == 9 + 2 * nw
    # per-wheel wear work last, 3 per wheel; the error norm stops before it
    assert lay.n_error_states(nw) == 9 + 3 * nw == lay.y_wheel_wear(nw, 0)
    assert [lay.y_wheel_wear(nw, k) for k in range(nw)] == list(range(9 + 3 * nw, 9 + 6 * nw, 3))
    assert lay.x0_size(nw) == 6 + nw
    # the controller's state is the head of the plant's, the reference rows use its order
    assert (lay.X0_X, lay.X0_Y, lay.X0_PHI, lay.X0_VX, lay.X0_VY, lay.X0_R, lay.X0_DELTA) == \
        (lay.Y_X, lay.Y_Y, lay.Y_PHI, lay.Y_VX, lay.Y_VY, lay.Y_R, lay.Y_DELTA)


def test_pack_params_puts_each_vehicle_value_at_its_name():
    v = n_axle_vehicle(3)
    P, wx, wy = dyn.pack_params(v, v_eps=0.2)
    assert P.shape == (lay.N_PARAMS,) and np.all(np.isfinite(P))
    lim, lo, la = v.limits, v.tire_longitudinal, v.tire_lateral
    want = {"P_MASS": v.mass, "P_YAW_INERTIA": v.yaw_inertia, "P_WHEEL_RADIUS": v.wheel_radius,
            "P_G": 9.81, "P_K_T": v.steer_loss_kt, "P_V_EPS": 0.2,
            "P_LON_B": lo.B, "P_LON_C": lo.C, "P_LON_MU": lo.mu, "P_LON_E": lo.E,
            "P_LAT_B": la.B, "P_LAT_C": la.C, "P_LAT_MU": la.mu, "P_LAT_E": la.E,
            "P_OMEGA_W_MAX": lim.omega_w_max, "P_OMEGA_S_MIN": lim.omega_s_min,
            "P_OMEGA_S_MAX": lim.omega_s_max, "P_DELTA_MIN": lim.delta_min,
            "P_DELTA_MAX": lim.delta_max, "P_CG_HEIGHT": v.plant.cg_height,
            "P_WHEEL_LAG": v.plant.wheel_lag, "P_STEER_LAG": v.plant.steer_lag,
            "P_COMBINED_SLIP": v.plant.combined_slip}
    assert set(want) == set(lay.names("P_"))
    for name, value in want.items():
        assert P[getattr(lay, name)] == value, name


def test_a_models_own_parameters_follow_the_shared_P_in_declared_order():
    """A model with parameters of its own (plant.model_params) packs them after the shared
    P, at N_PARAMS + offset, from the vehicle file's section; a model without keeps P."""
    from msagv.controller import rollout as ro
    from msagv.controller.models import MODELS, MPCSettings, make_model
    from msagv.plant.model_params import DUGOFF

    v = n_axle_vehicle(3)
    P, _, _ = dyn.pack_params(v)
    for name, cls in MODELS.items():
        m = make_model(v, MPCSettings(model=name, dugoff_stiffness="file"))
        own = () if cls.params is None else cls.params.names
        assert m.P.shape == (lay.N_PARAMS + len(own),), name
        np.testing.assert_array_equal(m.P[:lay.N_PARAMS], P)
    m = make_model(v, MPCSettings(model="dugoff", dugoff_stiffness="file"))
    dug = v.to_dict()["tire"]["dugoff"]
    assert DUGOFF.names == ("C_s", "C_alpha", "mu")
    assert (m.P[ro.P_DUGOFF_C_S], m.P[ro.P_DUGOFF_C_ALPHA], m.P[ro.P_DUGOFF_MU]) == \
        (dug["C_s"], dug["C_alpha"], dug["mu"])


def test_settings_hold_only_mpc_settings():
    from msagv.controller.models import MPCSettings, pack_settings

    v = default_vehicle()
    s = MPCSettings(dt=0.05, K_servo=7.0, K_pos=1.5, K_phi=0.5, v_fb_max=2.0, r_fb_max=0.2)
    S = pack_settings(v, s)
    assert S.shape == (lay.N_SETTINGS,)
    assert (S[lay.S_DT], S[lay.S_K_SERVO], S[lay.S_K_POS], S[lay.S_K_PHI], S[lay.S_V_FB_MAX],
            S[lay.S_R_FB_MAX]) == (0.05, 7.0, 1.5, 0.5, 2.0, 0.2)
    # k_alpha = m / (2n C_alpha), C_alpha the MF slope B C mu F_N at zero slip
    la = v.tire_lateral
    assert S[lay.S_K_ALPHA] == pytest.approx(
        v.mass / (v.n_wheels * la.B * la.C * la.mu * v.normal_load), rel=1e-12)
    assert pack_settings(v, s.with_(model="kinematic"))[lay.S_K_ALPHA] == 0.0


@pytest.mark.parametrize("path", KERNELS)
def test_no_bare_numeric_index_into_P_or_S(path):
    src = (ROOT / path).read_text()
    bad = [line.strip() for line in src.splitlines()
           if re.search(r"(?<![\w.])[PS]\[\s*-?\d", line)]
    assert not bad, f"{path}: {bad}"


def test_c_mirror_uses_the_generated_header():
    src = (ROOT / "controller/mirrors/rollout_ref.c").read_text()
    assert '#include "msagv_layout.h"' in src
    assert not re.search(r"\b(P|S|x0|refk)\[\s*\d", src)
    header = lay.c_header()
    for name, value in {**lay.names("P_"), **lay.names("S_"), **lay.names("X0_")}.items():
        assert f"#define {name} {value}\n" in header


# ---- the stale-cache guard ---------------------------------------------------------------
_KERNEL = '''
from numba import njit
from msagv.plant import layout as lay
from . import consts
{guard}
@njit(cache=True)
def f():
    return consts.K
'''
_GUARD = '''
_STAMP = lay.kernel_stamp(consts.__file__)

@njit(cache=True)
def _layout_stamp():
    return _STAMP

lay.drop_stale_cache(_layout_stamp, _STAMP, __file__)
'''


def _run(code: str, path: Path, **env) -> str:
    e = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    e["PYTHONPATH"] = os.pathsep.join([str(path), str(ROOT), e.get("PYTHONPATH", "")])
    e.update(env)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=e,
                       timeout=300, cwd=path)
    assert r.returncode == 0, r.stderr
    return r.stdout.strip() + "\n" + r.stderr


def test_guard_refreshes_a_kernel_whose_import_changed(tmp_path):
    pkg = tmp_path / "toy"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "consts.py").write_text("K = 1\n")
    (pkg / "guarded.py").write_text(_KERNEL.format(guard=_GUARD))
    (pkg / "unguarded.py").write_text(_KERNEL.format(guard=""))
    code = "import toy.guarded as g, toy.unguarded as u; print(g.f(), u.f())"
    assert _run(code, tmp_path).split("\n")[0] == "1 1"
    assert list((pkg / "__pycache__").glob("guarded.f-*.nbi"))  # cached on disk
    (pkg / "consts.py").write_text("K = 2\n")
    out = _run(code, tmp_path, MSAGV_CACHE_VERBOSE="1")
    # the guarded kernel sees the change; numba alone keeps the stale compiled constant
    assert out.split("\n")[0] == "2 1"
    assert "dropped stale numba cache" in out
    # and the next import finds a fresh cache: nothing to drop
    out = _run(code, tmp_path, MSAGV_CACHE_VERBOSE="1")
    assert out.split("\n")[0] == "2 1" and "dropped" not in out


def test_swapped_layout_reaches_the_cached_plant_kernel(tmp_path):
    """A copy of plant/ (imported under another name, as the FMU does): evaluate the
    dynamics, swap two parameter indices in its layout.py, evaluate again from the warm
    cache: same derivative (pack_params and the kernel both follow the new layout)."""
    shutil.copytree(ROOT / "plant", tmp_path / "plantcopy",
                    ignore=shutil.ignore_patterns("__pycache__"))
    code = (
        "import numpy as np\n"
        "import plantcopy.dynamics as dyn\n"
        "from plantcopy import n_axle_vehicle, layout as lay\n"
        "v = n_axle_vehicle(3)\n"
        "P, wx, wy = dyn.pack_params(v)\n"
        "nw = v.n_wheels\n"
        "y = np.zeros(lay.state_size(nw))\n"
        "y[lay.Y_VX], y[lay.Y_VY], y[lay.Y_R] = 8.0, 0.5, 0.2\n"
        "y[lay.Y_DELTA:lay.Y_DELTA + nw] = np.linspace(-0.2, 0.3, nw)\n"
        "aux = np.zeros((nw, lay.N_AUX)); dy = np.zeros_like(y)\n"
        "dyn.evaluate(y, np.full(nw, 17.0), np.linspace(-0.5, 0.5, nw), P, wx, wy, aux, dy)\n"
        "print(lay.P_MASS, repr(dy.tolist()))\n")
    first = _run(code, tmp_path).split("\n")[0]
    layout = tmp_path / "plantcopy" / "layout.py"
    src = layout.read_text()
    assert "P_MASS = 0 " in src and "P_YAW_INERTIA = 1 " in src
    layout.write_text(src.replace("P_MASS = 0 ", "P_MASS = 1 ").replace(
        "P_YAW_INERTIA = 1 ", "P_YAW_INERTIA = 0 "))
    out = _run(code, tmp_path, MSAGV_CACHE_VERBOSE="1")
    second = out.split("\n")[0]
    assert "dropped stale numba cache" in out
    assert first.split(" ", 1)[0] == "0" and second.split(" ", 1)[0] == "1"
    d1 = np.array(eval(first.split(" ", 1)[1]))
    d2 = np.array(eval(second.split(" ", 1)[1]))
    assert np.all(np.abs(d1[3:6]) > 1e-3)  # the accelerations depend on m and I_vz
    np.testing.assert_array_equal(d2, d1)
