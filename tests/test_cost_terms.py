"""The cost written once (issue 27, item 4): controller.cost_terms is the one definition of
each term, and every user of a term takes it from there.

* the CasADi cost (the mirror's ``symbolic_cost``, what IPOPT differentiates) built on
  symbols for the poses, wear powers, reference and decisions equals the numba
  ``batch_cost`` on random candidates to 1e-12 relative, for every model and
  parametrisation, with the heading errors past +-pi (the wrap);
* the SIMD tile's fused cost (the EXACT prediction's ``evaluate``) is, bit for bit, the
  uncompiled ``cost_terms.candidate_cost`` of the same prediction's poses and wear: the
  tile's inlined per-step terms are the shared definition;
* nothing is re-typed: the mirror's cost calls the shared functions (counted through a
  patch), the kernels' names are the shared objects, and no module of the controller
  defines a cost term again or writes the heading wrap's formula;
* the wear weights' named structure reads the ``L`` vector at :mod:`plant.layout`'s indices.
"""

from __future__ import annotations

import ast
import math
from pathlib import Path

import numpy as np
import pytest

import msagv.controller as controller_pkg
from msagv.controller import MPCSettings
from msagv.controller import cost_terms as ct
from msagv.controller import rollout as ro
from msagv.controller import sa_kernel as sk
from msagv.controller.models import make_model
from msagv.plant import default_vehicle, n_axle_vehicle
from msagv.plant import layout as lay

from test_rollout_ref import _random_case  # noqa: E402 (tests/ is on sys.path)

try:
    import casadi as ca
except ImportError:  # pragma: no cover
    ca = None
needs_casadi = pytest.mark.skipif(ca is None, reason="needs CasADi (pip install msagv[ipopt])")

TERMS = ("wrap", "pose_error", "tracking_term", "wear_weights", "wear_kw", "wear_term",
         "tracking_cost", "wear_cost", "smoothing_cost", "ridge_cost", "smoothing_row",
         "ridge_row", "candidate_cost")


def _problem(axles, model, policy, seed, rows=9):
    vehicle = default_vehicle() if axles == 2 else n_axle_vehicle(axles)
    m = make_model(vehicle, MPCSettings(model=model, policy=policy))
    rng = np.random.default_rng(seed)
    x0, ref = _random_case(rng, vehicle, MPCSettings(model=model, policy=policy))
    lo, hi, _ = m.box()
    Z = np.ascontiguousarray(rng.uniform(lo, hi, (rows, m.dim)))
    zprev = rng.uniform(lo[:m.stride], hi[:m.stride])
    Q = rng.uniform(0.5, 5.0, 3)
    L = rng.uniform(0.1, 3.0, lay.N_L)
    R = rng.uniform(0.01, 1.0, 4)
    return m, x0, ref, Z, zprev, Q, L, R


@needs_casadi
@pytest.mark.parametrize("axles,model,policy", [(2, "mf", "offsets"), (3, "dugoff", "twist"),
                                                (2, "kinematic", "raw"), (2, "tct", "offsets")])
def test_casadi_cost_is_the_numba_cost(axles, model, policy):
    m, x0, ref, Z, zprev, Q, L, R = _problem(axles, model, policy, 11 * axles + len(model))
    out = m.rollout(x0, ref, Z, exact=True)
    Np = out.poses.shape[1]
    # headings a turn and more away from the reference: the wrap is exercised
    poses = out.poses.copy()
    turns = np.random.default_rng(axles).integers(-3, 4, poses.shape[:2])
    poses[:, :, lay.POSE_PHI] += 2.0 * math.pi * turns
    want = np.empty(Z.shape[0])
    ro.batch_cost(poses, out.wear, ref, Z, zprev, Q, L, R, m.stride, m.nsplit, want)
    ps = ca.SX.sym("poses", Np, 3)
    ws = ca.SX.sym("wear", Np, 3)
    rs = ca.SX.sym("ref", Np + 1, lay.N_REF)
    zs = ca.SX.sym("z", m.dim)
    zp = ca.SX.sym("zprev", m.stride)
    J = ct.candidate_cost([tuple(ps[k, i] for i in range(3)) for k in range(Np)],
                          [tuple(ws[k, i] for i in range(3)) for k in range(Np)],
                          rs, zs, zp, Q, L, R, m.stride, m.nsplit)
    f = ca.Function("J", [ps, ws, rs, zs, zp], [J])
    for b in range(Z.shape[0]):
        got = float(f(poses[b], out.wear[b], ref, Z[b], zprev))
        assert got == pytest.approx(want[b], rel=1e-12, abs=0.0), b
    assert np.all(want > 0.0)


