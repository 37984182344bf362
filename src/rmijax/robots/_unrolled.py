"""3-vector and 3x3 algebra written out on scalars, for code vectorised over a trailing axis.

A vector is a tuple of 3 entries, a matrix a tuple of 3 rows; each entry is a
Python float (a constant of the robot description) or an array (one value per
track). Products with a constant 0 or 1 are folded here, before tracing, so
the sparse joint frames of real arms (axes along ``z``, frames turned by
quarter turns) cost only the multiply-adds they need.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "add",
    "constant",
    "cross",
    "dot",
    "is_constant",
    "matmul",
    "matvec",
    "mul",
    "plus_cross_force",
    "sub",
]


def is_constant(x) -> bool:
    """True for a Python number (folded at trace time), False for an array."""
    return isinstance(x, int | float)


def add(a, b):
    if is_constant(a) and a == 0:
        return b
    if is_constant(b) and b == 0:
        return a
    return a + b


def mul(a, b):
    if is_constant(b):
        a, b = b, a
    if is_constant(a):
        if a == 0:
            return 0.0
        if a == 1:
            return b
        if a == -1:
            return -b
    return a * b


def sub(a, b):
    return add(a, mul(-1.0, b))


def dot(u, v):
    out = 0.0
    for a, b in zip(u, v, strict=True):
        out = add(out, mul(a, b))
    return out


def cross(a, b):
    return (
        sub(mul(a[1], b[2]), mul(a[2], b[1])),
        sub(mul(a[2], b[0]), mul(a[0], b[2])),
        sub(mul(a[0], b[1]), mul(a[1], b[0])),
    )


def plus_cross_force(force, velocity, momentum):
    """``force + v x* momentum`` for spatial vectors (6-tuples, angular first): the spatial
    force cross product ``v x* h = (w x h_ang + v_o x h_lin, w x h_lin)``, added in the
    order ``(force + w x h_ang) + v_o x h_lin`` (a body's ``I a + v x* I v``)."""
    w, vo = velocity[:3], velocity[3:]
    torque = tuple(
        add(add(f, x), y)
        for f, x, y in zip(force[:3], cross(w, momentum[:3]), cross(vo, momentum[3:]), strict=True)
    )
    push = tuple(add(f, x) for f, x in zip(force[3:], cross(w, momentum[3:]), strict=True))
    return torque + push


def matvec(matrix, vector):
    return tuple(dot(row, vector) for row in matrix)


def matmul(left, right):
    columns = tuple(zip(*right, strict=True))
    return tuple(tuple(dot(row, column) for column in columns) for row in left)


def constant(array, *, snap=0.0):
    """A NumPy array as nested tuples of floats; entries with ``|x| <= snap`` become 0.

    ``snap`` removes the rounding residue of exact zeros (``cos(pi/2) = 6e-17`` in a
    frame turned by a quarter turn), so the product with it is folded away.
    """
    array = np.asarray(array, dtype=np.float64)
    array = np.where(np.abs(array) <= snap, 0.0, array)
    if array.ndim == 1:
        return tuple(float(x) for x in array)
    return tuple(constant(row) for row in array)
