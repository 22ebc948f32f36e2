"""The MPC's cost (paper eq. 22-26 plus the command regularisation R), each term written once.

Every term is plain scalar Python: numba compiles it into the kernels that call it
(:func:`numba.extending.register_jitable`: the per-step terms inlined into the SIMD tile
of :mod:`controller.rollout`, the loops as functions of their own), and the CasADi mirror
(:mod:`controller.mirrors.casadi_rollout`, hence IPOPT) calls the same functions on its
symbols, so the symbolic cost is built from these definitions, not re-typed. The only
function a term needs beyond arithmetic is ``ceil`` (the heading wrap): :func:`ceil` is
``np.ceil`` in numba and on numbers, ``casadi.ceil`` on a CasADi expression.

The terms:

* :func:`wrap` - an angle to (-pi, pi] (also the policy's heading feedback);
* :func:`pose_error` - ``(x - x_ref, y - y_ref, wrap(phi - phi_ref))``: the residuals of
  the tracking term (the polish's and acados' least-squares forms use it too);
* :func:`tracking_term` / :func:`tracking_cost` - ``e^T Q e`` per step / over the horizon;
* :func:`wear_kw`, :func:`wear_term` / :func:`wear_cost` - the wear powers in kW, ``P^T L P
  + lambda^T P`` per step / over the horizon, weights a :class:`WearWeights`
  (:func:`wear_weights` of the ``L`` vector, :mod:`plant.layout`'s ``L_*``, ``LE_*``);
* :func:`smoothing_cost`, :func:`ridge_cost` - the command regularisation (of one row of a
  batch: :func:`smoothing_row`, :func:`ridge_row`);
* :func:`candidate_cost` - ``(tracking + wear) / N_p + smoothing + ridge``.

``poses`` and ``wear`` are indexed ``[k][i]`` (numba: (N_p, 3) arrays; CasADi: lists of
triples), ``ref[k, i]`` and ``z[i]`` (arrays or CasADi matrices).
"""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
from numba.extending import overload, register_jitable

from msagv.plant.layout import (L_ALPHA, L_S, L_T, LE_ALPHA, LE_S, LE_T, POSE_PHI, POSE_X,
                                POSE_Y, Q_PHI, Q_X, Q_Y, R_DD, R_DW, R_OD, R_OW, REF_PHI,
                                REF_X, REF_Y, WEAR_ALPHA, WEAR_S, WEAR_T)

KW = 1e-3  # W -> kW: the cost's wear powers are in kW so that L has usable magnitudes

_NUMBERS = (float, int, np.floating, np.integer, np.ndarray)


def ceil(a):
    """``ceil(a)`` of a number (``np.ceil``) or of a CasADi expression (``casadi.ceil``:
    zero derivative); in numba, ``np.ceil``."""
    if isinstance(a, _NUMBERS):
        return np.ceil(a)
    import casadi  # a symbol: CasADi is installed (the ipopt or acados extra)
    return casadi.ceil(a)


@overload(ceil, inline="always")
def _ceil_numba(a):
    return lambda a: np.ceil(a)


def _step_term(fn):
    """A per-step term: inlined into the numba kernel that calls it."""
    return register_jitable(inline="always", error_model="numpy")(fn)


def _loop_term(fn):
    """A term with a loop: a function of its own in numba."""
    return register_jitable(error_model="numpy")(fn)


WearWeights = namedtuple("WearWeights", ("ls", "la", "lt", "les", "lea", "let"))
WearWeights.__doc__ = """The wear term's weights: quadratic ``ls, la, lt`` [1/kW^2] (the
paper's L, 'TWO') and linear ``les, lea, let`` [1/kW] ('two-energy') on the slip, slip
angle and steering powers."""


@_step_term
def wrap(a):
    """Angle wrapped to (-pi, pi]."""
    # (np.ceil: a float; math.ceil is an int, whose conversions do not vectorise)
    return a - 2.0 * math.pi * ceil((a - math.pi) / (2.0 * math.pi))


@_step_term
def pose_error(x, y, phi, rx, ry, rphi):
    """The pose error against a reference pose: ``(x - rx, y - ry, wrap(phi - rphi))``."""
    return x - rx, y - ry, wrap(phi - rphi)


@_step_term
def tracking_term(ex, ey, ephi, qx, qy, qphi):
    """One step's ``(Y_k - Yt_k)^T Q (Y_k - Yt_k)`` (eq. 22-24) from the pose errors."""
    return qx * ex * ex + qy * ey * ey + qphi * ephi * ephi


@_step_term
def wear_weights(L):
    """The :class:`WearWeights` of the weight vector ``L`` (``L_*``, ``LE_*``)."""
    return WearWeights(L[L_S], L[L_ALPHA], L[L_T], L[LE_S], L[LE_ALPHA], L[LE_T])