@needs_casadi
def test_mirror_cost_is_the_shared_definition():
    """symbolic_cost (IPOPT's) is cost_terms.candidate_cost with the offsets' blocks."""
    from msagv.controller.mirrors import casadi_rollout as cr
    m, x0, ref, Z, zprev, Q, L, R = _problem(2, "mf", "offsets", 5, rows=3)
    out = m.rollout(x0, ref, Z, exact=True)
    nw = m.n_wheels
    want = np.empty(Z.shape[0])
    ro.batch_cost(out.poses, out.wear, ref, Z, zprev, Q, L, R, 2 * nw, nw, want)
    for b in range(Z.shape[0]):
        poses = [tuple(ca.SX(v) for v in p) for p in out.poses[b]]
        wear = [tuple(ca.SX(v) for v in w) for w in out.wear[b]]
        got = float(ca.evalf(cr.symbolic_cost(poses, wear, ca.SX(ref), ca.SX(Z[b]),
                                              ca.SX(zprev), Q, L, R, nw)))
        assert got == pytest.approx(want[b], rel=1e-12, abs=0.0)


@pytest.mark.parametrize("model,policy", [("mf", "offsets"), ("kinematic", "twist"),
                                          ("dugoff", "raw")])
def test_tile_cost_is_the_shared_definition_bit_for_bit(model, policy):
    """The fused cost of the exact prediction's tiles is the uncompiled candidate_cost of
    that prediction's poses and wear, to the bit (the tile accumulates the same terms in
    the same order)."""
    m, x0, ref, Z, zprev, Q, L, R = _problem(3, model, policy, 3 + len(model))
    Z = np.ascontiguousarray(Z[:ro.LANES + 3])
    out = m.rollout(x0, ref, Z, exact=True)
    ws = np.empty((2, ro.workspace_size(m.n_wheels, m.dim)))
    J = np.empty(Z.shape[0])
    ro.EXACT.evaluate_serial(m.model_id, x0, ref, Z, m.block, m.P, m.S, m.wx, m.wy, Q, L, R,
                             m.nsplit, zprev, ws, J)
    for b in range(Z.shape[0]):  # plain Python: register_jitable leaves the function itself
        want = ct.candidate_cost(out.poses[b], out.wear[b], ref, Z[b], zprev, Q, L, R,
                                 m.stride, m.nsplit)
        assert J[b] == want, b


@needs_casadi
def test_the_mirror_calls_every_shared_term(monkeypatch):
    """A term re-typed in the mirror would not reach cost_terms: every term is counted."""
    from msagv.controller.mirrors import casadi_rollout as cr
    calls = dict.fromkeys(TERMS, 0)
    for name in TERMS:
        fn = getattr(ct, name)

        def counted(*a, _fn=fn, _name=name):
            calls[_name] += 1
            return _fn(*a)
        monkeypatch.setattr(ct, name, counted)
    Np, nw = 4, 4
    poses = [tuple(ca.SX.sym(f"p{k}_{i}") for i in range(3)) for k in range(Np)]
    wear = [tuple(ca.SX.sym(f"w{k}_{i}") for i in range(3)) for k in range(Np)]
    ref = ca.SX.sym("ref", Np + 1, lay.N_REF)
    z = ca.SX.sym("z", 2 * 2 * nw)
    J = cr.symbolic_cost(poses, wear, ref, z, ca.SX.sym("zp", 2 * nw), np.ones(3),
                         np.ones(lay.N_L), np.ones(4), nw)
    assert isinstance(J, ca.SX)
    # candidate_cost once, each per-step term once per step (wrap through pose_error)
    assert calls["candidate_cost"] == 0  # symbolic_cost holds the object, not the name
    assert calls["tracking_cost"] == calls["wear_cost"] == 1
    assert calls["smoothing_cost"] == calls["ridge_cost"] == 1
    assert calls["smoothing_row"] == calls["ridge_row"] == 1
    assert calls["pose_error"] == calls["wrap"] == calls["tracking_term"] == Np
    assert calls["wear_term"] == calls["wear_kw"] == Np
    assert calls["wear_weights"] == 1


