"""Small dense linear algebra written element by element, for ``vmap`` over many tiny systems.

A batched ``jnp.linalg.solve`` over millions of ``n x n`` matrices is 8-80x
slower on CPU than the factorisation written out on scalars (PERF_NOTES), so
the planar arm's dynamics and the structured corner searches use these. Under
``vmap`` of reverse-mode derivatives in float64, jaxlib 0.10.2's batched LAPACK
``trsm`` (behind ``jnp.linalg.solve`` and ``cho_solve``) also hung on large
batches on this CPU (README, "Known problem"), so every ``M qdd = tau - h`` of
the library goes through :func:`spd_solve`, which above :data:`UNROLL_MAX` joints
loops over columns instead of writing the factorisation out.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["UNROLL_MAX", "ldl_factor", "ldl_solve", "materialise", "reciprocal", "spd_solve"]

_SEED = {8: (np.int64(0x7FDE623822FC16E6), 5), 4: (np.int32(0x7EF311C3), 4)}
"""Per item size: the bit-trick constant of a reciprocal's seed and the Newton steps."""


def reciprocal(x):
    """``1 / x`` without a divide, for nonzero finite ``x``: a bit-trick seed and Newton steps.

    XLA's CPU fusion splits a loop at every divide (it counts it as expensive),
    so a factorisation over many tiny matrices becomes one kernel per pivot. The
    seed ``magic - bits(|x|)`` is within 12% of ``1/|x|``; each step
    ``y (2 - |x| y)`` squares the relative error (5 steps in float64, 4 in
    float32, to within a few units in the last place).
    """
    dtype = jnp.asarray(x).dtype
    magic, steps = _SEED[dtype.itemsize]
    itype = jnp.int64 if dtype.itemsize == 8 else jnp.int32
    size = jnp.abs(x)
    y = jax.lax.bitcast_convert_type(magic - jax.lax.bitcast_convert_type(size, itype), dtype)
    for _ in range(steps):
        y = y * (2.0 - size * y)
    return jnp.where(x < 0, -y, y)


def ldl_factor(matrix, *, divide=True):
    """``LDL'`` factorisation of a symmetric matrix given element by element.

    Args:
        matrix: ``matrix[a][b]`` for ``b <= a`` (the lower triangle), each an
            array of any shape (the factorisation runs elementwise over it).

        divide: False to take the pivots' reciprocals by :func:`reciprocal`
            (keeps XLA's CPU fusion in one loop; a few units in the last place).

    Returns:
        ``(lower, diag, inv_diag)``: ``lower[i][j]`` for ``j < i`` of the unit
        lower factor, the pivots and their reciprocals.
    """
    n = len(matrix)
    lower = [[None] * n for _ in range(n)]
    diag, inv_diag = [None] * n, [None] * n
    for j in range(n):
        d = matrix[j][j]
        for k in range(j):
            d = d - lower[j][k] * lower[j][k] * diag[k]
        diag[j] = d
        inv_diag[j] = 1.0 / d if divide else reciprocal(d)
        for i in range(j + 1, n):
            s = matrix[i][j]
            for k in range(j):
                s = s - lower[i][k] * lower[j][k] * diag[k]
            lower[i][j] = s * inv_diag[j]
    return lower, diag, inv_diag


def ldl_solve(lower, inv_diag, rhs):
    """Solve ``L D L' x = rhs`` with the factors of :func:`ldl_factor` (lists in, list out)."""
    n = len(rhs)
    y = list(rhs)
    for i in range(n):
        for k in range(i):
            y[i] = y[i] - lower[i][k] * y[k]
    x = [None] * n
    for i in range(n - 1, -1, -1):
        s = y[i] * inv_diag[i]
        for k in range(i + 1, n):
            s = s - lower[k][i] * x[k]
        x[i] = s
    return x


UNROLL_MAX = 8
"""Largest ``n`` that :func:`spd_solve` writes out element by element.

The written-out factorisation has ``O(n^3)`` scalar operations in the program; under
forward-mode differentiation with many tangents its compile time grows fast (one
16-link ``linearized`` test took 950 s in CI; 7 s with the loop). Above this size the
factorisation runs as a loop over columns (:func:`_spd_solve_loop`)."""


