"""Small dense linear algebra written element by element, for ``vmap`` over many tiny systems.

A batched ``jnp.linalg.solve`` over millions of ``n x n`` matrices is 8-80x
slower on CPU than the factorisation written out on scalars (PERF_NOTES), so
the planar arm's dynamics and the structured corner searches use these.
"""

from __future__ import annotations

__all__ = ["ldl_factor", "ldl_solve"]


def ldl_factor(matrix):
    """``LDL'`` factorisation of a symmetric matrix given element by element.

    Args:
        matrix: ``matrix[a][b]`` for ``b <= a`` (the lower triangle), each an
            array of any shape (the factorisation runs elementwise over it).

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
        inv_diag[j] = 1.0 / d
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
