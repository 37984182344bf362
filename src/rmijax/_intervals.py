"""Outward-rounded interval arithmetic in JAX and interval 2-jets (value, gradient, Hessian).

Used by :mod:`rmijax.methods.certified` to enclose the closed loop's perturbation and its
first and second derivatives over a box. Two layers:

- :class:`Interval`: ``[lo, hi]`` arrays in float64 (or float32). Every
  operation rounds outward: the float result of ``+ - *`` and ``/`` is within
  half an ulp of the exact result (IEEE round-to-nearest), and each bound is
  then moved outward by ``|x| 2^-50 + 2^-1000`` (4-8 ulps, plus a normal
  number that also covers underflow and flush-to-zero), so the exact real result
  of the operation on any reals in the operands lies inside. ``sin`` and
  ``cos`` are moved by a further ``2^-44`` absolute (XLA's float64
  ``sin``/``cos`` are accurate to a few ulps of 1).
- :class:`Jet`: a second-order Taylor jet ``(v, g, H)`` with interval entries.
  Evaluating a function on jets whose value intervals cover a box ``Z`` and
  whose derivative parts are the input's derivatives (the chain rule, each
  intermediate enclosed over ``Z``) gives intervals that contain the
  function's value, gradient and Hessian at *every* point of ``Z``. At a
  single point (zero-width values) it gives enclosures of the exact
  derivatives there.

The jet code is written against a tiny backend (``sin``, ``cos``, ``tanh``,
``recip``, ``sqr`` and the operators) so the same formulas run on
:class:`Interval` (JAX, fast) and on ``mpmath.iv`` object arrays (the
independent checker in :mod:`rmijax.methods.certificate_check`).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["Interval", "Jet", "JAX_BACKEND"]

_REL = 2.0**-50
_TINY = 2.0**-1000
_TRIG_ABS = 2.0**-44


def down(x):
    """A float below the exact real that ``x`` (one rounded operation) approximates."""
    return x - (jnp.abs(x) * _REL + _TINY)


def up(x):
    """A float above the exact real that ``x`` (one rounded operation) approximates."""
    return x + (jnp.abs(x) * _REL + _TINY)


@jax.tree_util.register_pytree_node_class
class Interval:
    """Closed intervals ``[lo, hi]`` elementwise, with outward rounding.

    Operands may be :class:`Interval` or exact floats/arrays (taken as points).
    """

    __array_priority__ = 1000

    def __init__(self, lo, hi=None):
        self.lo = jnp.asarray(lo)
        self.hi = self.lo if hi is None else jnp.asarray(hi)

    def tree_flatten(self):
        return (self.lo, self.hi), None

    @classmethod
    def tree_unflatten(cls, aux, children):
        return cls(*children)

    @property
    def shape(self):
        return jnp.broadcast_shapes(self.lo.shape, self.hi.shape)

    def __getitem__(self, index):
        return Interval(self.lo[index], self.hi[index])

    def __repr__(self):
        return f"Interval(lo={self.lo!r}, hi={self.hi!r})"

    @staticmethod
    def _of(x):
        return x if isinstance(x, Interval) else Interval(x)

    def __add__(self, other):
        o = Interval._of(other)
        return Interval(down(self.lo + o.lo), up(self.hi + o.hi))

    __radd__ = __add__

    def __neg__(self):
        return Interval(-self.hi, -self.lo)

    def __sub__(self, other):
        o = Interval._of(other)
        return Interval(down(self.lo - o.hi), up(self.hi - o.lo))

    def __rsub__(self, other):
        return Interval._of(other) - self

    def __mul__(self, other):
        o = Interval._of(other)
        p = jnp.stack(
            jnp.broadcast_arrays(self.lo * o.lo, self.lo * o.hi, self.hi * o.lo, self.hi * o.hi)
        )
        return Interval(down(jnp.min(p, axis=0)), up(jnp.max(p, axis=0)))

    __rmul__ = __mul__

    def __truediv__(self, other):
        return self * recip(Interval._of(other))

    def __rtruediv__(self, other):
        return Interval._of(other) * recip(self)

    def mag(self):
        """``max |x|`` over the interval (exact)."""
        return jnp.maximum(jnp.abs(self.lo), jnp.abs(self.hi))

    def mid(self):
        """A float inside the interval."""
        return jnp.clip(0.5 * self.lo + 0.5 * self.hi, self.lo, self.hi)

    def radius_about(self, center):
        """An upper bound of ``max |x - center|`` over the interval."""
        return up(jnp.maximum(self.hi - center, center - self.lo))

    def sum(self, axis):
        """Interval sum along ``axis``; float rounding covered by ``k 2^-52 sum|x|``."""
        count = self.lo.shape[axis]
        slack = (count + 2) * 2.0**-52
        lo, hi = jnp.sum(self.lo, axis), jnp.sum(self.hi, axis)
        return Interval(
            lo - (slack * jnp.sum(jnp.abs(self.lo), axis) + _TINY),
            hi + (slack * jnp.sum(jnp.abs(self.hi), axis) + _TINY),
        )


def recip(x: Interval) -> Interval:
    """``1 / x``; an interval that contains 0 gives ``[-inf, inf]``."""
    safe = (x.lo > 0) | (x.hi < 0)
    lo = jnp.where(safe, down(1.0 / x.hi), -jnp.inf)
    hi = jnp.where(safe, up(1.0 / x.lo), jnp.inf)
    return Interval(lo, hi)


def sqr(x: Interval) -> Interval:
    """``x^2`` without the dependency loss of ``x * x``."""
    a, b = x.lo * x.lo, x.hi * x.hi
    lo = jnp.where(x.lo >= 0, a, jnp.where(x.hi <= 0, b, 0.0))
    return Interval(jnp.maximum(down(lo), 0.0), up(jnp.maximum(a, b)))


def _contains(lo, hi, phase):
    """Whether ``[lo, hi]`` may contain a point ``phase + 2 pi k`` (errs towards yes)."""
    two_pi = 2.0 * math.pi
    k = jnp.ceil((lo - phase) / two_pi - 1e-9)
    point = phase + two_pi * k
    return point <= hi + 1e-9 * (1.0 + jnp.abs(hi))


def _trig(x: Interval, fn, top_phase, bottom_phase) -> Interval:
    a, b = fn(x.lo), fn(x.hi)
    lo, hi = jnp.minimum(a, b), jnp.maximum(a, b)
    wide = (x.hi - x.lo) >= 6.0
    hi = jnp.where(wide | _contains(x.lo, x.hi, top_phase), 1.0, hi)
    lo = jnp.where(wide | _contains(x.lo, x.hi, bottom_phase), -1.0, lo)
    slack = jnp.abs(x.lo) * _REL + jnp.abs(x.hi) * _REL + _TRIG_ABS
    return Interval(jnp.maximum(lo - slack, -1.0), jnp.minimum(hi + slack, 1.0))


def tanh(x: Interval) -> Interval:
    """Enclosure of ``tanh`` over ``x`` (increasing), clipped to ``[-1, 1]``.

    XLA's float64 ``tanh`` measured within 3.5 ulps of the exact value (200 000 points
    in ``[-40, 40]`` against ``mpmath``); the bounds are moved by ``2^-44`` absolute as
    for ``sin``/``cos`` (``|tanh| <= 1``, so that is over 200 ulps of any result), then
    by the usual outward step.
    """
    lo = jnp.maximum(down(jnp.tanh(x.lo) - _TRIG_ABS), -1.0)
    hi = jnp.minimum(up(jnp.tanh(x.hi) + _TRIG_ABS), 1.0)
    return Interval(lo, hi)


def sin(x: Interval) -> Interval:
    """Enclosure of ``sin`` over ``x`` (extrema at ``pi/2 + 2 pi k`` and ``-pi/2 + 2 pi k``)."""
    return _trig(x, jnp.sin, 0.5 * math.pi, -0.5 * math.pi)


def cos(x: Interval) -> Interval:
    """Enclosure of ``cos`` over ``x`` (extrema at ``2 pi k`` and ``pi + 2 pi k``)."""
    return _trig(x, jnp.cos, 0.0, math.pi)


class _JaxBackend:
    """The operations :class:`Jet` needs, on :class:`Interval` arrays."""

    sin = staticmethod(sin)
    cos = staticmethod(cos)
    tanh = staticmethod(tanh)
    recip = staticmethod(recip)
    sqr = staticmethod(sqr)

    @staticmethod
    def is_interval(x):
        return isinstance(x, Interval)

    @staticmethod
    def zeros(shape, like):
        zero = jnp.zeros(shape, like.lo.dtype)
        return Interval(zero, zero)

    @staticmethod
    def outer(a, b):
        return a[:, None] * b[None, :]

    @staticmethod
    def point(value):
        return Interval(value)


JAX_BACKEND = _JaxBackend()


class Jet:
    """A second-order jet of intervals: value ``v``, gradient ``g`` (m,), Hessian ``h`` (m, m).

    Supports ``+ - *``, ``/``, ``sin``, ``cos``, ``tanh``, ``sqr`` with other jets, with
    intervals (of the backend; taken as constants) and with floats.
    """

    __slots__ = ("v", "g", "h", "backend")

    def __init__(self, v, g, h, backend):
        self.v, self.g, self.h, self.backend = v, g, h, backend

    # ---- constants -------------------------------------------------------
    def _lift(self, other):
        if isinstance(other, Jet):
            return other
        return None

    def __add__(self, other):
        o = self._lift(other)
        if o is None:
            return Jet(self.v + other, self.g, self.h, self.backend)
        return Jet(self.v + o.v, self.g + o.g, self.h + o.h, self.backend)

    __radd__ = __add__

    def __neg__(self):
        return Jet(-self.v, -self.g, -self.h, self.backend)

    def __sub__(self, other):
        o = self._lift(other)
        if o is None:
            return Jet(self.v - other, self.g, self.h, self.backend)
        return Jet(self.v - o.v, self.g - o.g, self.h - o.h, self.backend)

    def __rsub__(self, other):
        return (-self) + other

    def __mul__(self, other):
        o = self._lift(other)
        if o is None:  # a constant (float or interval)
            return Jet(self.v * other, self.g * other, self.h * other, self.backend)
        cross = self.backend.outer(self.g, o.g) + self.backend.outer(o.g, self.g)
        return Jet(
            self.v * o.v,
            self.g * o.v + o.g * self.v,
            self.h * o.v + o.h * self.v + cross,
            self.backend,
        )

    __rmul__ = __mul__

    def reciprocal(self):
        r = self.backend.recip(self.v)
        r2 = self.backend.sqr(r)
        return Jet(
            r,
            self.g * (-r2),
            self.h * (-r2) + self.backend.outer(self.g, self.g) * (r2 * r * 2.0),
            self.backend,
        )

    def __truediv__(self, other):
        o = self._lift(other)
        if o is None:
            if self.backend.is_interval(other):
                return self * self.backend.recip(other)
            return self * (1.0 / self.backend.point(other))
        return self * o.reciprocal()

    def __rtruediv__(self, other):
        return self.reciprocal() * other

    def square(self):
        return Jet(
            self.backend.sqr(self.v),
            self.g * (self.v * 2.0),
            (self.h * self.v + self.backend.outer(self.g, self.g)) * 2.0,
            self.backend,
        )

    def sin(self):
        s, c = self.backend.sin(self.v), self.backend.cos(self.v)
        return Jet(s, self.g * c, self.h * c - self.backend.outer(self.g, self.g) * s, self.backend)

    def cos(self):
        s, c = self.backend.sin(self.v), self.backend.cos(self.v)
        return Jet(
            c, self.g * (-s), self.h * (-s) - self.backend.outer(self.g, self.g) * c, self.backend
        )

    def tanh(self):
        """``t = tanh(v)``, ``t' = 1 - t^2``, ``t'' = -2 t t'``, with ``t`` the enclosure of
        ``tanh`` over the value (so both derivatives hold over it too)."""
        t = self.backend.tanh(self.v)
        slope = 1.0 - self.backend.sqr(t)
        bend = t * slope * -2.0
        hess = self.h * slope + self.backend.outer(self.g, self.g) * bend
        return Jet(t, self.g * slope, hess, self.backend)


def constant_jet(value, m, backend, like):
    """A jet of a constant (interval or float) in ``m`` variables."""
    v = value if backend.is_interval(value) else backend.point(value)
    return Jet(v, backend.zeros((m,), like), backend.zeros((m, m), like), backend)


# --------------------------------------------------------------------------
# A tape of jet operations, replayed by one small XLA loop
# --------------------------------------------------------------------------
# Tracing the jet formulas straight into XLA unrolls every scalar operation
# (16k HLO lines for two joints, four minutes of compilation). Instead the
# formulas are recorded once in Python as a tape of elementary operations and
# replayed by a ``fori_loop`` whose body is a ``lax.switch`` over ten kinds:
# the program's size no longer grows with the robot.

_OPS = ("const", "add", "sub", "mul", "neg", "recip", "sqr", "sin", "cos", "tanh")
_CODE = {name: code for code, name in enumerate(_OPS)}


class Tape:
    """Recorded operations: ``ops`` (N,) codes, ``args`` (N, 2) operand rows, ``lits`` (N,)."""

    def __init__(self, n_leaves):
        self.n_leaves = n_leaves
        self.ops, self.args, self.lits = [], [], []

    def leaves(self):
        return [_Node(self, i) for i in range(self.n_leaves)]

    def _push(self, op, a=0, b=0, lit=0.0):
        self.ops.append(_CODE[op])
        self.args.append((a, b))
        self.lits.append(float(lit))
        return _Node(self, self.n_leaves + len(self.ops) - 1)

    def arrays(self):
        return (
            np.asarray(self.ops, np.int32),
            np.asarray(self.args, np.int32).reshape(-1, 2),
            np.asarray(self.lits, np.float64),
        )


class _Node:
    """A value on a :class:`Tape` (supports the operators the jet formulas use)."""

    __slots__ = ("tape", "index")

    def __init__(self, tape, index):
        self.tape, self.index = tape, index

    def _of(self, other):
        if isinstance(other, _Node):
            return other
        return self.tape._push("const", lit=float(other))

    def __add__(self, other):
        return self.tape._push("add", self.index, self._of(other).index)

    __radd__ = __add__

    def __sub__(self, other):
        return self.tape._push("sub", self.index, self._of(other).index)

    def __rsub__(self, other):
        return self.tape._push("sub", self._of(other).index, self.index)

    def __mul__(self, other):
        return self.tape._push("mul", self.index, self._of(other).index)

    __rmul__ = __mul__

    def __neg__(self):
        return self.tape._push("neg", self.index)

    def reciprocal(self):
        return self.tape._push("recip", self.index)

    def __truediv__(self, other):
        return self * self._of(other).reciprocal()

    def __rtruediv__(self, other):
        return self._of(other) * self.reciprocal()

    def square(self):
        return self.tape._push("sqr", self.index)

    def sin(self):
        return self.tape._push("sin", self.index)

    def cos(self):
        return self.tape._push("cos", self.index)

    def tanh(self):
        return self.tape._push("tanh", self.index)


def jet_branches(jet, flat, const):
    """The ``switch`` branches of a tape replay, one per op code of :data:`_OPS`.

    ``jet(row)`` builds a :class:`Jet` from one buffer row (a tuple of arrays), ``flat(j)``
    flattens one back, ``const(lit)`` is a literal's row.
    """
    return [
        lambda a, b, lit: const(lit),
        lambda a, b, lit: flat(jet(a) + jet(b)),
        lambda a, b, lit: flat(jet(a) - jet(b)),
        lambda a, b, lit: flat(jet(a) * jet(b)),
        lambda a, b, lit: flat(-jet(a)),
        lambda a, b, lit: flat(jet(a).reciprocal()),
        lambda a, b, lit: flat(jet(a).square()),
        lambda a, b, lit: flat(jet(a).sin()),
        lambda a, b, lit: flat(jet(a).cos()),
        lambda a, b, lit: flat(jet(a).tanh()),
    ]


def _slots(ops, args, n_leaves, outputs):
    """Buffer rows for a tape's values, reused once a value is dead.

    Returns ``(dest (N,), args (N, 2), out (k,), size)``: op ``i`` writes row ``dest[i]``
    and reads rows ``args[i]``; the outputs end in rows ``out``; ``size >= n_leaves``
    rows in all (the leaves start in rows ``0..L-1``). A value's row is given back after
    the op that reads it last (an op reads both operands before it writes, so its result
    may take an operand's row); the outputs' rows are never given back. On the loaded
    arms' tapes 173-210 rows instead of 2777-4511.
    """
    n_ops = ops.shape[0]
    last = np.full(n_leaves + n_ops, -1, np.int64)
    for i in range(n_ops):
        if ops[i] != _CODE["const"]:  # a literal reads no operand
            last[args[i, 0]] = i
            last[args[i, 1]] = i
    last[np.asarray(outputs, np.int64)] = n_ops
    row = np.arange(n_leaves + n_ops, dtype=np.int64)  # a value's row
    free = [j for j in range(n_leaves) if last[j] < 0][::-1]
    dying = [[] for _ in range(n_ops)]
    for j in range(n_leaves + n_ops):
        if 0 <= last[j] < n_ops:
            dying[last[j]].append(j)
    dest = np.empty(n_ops, np.int64)
    new_args = np.empty((n_ops, 2), np.int64)
    size = n_leaves
    for i in range(n_ops):
        new_args[i] = row[args[i]]
        free.extend(row[j] for j in dying[i])
        if free:
            dest[i] = free.pop()
        else:
            dest[i], size = size, size + 1
        row[n_leaves + i] = dest[i]
        if last[n_leaves + i] < 0:  # never read: its row is free again at once
            free.append(dest[i])
    out = row[np.asarray(outputs, np.int64)]
    return dest.astype(np.int32), new_args.astype(np.int32), out.astype(np.int32), size


def replay(tape_arrays, leaves, branches, outputs):
    """Replay a tape: one ``fori_loop`` step per op, each a ``switch`` over ``branches``.

    The buffers hold the live values only (:func:`_slots`): a dead value's row is reused,
    which keeps them small enough for the cache (and for forms over many symbols).

    Args:
        tape_arrays: ``(ops, args, lits)`` from :meth:`Tape.arrays` (numpy arrays).
        leaves: arrays with the ``L`` leaves' rows on their first axis (the buffers'
            layout, whatever the backend).
        branches: from :func:`jet_branches`.
        outputs: (k,) rows wanted.

    Returns:
        The buffers' rows ``outputs``, one array per leaf array.
    """
    ops, args, lits = (np.asarray(a) for a in tape_arrays)
    n_leaves = leaves[0].shape[0]
    dtype = leaves[0].dtype
    dest, args, out, size = _slots(ops, args, n_leaves, outputs)
    buffers = tuple(
        jnp.concatenate([leaf, jnp.zeros((size - n_leaves,) + leaf.shape[1:], dtype)])
        for leaf in leaves
    )
    ops, args, lits, dest = (jnp.asarray(a) for a in (ops, args, lits, dest))

    def body(i, buffers):
        op, (a, b), lit = ops[i], args[i], lits[i].astype(dtype)
        first = tuple(buf[a] for buf in buffers)
        second = tuple(buf[b] for buf in buffers)
        result = jax.lax.switch(op, branches, first, second, lit)
        row = dest[i]
        return tuple(buf.at[row].set(r) for buf, r in zip(buffers, result, strict=True))

    buffers = jax.lax.fori_loop(0, ops.shape[0], body, buffers)
    rows = jnp.asarray(out)
    return tuple(buf[rows] for buf in buffers)


class PackedHessians:
    """The Hessian rows of a tape replay stored packed: the upper triangle, ``m (m + 1) / 2``
    entries instead of ``m^2``.

    Every jet operation acts on Hessians entrywise or through ``outer(a, b) + outer(b,
    a)``, ``outer(a, a)``, whose ``(i, j)`` and ``(j, i)`` entries are the same float
    operations in swapped order (commutative, so equal): the upper triangle alone
    carries the whole Hessian, in about half the work and memory. (Measured against the
    full replay: the certified bands of the two-joint arm, the affine pendulum and
    ``preset_arm(4)`` equal to the bit; the noisy pendulum's within an ulp, where XLA
    fused the arithmetic differently; both are rounded outward as bounded.)
    """

    def __init__(self, m, backend):
        self.base = backend
        self.rows, self.cols = (np.asarray(i, np.int32) for i in np.triu_indices(m))
        full = np.zeros((m, m), np.int32)
        full[self.rows, self.cols] = np.arange(self.rows.size)
        full[self.cols, self.rows] = np.arange(self.rows.size)
        self.full = full

    @property
    def size(self):
        return self.rows.size

    def pack(self, x):
        """``(L, m, m, ...)`` -> ``(L, P, ...)``."""
        return x[:, self.rows, self.cols]

    def unpack(self, x):
        """``(L, P, ...)`` -> ``(L, m, m, ...)``."""
        return x[:, self.full]

    def __getattr__(self, name):  # everything but outer is the base backend's
        return getattr(self.base, name)

    def outer(self, a, b):
        return a[self.rows] * b[self.cols]


def run_tape(tape_arrays, leaves, outputs):
    """Replay a tape on interval jets.

    Args:
        tape_arrays: ``(ops, args, lits)`` from :meth:`Tape.arrays`.
        leaves: six arrays ``(v_lo, v_hi (L,), g_lo, g_hi (L, m), h_lo, h_hi (L, m, m))``.
        outputs: (k,) rows of the results wanted.

    Returns:
        ``(value, grad, hess)`` Intervals (k,), (k, m), (k, m, m).
    """
    m = leaves[2].shape[1]
    dtype = leaves[0].dtype
    packed = PackedHessians(m, JAX_BACKEND)
    zero_g = jnp.zeros((m,), dtype)
    zero_h = jnp.zeros((packed.size,), dtype)

    def jet(a):
        return Jet(Interval(a[0], a[1]), Interval(a[2], a[3]), Interval(a[4], a[5]), packed)

    def flat(j):
        return (j.v.lo, j.v.hi, j.g.lo, j.g.hi, j.h.lo, j.h.hi)

    def const(lit):
        return (lit, lit, zero_g, zero_g, zero_h, zero_h)

    leaves = tuple(leaves[:4]) + tuple(packed.pack(h) for h in leaves[4:])
    out = replay(tape_arrays, leaves, jet_branches(jet, flat, const), outputs)
    hess = Interval(packed.unpack(out[4]), packed.unpack(out[5]))
    return Interval(out[0], out[1]), Interval(out[2], out[3]), hess
