"""Exact RMI corner search for models declaring :class:`~rmijax.robots.structure.LinearDynamics`.

``M`` and ``h`` are affine in every parameter: ``M = M0 + sum_b th_b M_b``,
``h = h0 + sum_b th_b h_b``. For a track in state ``(q, qd)`` with servo command
``v`` and the nominal controller's torque ``tau = M_n v + h_n``, a corner's
perturbation is

    gv = M^-1 (tau - h) - v = M^-1 r,    r = sum_b (nominal_b - th_b) z_b,    z_b = M_b v + h_b,

so nothing cancels against ``v``. The track's score is ``sigma x.r`` with the row
``x = M^-1 e_i``. The parameters entering ``h`` only (``affine``) are chosen by the
sign of their coefficient ``sigma x.(-(hi_b - lo_b) h_b)``; the ``E = 2^(p - a)``
corners of the others (``enumerated``) are all evaluated. Work per window step,
for all ``T = 4n`` tracks at once (:func:`coupled_window_step`):

1. the terms of every track in one call, tracks on the last axis
   (``LinearDynamics.terms_tracks_last`` when the model gives it, else ``vmap`` of
   ``terms``), and from them each track's ``z_b`` and affine coefficients,
   materialised once (left elementwise, XLA would fuse them into step 2's kernels
   and recompute them per corner);
2. per (track, enumerated corner) the row ``x`` and the score with every affine
   parameter at ``lo``:

   - for a serial chain (``LinearDynamics.reach`` declared: ``M_b`` and ``h_b``
     vanish outside joints ``0..reach_b``), by one ``U D U'`` factorisation that
     eliminates the joints from the tip: eliminating joint ``k`` needs only the
     parameters that reach it, so its pivot, multipliers, the partial solves and
     the score's share are computed once per corner *of those parameters* and
     shared by all corners of the others (a tree: 2, 4, ..., E variants). Per
     corner there remains ``x = U^-T z``, ``n(n-1)/2`` multiply-adds;
   - otherwise by an elementwise ``LDL'`` of every corner's ``M`` (a sum of two
     half-tables of the low and high enumerated bits) and one solve;

3. the best and worst completion of the affine bits (a product per affine
   parameter when ``LinearDynamics.affine_joints`` is declared, a dot product
   otherwise), one integer max-reduction for the extremes, hence the tie
   threshold (SPEC section 2);
4. per corner the lowest index within the threshold (affine bits greedily from the
   most significant) and one integer min-reduction over corners: the corner
   :func:`~rmijax.methods.choosers.pick_corner` picks among all ``2^p``;
5. the chosen corner's full ``gv`` (one factorisation per track) and the next
   states, written out entry by entry and materialised in one kernel.

Step 2's rows and step 3's best and worst completions are materialised in one
kernel; the two reductions read them, and step 4 recomputes the affine spans from
the rows inside its reduction. Divisions are
Newton reciprocals (:func:`rmijax._linalg.reciprocal`) so that each pass stays one
fused, vectorised loop; the tree's levels are materialised between levels (a
division by a runtime one is a boundary XLA does not fuse across a broadcast).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from rmijax._linalg import ldl_factor, ldl_solve, materialise, reciprocal
from rmijax.methods._keys import float_of_ordered, ordered_int, tie_tolerance

__all__ = ["coupled_window_step"]


def _lead(a, ndim):
    """``a`` with leading unit axes up to ``ndim`` (explicit rank promotion)."""
    return jnp.reshape(a, (1,) * (ndim - a.ndim) + a.shape)


def _rows(array, index):
    """``array[index]`` for NumPy indices, by slices (a gather is a kernel of its own)."""
    index = np.asarray(index, int)
    if not index.size:
        return array[:0]
    if np.array_equal(index, np.arange(index[0], index[0] + index.size)):
        return array[int(index[0]) : int(index[0]) + index.size]
    return jnp.stack([array[int(b)] for b in index])


def _materialise_by_shape(arrays):
    """:func:`materialise` of arrays of each shape in a kernel of their own, in order.

    When the tracks share their state (a window's first step) the factorisation's
    arrays have one track and the rows all of them: materialised together, the
    shared ones would be broadcast to every track and computed once per track.
    """
    groups = {}
    for i, a in enumerate(arrays):
        groups.setdefault(a.shape, []).append(i)
    out = [None] * len(arrays)
    for members in groups.values():
        for i, value in zip(members, materialise([arrays[i] for i in members]), strict=True):
            out[i] = value
    return out


def _spread(a, of_track):
    """``a[..., of_track]`` for a static index; a broadcast when the tracks repeat a block.

    A gather is a kernel of its own on CPU; ``tile(repeat(arange(r), inner), outer)``
    (the engine's track layout) is a broadcast and a reshape, which fuse into the reader.
    """
    r = int(np.max(of_track)) + 1
    for inner in range(1, of_track.size // r + 1):
        outer = of_track.size // (r * inner)
        if outer * r * inner == of_track.size and np.array_equal(
            of_track, np.tile(np.repeat(np.arange(r), inner), outer)
        ):
            wide = jnp.broadcast_to(a[..., None, :r, None], (*a.shape[:-1], outer, r, inner))
            return wide.reshape(*a.shape[:-1], of_track.size)
    return jnp.take(a, of_track, axis=-1)


class _Corners(NamedTuple):
    """Every corner of every track, tracks on the last (minor) axis.

    Attributes:
        x: n arrays broadcastable to ``shape + (R,)``: the row ``M^-1 e_i``.
        base: ``x.r`` with every affine parameter at lo, same shape (unweighted).
        index: NumPy ints of ``shape``: each corner's index (its enumerated bits).
    """

    x: list
    base: jax.Array
    index: np.ndarray


def _chain_corners(m0, m_terms, z, rho0, onehots, nominal, lo, hi, enum, reach):
    """Every corner by the tip-first tree factorisation (``reach`` declared).

    Arrays carry one leading axis per enumerated parameter (length 2 once the
    parameter is active, else 1) and the tracks last. At joint ``k`` (from the
    tip) the parameters reaching ``k`` become active: the Schur complement of the
    joints ``0..k`` and the partial right-hand sides get their contribution; then
    joint ``k`` is eliminated: pivot ``d_k``, multipliers ``U_jk``, ``y = U^-1 e_i``
    and ``w = U^-1 r`` at ``k`` and ``z_k = y_k / d_k``; the score's share
    ``z_k w_k`` accumulates (``x.r = z.w``). Each level is materialised once.

    Args:
        m0 (n, n, T), m_terms (E_p, n, n, T) of the enumerated parameters (in ``enum``
            order), z (p, n, T): the terms, tracks last.
        rho0 (n, T): ``r`` with the enumerated parameters at their nominal values
            and the affine ones at lo; onehots (n, R): the rows ``e_i`` wanted.
        nominal, lo, hi: (p,); enum: NumPy indices; reach: per parameter.
    """
    n = rho0.shape[0]
    axis_of = {int(b): a for a, b in enumerate(enum)}
    n_axes = len(enum)

    def along(b, values):  # values (2,) on parameter b's axis, tracks last
        shape = [1] * n_axes + [1]
        shape[axis_of[b]] = 2
        return values.reshape(shape)

    def lift(a):  # (..., T) with every parameter axis
        return a.reshape((1,) * (n_axes + 1 - a.ndim) + a.shape)

    schur = {(r, c): lift(m0[r, c]) for r in range(n) for c in range(r + 1)}
    rho = [lift(rho0[j]) for j in range(n)]
    eta = [lift(onehots[j]) for j in range(n)]
    base = None
    z_level, u_level = [None] * n, {}
    for k in range(n - 1, -1, -1):
        for b in (int(b) for b in enum if reach[b] == k):
            th = along(b, jnp.stack([lo[b], hi[b]]))
            for r in range(k + 1):
                for c in range(r + 1):
                    schur[r, c] = schur[r, c] + th * lift(m_terms[axis_of[b], r, c])
            for j in range(k + 1):
                rho[j] = rho[j] + (nominal[b] - th) * lift(z[b, j])
        inv = reciprocal(schur[k, k])
        if k == 0 and inv.shape != eta[0].shape:  # shared: not once per row
            (inv,) = materialise([inv])
        mult = [schur[k, j] * inv for j in range(k)]  # U_jk
        w_k, y_k = rho[k], eta[k]
        z_k = y_k * inv
        base = z_k * w_k if base is None else base + z_k * w_k
        for j in range(k):
            rho[j] = rho[j] - mult[j] * w_k
            eta[j] = eta[j] - mult[j] * y_k
        for r in range(k):
            for c in range(r + 1):
                schur[r, c] = schur[r, c] - mult[r] * schur[k, c]
        if k == 0:  # the last level is computed with the corners' own work
            z_level[0] = z_k
            break
        keys = [(r, c) for r in range(k) for c in range(r + 1)]
        kept = _materialise_by_shape(
            [schur[key] for key in keys] + rho[:k] + eta[:k] + mult + [z_k, base]
        )
        for key, value in zip(keys, kept, strict=False):
            schur[key] = value
        kept = kept[len(keys) :]
        rho[:k], eta[:k], kept = kept[:k], kept[k : 2 * k], kept[2 * k :]
        for j in range(k):
            u_level[j, k] = kept[j]
        z_level[k], base = kept[k], kept[k + 1]
    x = [z_level[0]]
    for j in range(1, n):
        value = z_level[j]
        for m in range(j):
            value = value - u_level[m, j] * x[m]
        x.append(value)
    bits = np.indices((2,) * n_axes).reshape(n_axes, -1).T  # corner grid, C order
    index = np.sum(bits << np.asarray(enum, int)[None, :], axis=1).reshape((2,) * n_axes)
    return _Corners(x, base, index)


def _dense_corners(m0, m_terms, z, rho0, onehots, lo, hi, enum):
    """Every corner by an elementwise ``LDL'`` of its ``M`` (no ``reach`` declared).

    The enumerated parameters split into low and high halves; a corner's ``M`` and
    ``r`` are the sum of a high-half and a low-half table entry, ``(H, L, T)``.
    """
    n = rho0.shape[0]
    dtype = rho0.dtype
    width = hi - lo
    n_enum = enum.size
    n_low = n_enum // 2

    def half(bits_idx):
        table = (np.arange(2**bits_idx.size)[:, None] >> np.arange(bits_idx.size)[None, :]) & 1
        table = jnp.asarray(table, dtype) * width[enum[bits_idx]][None, :]  # (E_half, k)
        m_half = jnp.einsum("ek,kabt->abet", table, m_terms[bits_idx])
        r_half = -jnp.einsum("ek,kat->aet", table, z[enum[bits_idx]])
        return m_half, r_half

    m_low, r_low = half(np.arange(n_low))
    m_high, r_high = half(np.arange(n_low, n_enum))
    m_high = m_high + (m0 + jnp.einsum("p,pabt->abt", lo[enum], m_terms))[:, :, None, :]
    r_high = r_high + rho0[:, None, :]
    matrix = [
        [m_high[a, b][:, None, :] + m_low[a, b][None, :, :] for b in range(a + 1)] for a in range(n)
    ]
    resid = [r_high[a][:, None, :] + r_low[a][None, :, :] for a in range(n)]
    lower, _, inv_diag = ldl_factor(matrix, divide=False)
    x = ldl_solve(lower, inv_diag, [onehots[a][None, None, :] for a in range(n)])
    base = x[0] * resid[0]
    for a in range(1, n):
        base = base + x[a] * resid[a]
    e_bits = (np.arange(2**n_enum)[:, None] >> np.arange(n_enum)[None, :]) & 1
    index = np.sum(e_bits << enum[None, :], axis=1).reshape(2 ** (n_enum - n_low), 2**n_low)
    return _Corners(x, base, index)


def _extremes(corners, coef, pos, neg, joints, spans=False):
    """``(best, worst, span_list)`` of the affine completions of every corner.

    ``coef`` (A, n, T): the score per unit ``x_k`` of moving affine ``j`` lo to hi;
    ``pos``, ``neg`` (n, T) its positive and negative parts summed per joint (when
    each affine parameter enters one joint, ``joints``).
    """
    x, base = corners.x, corners.base
    nd = base.ndim

    def t(a):
        return _lead(a, nd)

    if pos is not None:
        best = worst = base
        for k in range(len(x)):
            up = x[k] > 0
            best = best + x[k] * jnp.where(up, t(pos[k]), t(neg[k]))
            worst = worst + x[k] * jnp.where(up, t(neg[k]), t(pos[k]))
        span_list = [x[k] * t(coef[j, k]) for j, k in enumerate(joints)] if spans else None
        return best, worst, span_list
    span_list = []
    for j in range(coef.shape[0]):
        s = x[0] * t(coef[j, 0])
        for a in range(1, len(x)):
            s = s + x[a] * t(coef[j, a])
        span_list.append(s)
    best = worst = base
    for s in span_list:
        best = best + jnp.maximum(s, 0.0)
        worst = worst + jnp.minimum(s, 0.0)
    return best, worst, span_list


def _lowest_index(best, threshold, span_list, affine, index):
    """Per corner, the lowest index scoring ``>= threshold`` (max int if none).

    From the most significant affine bit down, a bit stays clear while the slack
    ``best - threshold`` covers the gain it gives up.
    """
    threshold = _lead(threshold, best.ndim)
    slack = best - threshold
    for j in np.argsort(-np.asarray(affine)):
        gain = jnp.maximum(span_list[j], 0.0)
        take1 = gain > slack
        index = index + jnp.where(take1, 1 << int(affine[j]), 0).astype(index.dtype)
        slack = jnp.where(take1, slack, slack - gain)
    return jnp.where(best >= threshold, index, jnp.iinfo(index.dtype).max)


def coupled_window_step(
    terms: Callable,
    enumerated,
    affine,
    affine_joints,
    reach,
    states,
    u,
    weights,
    onehots,
    nominal,
    lo,
    hi,
    kp,
    kd,
    dt,
):
    """One coupled window step of every track, each with its exact corner (module docstring).

    Args:
        terms: the model's terms of all tracks, tracks last: ``(q (n, T), qd (n, T)) ->
            (M0 (n, n, T), M_b (p, n, n, T), h0 (n, T), h_b (p, n, T))``.
        enumerated, affine: parameter indices (ascending) enumerated and chosen by sign.
        affine_joints: for each affine parameter the one joint whose bias it enters,
            or None (``h_b`` dense).
        reach: per parameter the last joint ``M_b``, ``h_b`` touch, or None.
        states: (T, n, 2) the tracks' states, or (1, n, 2) when every track is in that
            state (a window's first step): the terms, ``z`` and, along a chain, the
            factorisation are then computed once and shared; only the rows, scores
            and the chosen corners' updates are per track. u: (n,) feed-forward.
        weights: (T,) ``sigma``; onehots: (T, n) each track's joint.
        nominal, lo, hi: (p,) the box; kp, kd: (n,) gains; dt: s.

    Returns:
        (T, n, 2) the states after the step (SPEC section 5, step 3).
    """
    enum, aff = np.asarray(enumerated, int), np.asarray(affine, int)
    q, qd = states[..., 0], states[..., 1]
    dtype = q.dtype
    n_params, n = lo.shape[0], q.shape[1]
    tracks = weights.shape[0]
    v = u[None, :] - kd[None, :] * qd - kp[None, :] * q
    # tracks last from here on: every per-track scalar is a vector along the minor axis
    m0, m_terms, _, h_terms = terms(q.T, qd.T)  # (n,n,T) (p,n,n,T) (n,T) (p,n,T)
    # the affine parameters' M_b vanish (declared): only the enumerated ones are kept
    # (slices and elementwise sums over the small axes, not gathers, scatters or dots:
    # on CPU each of those is a kernel of its own around arrays this small)
    m_terms = _rows(m_terms, enum)  # (E_p, n, n, T)
    v_t = v.T
    pushed = sum(m_terms[:, :, j] * v_t[j][None, None] for j in range(n))  # (E_p, n, T): M_b v
    slot = {int(b): e for e, b in enumerate(enum)}
    z = jnp.stack(
        [h_terms[b] + pushed[slot[b]] if b in slot else h_terms[b] for b in range(n_params)]
    )  # (p, n, T): M_b v + h_b
    # the per-track inputs of the corners are materialised here: left elementwise, XLA
    # would fuse them into the corners' kernels and compute them once per corner
    (z,) = materialise([z])
    width = hi - lo
    onehot_t = onehots.T
    coef = -(width[aff][:, None, None] * weights[None, None, :]) * h_terms[aff]  # (A, n, T)
    pos = neg = None
    joints = ()
    if affine_joints is not None and aff.size:
        joints = tuple(int(k) for k in affine_joints)
        own = [coef[j, k] for j, k in enumerate(joints)]  # A arrays (T,)
        on = [[j for j, k in enumerate(joints) if k == joint] for joint in range(n)]
        pos = jnp.stack([sum((jnp.maximum(own[j], 0.0) for j in js), 0.0 * v_t[0]) for js in on])
        neg = jnp.stack([sum((jnp.minimum(own[j], 0.0) for j in js), 0.0 * v_t[0]) for js in on])
        pos, neg = materialise([pos, neg])
    # the rows x = M^-1 e_i wanted: one per track, or one per joint when the tracks share
    # their state (then every track of a joint has the same row)
    rows, of_track = onehot_t, None
    if v.shape[0] == 1 and isinstance(onehots, np.ndarray):
        joint_of = np.argmax(onehots, axis=1)
        wanted, of_track = np.unique(joint_of, return_inverse=True)
        # padded to whole vectors (4 lanes): a minor axis of 7 is not vectorised
        padded = np.concatenate([wanted, np.repeat(wanted[:1], -wanted.size % 4)])
        rows = jnp.asarray(np.eye(n)[padded].T, dtype)  # (n, R)
    if reach is None:
        rho0 = sum((nominal[b] - lo[b]) * z[b] for b in range(n_params))  # every parameter at lo
        corners = _dense_corners(m0, m_terms, z, rho0, rows, lo, hi, enum)
    else:  # r with the enumerated parameters at nominal, the affine ones at lo
        rho_top = sum(((nominal[b] - lo[b]) * z[b] for b in aff), 0.0 * z[0])
        (rho_top,) = materialise([rho_top])
        corners = _chain_corners(m0, m_terms, z, rho_top, rows, nominal, lo, hi, enum, reach)
    if of_track is not None:  # materialised once per joint, then read by every track
        kept = materialise([*corners.x, corners.base])
        corners = corners._replace(
            x=[_spread(a, of_track) for a in kept[:n]], base=_spread(kept[n], of_track)
        )
    corners = corners._replace(base=_lead(weights, corners.base.ndim) * corners.base)
    offset = weights * jnp.sum(onehots * v, axis=-1)
    corner_axes = tuple(range(corners.index.ndim))

    # every corner's row x, best and worst completion, materialised in one kernel
    best, worst, _ = _extremes(corners, coef, pos, neg, joints)
    if of_track is None:
        kept = materialise([*corners.x, best, worst])
        corners = corners._replace(x=kept[:n])
        best, worst = kept[n], kept[n + 1]
    else:
        best, worst = materialise([best, worst])

    # pass 1: the extremes over every corner (one integer max-reduction)
    high, low = ordered_int(best), ordered_int(-worst)
    smallest = jnp.array(jnp.iinfo(high.dtype).min, high.dtype)
    top_i, bottom_i = jax.lax.reduce(
        (high, low),
        (smallest, smallest),
        lambda a, b: (jnp.maximum(a[0], b[0]), jnp.maximum(a[1], b[1])),
        corner_axes,
    )
    top, bottom = float_of_ordered(top_i, dtype), -float_of_ordered(bottom_i, dtype)
    threshold = top - tie_tolerance(jnp.maximum(jnp.abs(top), jnp.abs(bottom)), offset)

    # pass 2: the lowest corner index within the threshold (one integer min-reduction)
    itype = jnp.int32 if n_params <= 30 else jnp.int64
    if pos is not None:
        span_list = [corners.x[k] * _lead(coef[j, k], best.ndim) for j, k in enumerate(joints)]
    else:
        _, _, span_list = _extremes(corners, coef, pos, neg, joints, spans=True)
    index = jnp.asarray(corners.index, itype)[..., None]  # corners x 1 (tracks)
    candidate = _lowest_index(best, threshold, span_list, aff, index)
    chosen = jnp.min(candidate, axis=corner_axes)  # (T,)

    # the chosen corner's perturbation of every joint
    bits = (chosen[:, None] >> jnp.arange(n_params, dtype=itype)[None, :]) & 1
    th = jnp.where(bits == 1, hi[None, :], lo[None, :]).T  # (p, T)
    # written out entry by entry and materialised at once: one kernel for the whole update
    m_c = [[m0[a, b] for b in range(a + 1)] for a in range(n)]
    for e, b in enumerate(enum):
        m_c = [[m_c[a][c] + th[b] * m_terms[e, a, c] for c in range(a + 1)] for a in range(n)]
    r_c = [sum((nominal[b] - th[b]) * z[b, a] for b in range(n_params)) for a in range(n)]
    # the corner's M and r in one kernel (else XLA splits th's rows into kernels of their own)
    kept = materialise([entry for row in m_c for entry in row] + r_c)
    m_c = [[kept[a * (a + 1) // 2 + c] for c in range(a + 1)] for a in range(n)]
    r_c = kept[n * (n + 1) // 2 :]
    lower, _, inv = ldl_factor(m_c, divide=False)
    gv = ldl_solve(lower, inv, r_c)  # n arrays (T,)
    q_t, qd_t = q.T, qd.T
    q_next = [q_t[a] + dt * qd_t[a] for a in range(n)]
    qd_next = [
        (-kp[a] * dt) * q_t[a] + (1.0 - kd[a] * dt) * qd_t[a] + dt * u[a] + dt * gv[a]
        for a in range(n)
    ]
    kept = materialise(q_next + qd_next)
    kept = [jnp.broadcast_to(a, (tracks,)) for a in kept]  # a shared start moves every track
    return jnp.stack([jnp.stack(kept[:n], axis=-1), jnp.stack(kept[n:], axis=-1)], axis=-1)