def test_users_hold_the_shared_objects():
    from msagv.controller import acados_rti
    from msagv.controller.mirrors import casadi_rollout as cr
    assert cr.candidate_cost is ct.candidate_cost and cr._wrap is ct.wrap
    assert acados_rti.pose_error is ct.pose_error and acados_rti.wear_kw is ct.wear_kw
    assert sk.pose_error is ct.pose_error and sk.KW is ct.KW
    for name in ("candidate_cost", "pose_error", "ridge_row", "smoothing_row",
                 "tracking_term", "wear_term", "wear_weights"):
        assert getattr(ro, name) is getattr(ct, name), name
    assert ro._wrap is ct.wrap


def _wrap_formula(node):
    """``... 2.0 * math.pi * <something ceil>(...)``: the heading wrap written out."""
    return (isinstance(node, ast.BinOp) and isinstance(node.op, ast.Mult)
            and isinstance(node.right, ast.Call)
            and "ceil" in ast.unparse(node.right.func)
            and "pi" in ast.unparse(node.left))


def test_no_controller_module_writes_a_term_again():
    root = Path(controller_pkg.__file__).parent
    found = []
    for path in sorted(root.rglob("*.py")):
        if path.name == "cost_terms.py":
            continue
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef) and node.name.lstrip("_") in TERMS:
                found.append(f"{path.name}: def {node.name}")
            if _wrap_formula(node):
                found.append(f"{path.name}:{node.lineno}: the wrap's formula")
    assert not found, found
    # the check itself sees the definitions where they are
    tree = ast.parse((root / "cost_terms.py").read_text())
    assert any(_wrap_formula(n) for n in ast.walk(tree))


def test_wear_weights_read_the_layout_indices():
    L = np.arange(1.0, lay.N_L + 1.0)
    w = ct.wear_weights(L)
    assert (w.ls, w.la, w.lt) == (L[lay.L_S], L[lay.L_ALPHA], L[lay.L_T])
    assert (w.les, w.lea, w.let) == (L[lay.LE_S], L[lay.LE_ALPHA], L[lay.LE_T])
    # one step's term by hand: powers 1000, 2000, 3000 W = 1, 2, 3 kW
    J = ct.wear_term(0.5, 1000.0, 2000.0, 3000.0, w)
    assert J == pytest.approx(0.5 + w.ls + 4 * w.la + 9 * w.lt + w.les + 2 * w.lea + 3 * w.let,
                              rel=1e-15)


def test_wrap_on_numbers_and_symbols():
    for a in (0.0, math.pi, -math.pi + 1e-9, 3 * math.pi + 0.5, -7.0, 100.0):
        w = float(ct.wrap(a))
        assert -math.pi < w <= math.pi
        assert math.isclose(math.cos(w), math.cos(a), abs_tol=1e-12)
        assert math.isclose(math.sin(w), math.sin(a), abs_tol=1e-12)
    if ca is not None:
        x = ca.SX.sym("x")
        f = ca.Function("w", [x], [ct.wrap(x)])
        for a in (0.3, 4.0, -9.0):
            assert float(f(a)) == float(ct.wrap(a))