def spd_solve(matrix, rhs):
    """Solve ``matrix x = rhs`` for a symmetric positive definite ``matrix`` (..., n, n).

    ``LDL'`` without pivoting and without a LAPACK call: written out element by
    element up to :data:`UNROLL_MAX` joints (``n`` static), a loop over the columns
    above. Only the lower triangle is read. ``rhs`` (..., n) with the matrix's leading
    shape (above :data:`UNROLL_MAX` it is broadcast to it). Returns ``x`` (..., n).
    A mass matrix is positive definite (``check_model`` refuses one that is not before
    any method runs).
    """
    size = matrix.shape[-1]
    if size > UNROLL_MAX:
        return _spd_solve_loop(matrix, rhs)
    lower, _, inv_diag = ldl_factor(
        [[matrix[..., a, b] for b in range(a + 1)] for a in range(size)]
    )
    return jnp.stack(ldl_solve(lower, inv_diag, [rhs[..., a] for a in range(size)]), -1)


def _spd_solve_loop(matrix, rhs):
    """:func:`spd_solve` as ``fori_loop``s over columns: the program's size does not grow with n.

    Column ``j``: ``d_j = A_jj - sum_(k<j) L_jk^2 d_k`` and ``L_ij = (A_ij - sum_(k<j) L_ik
    L_jk d_k) / d_j`` for ``i > j`` (the same arithmetic as :func:`ldl_factor`, summed as
    vectors); then ``L y = b`` forward and ``D L' x = y`` backward, one row per iteration.
    """
    size = matrix.shape[-1]
    index = jnp.arange(size)

    def factor(j, carry):
        low, diag = carry
        row = jnp.take(low, j, axis=-2)  # (..., n): L_jk, zero for k >= j
        weighted = row * diag
        column = jnp.take(matrix, j, axis=-1)  # A_ij; only i >= j (the lower triangle) is kept
        d_j = jnp.take(column, j, axis=-1) - jnp.sum(row * weighted, -1)
        col = (column - jnp.einsum("...ik,...k->...i", low, weighted)) / d_j[..., None]
        col = jnp.where(index > j, col, 0.0)
        low = jax.lax.dynamic_update_slice_in_dim(low, col[..., :, None], j, axis=-1)
        diag = jax.lax.dynamic_update_slice_in_dim(diag, d_j[..., None], j, axis=-1)
        return low, diag

    low0 = jnp.zeros(matrix.shape, matrix.dtype)
    diag0 = jnp.zeros(matrix.shape[:-1], matrix.dtype)
    low, diag = jax.lax.fori_loop(0, size, factor, (low0, diag0))
    rhs = jnp.broadcast_to(rhs, matrix.shape[:-1]).astype(matrix.dtype)

    def forward(i, y):  # L y = b, unit lower L
        y_i = jnp.take(rhs, i, axis=-1) - jnp.sum(jnp.take(low, i, axis=-2) * y, -1)
        return jax.lax.dynamic_update_slice_in_dim(y, y_i[..., None], i, axis=-1)

    y = jax.lax.fori_loop(0, size, forward, jnp.zeros_like(rhs))

    def backward(step, x):  # L' x = y / d, from the last row
        i = size - 1 - step
        x_i = jnp.take(y, i, axis=-1) / jnp.take(diag, i, axis=-1) - jnp.sum(
            jnp.take(low, i, axis=-1) * x, -1
        )
        return jax.lax.dynamic_update_slice_in_dim(x, x_i[..., None], i, axis=-1)

    return jax.lax.fori_loop(0, size, backward, jnp.zeros_like(rhs))


def materialise(arrays):
    """Materialise arrays once, in one kernel: a variadic max-reduction of each over a
    broadcast leading axis of length 2 (exact).

    XLA's CPU backend has no multi-output loop fusion and fuses cheap producers into
    every consumer; a variadic reduction computes all its operands in one loop and is
    not fused into its consumers, so the arrays' common work runs once.
    """
    if not arrays:
        return []
    shape = jnp.broadcast_shapes(*(a.shape for a in arrays))
    wide = tuple(jnp.broadcast_to(a, (2, *shape)) for a in arrays)
    init = tuple(jnp.array(-jnp.inf, a.dtype) for a in arrays)
    out = jax.lax.reduce(
        wide, init, lambda x, y: tuple(jnp.maximum(a, b) for a, b in zip(x, y, strict=True)), (0,)
    )
    return list(out)
