"""Exact RMI corner search for the planar point-mass arm, without enumerating all corners.

RMI (SPEC section 5) picks, at every window step and for every track, the
corner of the parameter box that maximises (or minimises) the score
``sigma * gv_i``. Enumerating all ``K = 4^n`` corners is the definition; this
module finds the same corner, with the same tie rule, at a fraction of the
cost, by using the structure of the planar arm (SPEC section 1).

Coupled mode. In absolute angles ``phi = S q`` and with ``psi_a = l_a phidd_a``
the forward dynamics reads

    (Mu o C) psi = S'^-1 tau / l - (Mu o Sn)(l o phid^2) - g mu o cos(phi),

where ``Mu_ab = mu_max(a,b)`` depends on the masses alone and ``C``, ``Sn`` are
the cosines and sines of ``phi_a - phi_b``. For one mass corner, row ``r`` of
``(Mu o C)^-1`` therefore gives ``psi_r = A_r . (1/l) + B_r . l + G_r``, affine in
``1/l`` and ``l``. Output ``i`` needs ``qdd_i = psi_i / l_i - psi_{i-1} / l_{i-1}``:
once the two lengths ``l_i`` and ``l_{i-1}`` are fixed (a *combo*, 4 of them),
the score is a constant plus a sum of independent terms ``P_b / l_b + Q_b l_b``,
one per other length, each maximised on its own. Work per track and step:
``2^n`` factorisations and ``4 * 2^n`` separable sums instead of ``4^n``
factorisations.

Per-joint mode. Joint ``i``'s perturbation is ``N / D - v_i`` with ``N`` and
``D = M_ii`` quadratic in the lengths; neither depends on the masses
``m_k, k < i``, and the lengths ``l_b, b < i`` enter ``N`` linearly and ``D``
not at all. So joint ``i`` enumerates ``4^(n-i)`` corners of its own masses and
lengths and takes the lower lengths separably.

Ties (SPEC section 2). Scores within ``eps^(2/3)`` of the best, relative to
``max|score| + |sigma v_i|``, are ties, and the lowest corner index wins. Corner
index bits are the masses (low bits), then the lengths. For every enumerated
entry the lowest-index corner within the tolerance is found greedily from its
top free bit down (keep a bit at 0 while the slack allows its loss), and the
entries' candidate indices are compared as integers. Corners that differ only
in parameters an output does not depend on score identically, so the lowest
index has those bits at 0, which is what the search returns.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from rmijax._linalg import ldl_factor, ldl_solve
from rmijax.control import closed_loop_step
from rmijax.methods._keys import float_of_ordered, ordered_int
from rmijax.robots.model import GRAVITY
from rmijax.robots.planar import (
    PlanarState,
    planar_scaled_accelerations,
    planar_torque_differences,
    running_sums,
    tail_sums,
)

__all__ = [
    "MAX_LINKS",
    "SEARCH",
    "FactoredSearch",
    "coupled_window_step",
    "estimate_memory",
    "per_joint_window_step",
    "tie_tolerance",
]

MAX_LINKS = 15
"""Largest arm the exact search takes: corner indices must fit in int32 (2n <= 30 bits)."""

_UNROLL_LINKS = 2
"""Up to this many links the corners are unrolled into scalar code (no reductions)."""

_NO_CORNER = np.int32(2**31 - 1)


def tie_tolerance(dtype) -> float:
    """Relative tolerance below which two scores count as tied: ``eps^(2/3)``."""
    return float(jnp.finfo(dtype).eps ** (2.0 / 3.0))


# --------------------------------------------------------------------------
# Reductions over the enumerated entries
# --------------------------------------------------------------------------


def _max_min_all(high, low):
    """``(max(high), min(low))`` over all entries, as one integer reduction.

    XLA's CPU backend hands float reductions to a library kernel that forces
    every operand to be materialised (each recomputing the whole corner
    pipeline); a max of order-preserving integer images is fused with its
    producer instead, and one variadic reduction computes both extremes in one
    pass. Exact: it returns entries of ``high`` and ``low``.
    """
    a, b = ordered_int(high), ordered_int(-low)
    smallest = jnp.array(jnp.iinfo(a.dtype).min, a.dtype)
    top, bottom = jax.lax.reduce(
        (a, b),
        (smallest, smallest),
        lambda x, y: (jnp.maximum(x[0], y[0]), jnp.maximum(x[1], y[1])),
        tuple(range(a.ndim)),
    )
    return float_of_ordered(top, high.dtype), -float_of_ordered(bottom, low.dtype)


def _threshold(top, bottom, offset):
    """Scores at or above this tie with the best one ``top`` (SPEC section 2).

    ``eps^(2/3)`` relative to ``max|score| + |offset|``: ``bottom`` is the
    smallest score, ``offset = sigma v_i`` the part cancelled in ``gv = qdd - v``.
    """
    scale = jnp.maximum(jnp.abs(top), jnp.abs(bottom)) + jnp.abs(offset)
    return top - tie_tolerance(top.dtype) * scale


def _separable_extremes(base, s0, s1):
    """Best and worst score of an entry whose free bits each add ``s0[b]`` or ``s1[b]``.

    Returns ``(best_total, worst_total, best_terms)``.
    """
    best = [jnp.maximum(x, y) for x, y in zip(s0, s1, strict=True)]
    worst = [jnp.minimum(x, y) for x, y in zip(s0, s1, strict=True)]
    return base + sum(best), base + sum(worst), best


def _chain(values, op):
    out = values[0]
    for value in values[1:]:
        out = op(out, value)
    return out


def _keep(index, one):
    """Materialise an integer corner index once (a division by a runtime 1, exact).

    XLA fuses cheap elementwise code into every consumer; without this the
    whole unrolled corner search would be recomputed for each output slot of
    the state. A float divide is not duplicated into consumers.
    """
    return (index.astype(one.dtype) / one).astype(index.dtype)


# --------------------------------------------------------------------------
# Shared pieces of one track's step
# --------------------------------------------------------------------------


def _lists(x):
    return [x[a] for a in range(x.shape[0])]


def _corner_values(lo, hi, index, first, count):
    """Values of parameters ``first .. first+count-1`` at the corners in ``index``.

    ``index`` holds corner indices over those parameters (bit ``b`` for parameter
    ``first + b``); an int or array. Returns a list of ``count`` arrays.
    """
    return [jnp.where((index >> b) & 1 == 1, hi[first + b], lo[first + b]) for b in range(count)]


def _lowest_index(total, slack, free_bits, base_index):
    """Lowest corner index within ``slack`` of ``total`` for each enumerated entry.

    Args:
        total: best score of each entry (its free bits at their best values).
        slack: ``total - threshold``; entries with negative slack have no
            candidate.
        free_bits: from the most significant bit down, ``(position, loss0,
            fixed, fixed_value)``: the bit's place in the corner index, the
            score lost by setting it to 0 (``>= 0``), and, unless ``fixed`` is
            None, where (bool) the entry fixes the bit and to which value.
        base_index: the index bits the entry fixes.
    """
    index = base_index
    remaining = slack
    for position, loss0, fixed, fixed_value in free_bits:
        take0 = loss0 <= remaining
        if fixed is not None:
            take0 = jnp.where(fixed, ~fixed_value, take0)
        remaining = jnp.where(take0, remaining - loss0, remaining)
        index = index + jnp.where(take0, 0, 1 << position).astype(jnp.int32)
    return jnp.where(slack >= 0, index, _NO_CORNER)


# --------------------------------------------------------------------------
# Coupled mode
# --------------------------------------------------------------------------


def _row_tables(state, torque_diff, mu, rows):
    """For one mass corner: ``psi_r = A . (1/l) + B . l + G`` for each selected row.

    Args:
        state: :class:`~rmijax.robots.planar.PlanarState` of the track.
        torque_diff: ``S'^-1 tau`` of the nominal controller (list).
        mu: tail sums of the corner's masses (list of arrays, any shape).
        rows: one-hot row selectors (lists of per-track scalars).

    Returns:
        per row, ``(A, B, G)``: lists of ``n`` arrays and an array.
    """
    n = len(mu)
    matrix = [[mu[a] * state.cos_diff[a][b] for b in range(a + 1)] for a in range(n)]
    lower, _, inv_diag = ldl_factor(matrix)
    tables = []
    for row in rows:
        w = ldl_solve(lower, inv_diag, row)  # row of (Mu o C)^-1 (symmetric)
        coef_inv = [w[b] * torque_diff[b] for b in range(n)]
        coef_len = []
        for b in range(n):
            total = w[0] * (mu[b] * state.sin_diff[0][b])
            for a in range(1, n):
                total = total + w[a] * (mu[max(a, b)] * state.sin_diff[a][b])
            coef_len.append(-state.rate_sq[b] * total)
        const = w[0] * (mu[0] * state.cos[0])
        for a in range(1, n):
            const = const + w[a] * (mu[a] * state.cos[a])
        tables.append((coef_inv, coef_len, -GRAVITY * const))
    return tables


def _combo_scores(tables, combo, box, own, weight, v_own):
    """Score pieces of the entries ``(mass corner, combo)``, broadcasting over both.

    Args:
        tables: :func:`_row_tables` for rows ``i`` and ``j`` (``j`` absent at n=1).
        combo: ``(inv_li, inv_lj, hi_i, hi_j)``: reciprocal lengths of the
            combo's two fixed links and whether each is at its upper bound.
        box: ``(inv_lo, inv_hi, len_lo, len_hi)`` lists over the links.
        own: ``(onehot_i, onehot_j, sign_j, in_pair)`` per-track selectors.
        weight: ``sigma``, the sign times the costate weight.
        v_own: ``v_i``.

    Returns:
        ``(base, s0, s1)``: the fixed part and, per link, the weighted terms at
        its lower and upper length (zero for the two fixed links).
    """
    inv_lo, inv_hi, len_lo, len_hi = box
    onehot_i, onehot_j, sign_j, in_pair = own
    inv_li, inv_lj, hi_i, hi_j = combo
    (a_i, b_i, g_i) = tables[0]
    n = len(a_i)
    coef_p = [a_i[b] * inv_li for b in range(n)]
    coef_q = [b_i[b] * inv_li for b in range(n)]
    const = g_i * inv_li
    if len(tables) > 1:
        (a_j, b_j, g_j) = tables[1]
        scale_j = sign_j * inv_lj
        coef_p = [coef_p[b] + a_j[b] * scale_j for b in range(n)]
        coef_q = [coef_q[b] + b_j[b] * scale_j for b in range(n)]
        const = const + g_j * scale_j
    base = const - v_own
    s0, s1 = [], []
    for b in range(n):
        t_lo = coef_p[b] * inv_lo[b] + coef_q[b] * len_lo[b]
        t_hi = coef_p[b] * inv_hi[b] + coef_q[b] * len_hi[b]
        fixed_hi = onehot_i[b] * hi_i + onehot_j[b] * hi_j
        base = base + in_pair[b] * jnp.where(fixed_hi > 0, t_hi, t_lo)
        free = weight * (1.0 - in_pair[b])
        s0.append(free * t_lo)
        s1.append(free * t_hi)
    return weight * base, s0, s1


def _coupled_corner(state, torque_diff, v, weight, onehot, lo, hi):
    """Index of the exact RMI corner of one coupled track (SPEC section 5, step 3)."""
    n = len(v)
    dtype = v[0].dtype
    onehot_i = _lists(onehot)
    v_own = onehot_i[0] * v[0]
    for a in range(1, n):
        v_own = v_own + onehot_i[a] * v[a]
    zero = jnp.zeros((), dtype)
    if n > 1:  # j = i - 1, or for the first joint a stand-in link with weight 0
        first = onehot_i[0]
        onehot_j = [onehot_i[b + 1] if b + 1 < n else zero for b in range(n)]
        onehot_j[1] = onehot_j[1] + first
        sign_j = first - 1.0
        rows = [onehot_i, onehot_j]
        in_pair = [onehot_i[b] + onehot_j[b] for b in range(n)]
    else:
        onehot_j, sign_j, rows, in_pair = [zero], zero, [onehot_i], onehot_i
    own = (onehot_i, onehot_j, sign_j, in_pair)
    len_lo, len_hi = [lo[n + b] for b in range(n)], [hi[n + b] for b in range(n)]
    inv_lo, inv_hi = [1.0 / x for x in len_lo], [1.0 / x for x in len_hi]
    box = (inv_lo, inv_hi, len_lo, len_hi)

    def pick(flags, values):
        total = flags[0] * values[0]
        for b in range(1, n):
            total = total + flags[b] * values[b]
        return total

    inv_li = (pick(onehot_i, inv_lo), pick(onehot_i, inv_hi))
    inv_lj = (pick(onehot_j, inv_lo), pick(onehot_j, inv_hi)) if n > 1 else (zero, zero)
    combos = [(c & 1, (c >> 1) & 1) for c in range(4 if n > 1 else 2)]
    n_masses = 2**n

    def free_bits(s0, best, hi_i, hi_j):
        bits = []
        for b in range(n - 1, -1, -1):
            fixed_value = onehot_i[b] * hi_i + onehot_j[b] * hi_j > 0
            bits.append((n + b, best[b] - s0[b], in_pair[b] > 0, fixed_value))
        return bits

    if n <= _UNROLL_LINKS:
        entries = []
        for m in range(n_masses):
            mu = tail_sums(_corner_values(lo, hi, m, 0, n))
            tables = _row_tables(state, torque_diff, mu, rows)
            for hi_i, hi_j in combos:
                combo = (inv_li[hi_i], inv_lj[hi_j], float(hi_i), float(hi_j))
                base, s0, s1 = _combo_scores(tables, combo, box, own, weight, v_own)
                total, bottom, best = _separable_extremes(base, s0, s1)
                entries.append((m, hi_i, hi_j, total, bottom, s0, best))
        top = _chain([e[3] for e in entries], jnp.maximum)
        bottom = _chain([e[4] for e in entries], jnp.minimum)
        threshold = _threshold(top, bottom, weight * v_own)
        candidates = [
            _lowest_index(total, total - threshold, free_bits(s0, best, hi_i, hi_j), np.int32(m))
            for m, hi_i, hi_j, total, _, s0, best in entries
        ]
        one = (v[0] == v[0]).astype(dtype)
        return _keep(_chain(candidates, jnp.minimum), one)

    # Stacked: combos along axis 0, mass corners along axis 1.
    mass_index = jnp.arange(n_masses, dtype=jnp.int32)
    mu = tail_sums([m[None, :] for m in _corner_values(lo, hi, mass_index, 0, n)])
    tables = _row_tables(state, torque_diff, mu, rows)
    hi_i = jnp.asarray([[c[0]] for c in combos], dtype)  # (C, 1)
    hi_j = jnp.asarray([[c[1]] for c in combos], dtype)
    combo = (
        jnp.where(hi_i > 0, inv_li[1], inv_li[0]),
        jnp.where(hi_j > 0, inv_lj[1], inv_lj[0]),
        hi_i,
        hi_j,
    )
    base, s0, s1 = _combo_scores(tables, combo, box, own, weight, v_own)
    total, bottom, best = _separable_extremes(base, s0, s1)
    top, bottom = _max_min_all(total, bottom)
    threshold = _threshold(top, bottom, weight * v_own)
    candidates = _lowest_index(
        total, total - threshold, free_bits(s0, best, hi_i, hi_j), mass_index[None, :]
    )
    return jnp.min(candidates)


def _coupled_track_step(x, u, weight, onehot, nominal, lo, hi, kp, kd, dt):
    n = x.shape[0]
    q, qd = _lists(x[:, 0]), _lists(x[:, 1])
    v = [u[a] - kd[a] * qd[a] - kp[a] * q[a] for a in range(n)]
    state = PlanarState.of(q, qd)
    mu_nominal = tail_sums(_lists(nominal[:n]))
    torque_diff = planar_torque_differences(state, mu_nominal, _lists(nominal[n:]), running_sums(v))
    corner = _coupled_corner(state, torque_diff, v, weight, onehot, lo, hi)
    masses = _corner_values(lo, hi, corner, 0, n)
    lengths = _corner_values(lo, hi, corner >> n, n, n)
    inv_lengths = [1.0 / length for length in lengths]
    psi = planar_scaled_accelerations(state, tail_sums(masses), lengths, inv_lengths, torque_diff)
    phidd = [psi[a] * inv_lengths[a] for a in range(n)]
    qdd = jnp.stack([phidd[0]] + [phidd[a] - phidd[a - 1] for a in range(1, n)])
    q_next, qd_next = closed_loop_step(x[:, 0], x[:, 1], u, qdd - jnp.stack(v), kp, kd, dt)
    return jnp.stack([q_next, qd_next], axis=-1)


def coupled_window_step(states, u, weights, onehots, nominal, lo, hi, kp, kd, dt):
    """One window step of every coupled track, each with its exact corner.

    Args:
        states: (4n, n, 2) the tracks' full states ``x(k)``.
        u: (n,) feed-forward ``u_d(k)``.
        weights: (4n,) ``sigma = sign * L(k+1)' e2`` of each track's output.
        onehots: (4n, n) each track's joint.
        nominal, lo, hi: (2n,) the parameter box (masses then lengths).
        kp, kd: (n,) gains; dt: step in s.

    Returns:
        (4n, n, 2) states ``x(k+1)`` (SPEC section 5, step 3).
    """

    def track(x, weight, onehot):
        return _coupled_track_step(x, u, weight, onehot, nominal, lo, hi, kp, kd, dt)

    return jax.vmap(track)(states, weights, onehots)


# --------------------------------------------------------------------------
# Per-joint mode
# --------------------------------------------------------------------------


class _PerJointState(NamedTuple):
    """Array-form state terms of one per-joint track (links ``a, b``)."""

    cos: jax.Array  # (n,) cos(phi_a)
    cos_diff: jax.Array  # (n, n) cos(phi_a - phi_b)
    terms: jax.Array  # (n, n) E_ab = cos(phi_a - phi_b) Z_b + sin(phi_a - phi_b) phid_b^2


def _per_joint_state(q, qd, accel_others):
    """``E_ab`` with ``Z_b = sum_{j <= b, j != i} qdd_n,j`` (``accel_others``, joint i zeroed).

    Then ``sum_{j != i} M_ij qdd_n,j + h_i = sum_{a >= i} l_a (sum_b mu_max(a,b) l_b
    E_ab + g mu_a cos phi_a)`` and ``M_ii = sum_{a,b >= i} mu_max(a,b) l_a l_b C_ab``.
    """
    phi, rate = jnp.cumsum(q), jnp.cumsum(qd)
    cos, sin = jnp.cos(phi), jnp.sin(phi)
    cos_diff = cos[:, None] * cos[None, :] + sin[:, None] * sin[None, :]
    sin_diff = sin[:, None] * cos[None, :] - cos[:, None] * sin[None, :]
    terms = cos_diff * jnp.cumsum(accel_others)[None, :] + sin_diff * (rate * rate)[None, :]
    return _PerJointState(cos, cos_diff, terms), sin_diff, rate * rate


def _per_joint_torque(state, sin_diff, rate_sq, v, nominal, i):
    """The nominal controller's torque on joint ``i``: ``tau_i = sum_{a >= i} (S'^-1 tau)_a``."""
    n = v.shape[0]
    mu = jnp.flip(jnp.cumsum(jnp.flip(nominal[:n])))
    lengths = nominal[n:]
    index = np.arange(n)
    weights = mu[np.maximum(index[:, None], index[None, :])] * lengths[:, None] * lengths[None, :]
    accel_abs = jnp.cumsum(v)
    torque_diff = (
        jnp.sum(weights * (state.cos_diff * accel_abs[None, :] + sin_diff * rate_sq[None, :]), 1)
        + GRAVITY * mu * lengths * state.cos
    )
    return jnp.sum(torque_diff[i:])


def _per_joint_corner_parts(i, state, mu, lengths):
    """``(load, M_ii)`` of one corner: ``mu``, ``lengths`` (n,), every length included."""
    n = lengths.shape[0]
    index = np.arange(n)
    mu_max = mu[np.maximum(index[:, None], index[None, :])]
    weights = mu_max[i:] * lengths[None, :]  # rows a >= i
    load = jnp.dot(
        lengths[i:], jnp.sum(weights * state.terms[i:], 1) + GRAVITY * mu[i:] * state.cos[i:]
    )
    inertia = jnp.dot(lengths[i:], jnp.sum(weights[:, i:] * state.cos_diff[i:, i:], 1))
    return load, inertia


def _per_joint_grid(i, state, lo, hi, index):
    """Load, ``M_ii`` and lower-length weights for every corner of links ``i..``.

    Mass corners of links ``i..`` run along axis 0 and their length corners
    along axis 1. The quadratic forms in the lengths are contractions of
    per-mass-corner coefficients with the corner features ``l_a l_b``
    (``a <= b``): one matrix product per quantity. The lower lengths ``l_b,
    b < i`` enter the load linearly, with weight ``K_b = sum_{a >= i} mu_a l_a E_ab``.

    Returns:
        ``load``, ``inertia`` (2^(n-i), 2^(n-i)) and ``lower`` (i, 2^(n-i), 2^(n-i)).
    """
    n = state.cos.shape[0]
    own = n - i
    precision = jax.lax.Precision.HIGHEST
    masses = jnp.stack(_corner_values(lo, hi, index, i, own), -1)  # (Km, own)
    mu = jnp.flip(jnp.cumsum(jnp.flip(masses, -1), -1), -1)  # tail sums over links i..
    lengths = jnp.stack(_corner_values(lo, hi, index, n + i, own), -1)  # (Kl, own)
    first, second = np.triu_indices(own)
    mu_pair = mu[:, second]  # mu_max(a, b) = mu_b for a <= b
    features = lengths[:, first] * lengths[:, second]  # (Kl, pairs)
    cos_diff, terms = state.cos_diff[i:, i:], state.terms[i:, i:]
    twice = np.where(first == second, 1.0, 2.0)
    inertia_coef = mu_pair * (twice * cos_diff[first, second])[None, :]
    symmetric = np.where(first == second, 1.0, 0.0) * terms[first, second]
    load_pair = terms[first, second] + terms[second, first] - symmetric
    inertia = jnp.einsum("mp,lp->ml", inertia_coef, features, precision=precision)
    gravity = GRAVITY * mu * state.cos[None, i:]
    load = jnp.einsum("mp,lp->ml", mu_pair * load_pair[None, :], features, precision=precision)
    load = load + jnp.einsum("ma,la->ml", gravity, lengths, precision=precision)
    weights = mu[:, :, None] * state.terms[None, i:, :i]  # (Km, own, i): mu_a E_ab
    lower = jnp.einsum("mab,la->bml", weights, lengths, precision=precision)
    return load, inertia, lower


def _per_joint_track_step(i, x, weight, u, x_nominal, qdd_nominal, nominal, lo, hi, kp, kd, dt):
    n = u.shape[0]
    q = x_nominal[:, 0].at[i].set(x[0])
    qd = x_nominal[:, 1].at[i].set(x[1])
    v = u - kd * qd - kp * q
    state, sin_diff, rate_sq = _per_joint_state(q, qd, qdd_nominal.at[i].set(0.0))
    torque = _per_joint_torque(state, sin_diff, rate_sq, v, nominal, i)

    # Enumerate masses i.. (axis 0) and lengths i.. (axis 1); lower lengths are separable.
    index = jnp.arange(2 ** (n - i), dtype=jnp.int32)
    load, inertia, lower = _per_joint_grid(i, state, lo, hi, index)
    inv_inertia = 1.0 / inertia
    base = weight * ((torque - load) * inv_inertia - v[i])
    s0 = [-weight * lower[b] * inv_inertia * lo[n + b] for b in range(i)]
    s1 = [-weight * lower[b] * inv_inertia * hi[n + b] for b in range(i)]
    total, bottom, best = _separable_extremes(base, s0, s1)
    top, bottom = _max_min_all(total, bottom)
    threshold = _threshold(top, bottom, weight * v[i])
    base_index = (index[:, None] << i) + (index[None, :] << (n + i))
    free = [(n + b, best[b] - s0[b], None, None) for b in range(i - 1, -1, -1)]
    corner = jnp.min(_lowest_index(total, total - threshold, free, base_index))

    # The chosen corner's perturbation, evaluated directly.
    masses = jnp.stack(_corner_values(lo, hi, corner, 0, n))
    lengths = jnp.stack(_corner_values(lo, hi, corner >> n, n, n))
    load, inertia = _per_joint_corner_parts(
        i, state, jnp.flip(jnp.cumsum(jnp.flip(masses))), lengths
    )
    gv = (torque - load) / inertia - v[i]
    return jnp.stack(closed_loop_step(x[0], x[1], u[i], gv, kp[i], kd[i], dt))


def per_joint_window_step(
    states, u, weights, joints, x_nominal, qdd_nominal, nominal, lo, hi, kp, kd, dt
):
    """One window step of every per-joint track, each with its exact corner.

    Args:
        states: (4n, 2) each track's own joint state.
        u: (n,) feed-forward ``u_d(k)``.
        weights: (4n,) ``sigma`` of each track's output.
        joints: (4n,) NumPy ints, each track's joint (static).
        x_nominal: (n, 2) nominal states ``x_n(k)``; qdd_nominal: (n,) ``qdd_n(k)``.
        nominal, lo, hi: (2n,) the parameter box; kp, kd: (n,); dt: s.

    Returns:
        (4n, 2) own states ``x_i(k+1)`` (SPEC section 4, per_joint).
    """
    n = u.shape[0]
    pieces, order = [], []
    for i in range(n):
        tracks = np.flatnonzero(joints == i)
        step = jax.vmap(
            lambda x, w, i=i: _per_joint_track_step(
                i, x, w, u, x_nominal, qdd_nominal, nominal, lo, hi, kp, kd, dt
            )
        )
        pieces.append(step(states[tracks], weights[tracks]))
        order.append(tracks)
    return jnp.concatenate(pieces)[np.argsort(np.concatenate(order))]


# --------------------------------------------------------------------------
# The search as the engine takes it
# --------------------------------------------------------------------------

_WINDOW_DATA_BYTES = 64 * 2**10
"""Allowance for the window's own arrays and XLA's small buffers, per end step."""


def estimate_memory(params, *, mode, itemsize):
    """Working set of one end step of the planar arm's factored search, in bytes.

    ``coupled``: every track holds ``O(n^2)`` values per mass corner (the
    factorisation) and ``O(n)`` per (mass corner, length combo); XLA's buffer
    analysis (float64, n = 1..8, one and four end steps per batch) measured
    28-136 x ``4n 2^n`` values, growing like ``0.75 n^2``. ``per_joint``: joint 1
    enumerates ``4^n`` corners on its four tracks; measured 8.5-70 x ``4 4^n``.
    The estimates below, plus 64 KiB for the window's own data, lie above every
    measurement by 1.3-4x.
    """
    n = params.n_joints
    if mode == "coupled":
        return _WINDOW_DATA_BYTES + 4 * n * 2**n * itemsize * (n * n + 4 * n + 16)
    return _WINDOW_DATA_BYTES + 4 * 4**n * itemsize * (2 * n + 8)


@dataclasses.dataclass(frozen=True)
class FactoredSearch:
    """A corner search that runs whole window steps over all tracks at once.

    Attributes:
        coupled_step, per_joint_step: the window steps of each mode.
        estimate_memory: ``(params, *, mode, itemsize) -> bytes`` of one end step.
        max_links: the largest arm it takes.
    """

    coupled_step: Callable
    per_joint_step: Callable
    estimate_memory: Callable
    max_links: int
    needs_corners = False


SEARCH = FactoredSearch(coupled_window_step, per_joint_window_step, estimate_memory, MAX_LINKS)
"""The planar arm's exact factored search, as :func:`rmijax.methods.choosers.resolve` returns it."""