@_step_term
def wear_kw(ps, pa, pt):
    """The wear powers [W] in kW, the cost's unit."""
    return ps * KW, pa * KW, pt * KW


@_step_term
def wear_term(J, ps, pa, pt, lw):
    """``J`` plus one step's wear term, the powers [W] taken in kW: ``P^T L P`` (eq. 22,
    25; ``lw`` a :class:`WearWeights`) and ``lambda^T P`` (over the horizon, times the
    step, the predicted wear work that W_tw measures: TWO-energy)."""
    p0, p1, p2 = wear_kw(ps, pa, pt)
    J += lw.ls * p0 * p0 + lw.la * p1 * p1 + lw.lt * p2 * p2
    J += lw.les * p0 + lw.lea * p1 + lw.let * p2
    return J


@_step_term
def tracking_cost(poses, ref, Q):
    """``sum_k (Y_k - Yt_k)^T Q (Y_k - Yt_k)`` (eq. 22-24, W_Y = E (x) Q) over the
    predicted poses, against the reference rows 1..N_p; heading error wrapped."""
    J = 0.0
    for k in range(len(poses)):
        pk = poses[k]
        ex, ey, ephi = pose_error(pk[POSE_X], pk[POSE_Y], pk[POSE_PHI], ref[k + 1, REF_X],
                                  ref[k + 1, REF_Y], ref[k + 1, REF_PHI])
        J += tracking_term(ex, ey, ephi, Q[Q_X], Q[Q_Y], Q[Q_PHI])
    return J


@_step_term
def wear_cost(wear, L):
    """The wear term over the horizon (:func:`wear_term` per step, weights
    :func:`wear_weights` of ``L``)."""
    lw = wear_weights(L)
    J = 0.0
    for k in range(len(wear)):
        wk = wear[k]
        J = wear_term(J, wk[WEAR_S], wk[WEAR_ALPHA], wk[WEAR_T], lw)
    return J


@_loop_term
def smoothing_row(Z, row, zprev, R, stride, nsplit):
    """:func:`smoothing_cost` of the decision vector ``Z[row]`` (the tile's form: taking
    the row as a view first was slower in the tile)."""
    J = 0.0
    for blk in range(Z.shape[1] // stride):
        for j in range(stride):
            prev = zprev[j] if blk == 0 else Z[row, (blk - 1) * stride + j]
            dz = Z[row, blk * stride + j] - prev
            J += (R[R_DW] if j < nsplit else R[R_DD]) * dz * dz
    return J


@_loop_term
def ridge_row(Z, row, R, stride, nsplit):
    """:func:`ridge_cost` of the decision vector ``Z[row]``."""
    J = 0.0
    for blk in range(Z.shape[1] // stride):
        for j in range(stride):
            zi = Z[row, blk * stride + j]
            J += (R[R_OW] if j < nsplit else R[R_OD]) * zi * zi
    return J


@_loop_term
def smoothing_cost(z, zprev, R, stride, nsplit):
    """Changes of the decision variables ``z`` (D,) between consecutive blocks
    (``stride`` variables each) and from the previous solution's first block ``zprev``:
    R_dw on the first ``nsplit`` of a block (wheel speeds [1/(rad/s)^2]; all three twist
    offsets), R_dd on the rest (steering targets [1/rad^2]; raw steering rates)."""
    return smoothing_row(z.reshape((1, z.shape[0])), 0, zprev, R, stride, nsplit)


@_loop_term
def ridge_cost(z, R, stride, nsplit):
    """A ridge on the decision variables themselves: R_ow on the first ``nsplit`` of a
    block, R_od on the rest (as :func:`smoothing_cost`; raw commands get none)."""
    return ridge_row(z.reshape((1, z.shape[0])), 0, R, stride, nsplit)


@_loop_term
def candidate_cost(poses, wear, ref, z, zprev, Q, L, R, stride, nsplit):
    """Cost of one candidate (paper eq. 22-26) plus the shared command regularisation.

    ``poses``, ``wear`` (N_p, 3) of the candidate, ``z`` (D,) its decision vector in
    blocks of ``stride`` (the first ``nsplit`` of each weighted as wheel speeds):
    ``(tracking + wear) / N_p + smoothing + ridge`` (:func:`tracking_cost`,
    :func:`wear_cost`, :func:`smoothing_cost`, :func:`ridge_cost`; weights ``Q``, ``L``
    (``plant.layout.L_*``, ``LE_*``), ``R = (R_dw, R_dd, R_ow, R_od)``).
    """
    Np = len(poses)
    return ((tracking_cost(poses, ref, Q) + wear_cost(wear, L)) / Np
            + smoothing_cost(z, zprev, R, stride, nsplit) + ridge_cost(z, R, stride, nsplit))
