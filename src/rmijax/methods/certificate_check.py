"""An independent checker of a :class:`rmijax.methods.certified.Certificate` (``mpmath.iv``).

:func:`check_certificate` re-derives, step by step, every inequality that the
certified band rests on, with ``mpmath``'s outward-rounded interval
arithmetic (53-bit, each operation rounded outward by the library) instead of
the JAX float64 code that produced the certificate. It trusts nothing in the
certificate but uses its numbers as the *claims* to verify:

1. the pieces tile the box (inside it, no two interiors meeting, volumes summing
   to the box's: a product grid or an adaptive bisection), and each centre lies in
   its piece;
2. the start: ``x_c(0) = x_d(0)``, ``S_0 = 0``, ``Q_0 = 0``;
3. for every checked step ``k``: the exact coefficients ``c0, c1, c2`` of the
   next Taylor model (the closed loop applied to the stored one, ``gv``'s jets
   at the centre) are enclosed, and the stored ``x_c(k+1), S_{k+1}, Q_{k+1}``
   differ from them by at most the rounding part; with the Lagrange remainder
   of ``gv`` over the tube that ``r_k`` defines (the Hessian enclosed by interval
   jets, or for ``enclosure="affine"`` by affine jets whose coefficients are
   ``mpmath`` intervals, :class:`_Form`; ``"paired"`` and ``"paired_inertia"``:
   :class:`_PairedForm`, whose products carry their first-order parts in pair symbols,
   of the variables that ``rmijax.methods.certified.paired_variables`` names: a choice,
   sound for any), the stored input bound
   ``w_k`` is at least the recomputed one;
4. ``propagate="kernel"``: ``r_{k+1} >= sum_{j <= k} |A^(k-j)| w_j`` with the powers
   of ``A`` in interval arithmetic (no truncation). ``propagate="carried"``: the
   checker carries its own generators, ``R_k = G eps + sum_b d_b G^b eps``, through
   its own centre loop ``A_c`` (a float inside its enclosure of the true one, the
   rest ``|A_true - A_c| r_k`` added to the new generators), ``G^b`` picking up
   ``dt e2 H_b G`` with ``H_b`` its own float midpoints; the products in interval
   arithmetic, then rebased on floats with the radii moved into the new generators;
   ``r_{k+1}`` must be at least ``|G| 1 + sum_b |d_b| |G^b| 1``. (``w_k`` then holds
   the noise's first-order term, ``1/2 z' H z`` at the centre over the blocks that are
   not carried and ``sum d_b d_c H_b R^c`` with the checker's generators.)
5. the band ``[lower_k, upper_k]`` holds every piece's enclosure
   ``x_c + range(S d + 1/2 Q[d, d]) + [-r_k, r_k] + [V_lo, V_hi]``.

Together these are the induction of :mod:`rmijax.methods.certified`, so a certificate
that passes for steps ``0..K`` proves the band for those steps. It is slow
(pure Python intervals, per step and piece on a 2-core AMD EPYC host,
``benchmarks/results/certified_checker_cpu.json``: with interval jets 0.2-0.3 s for two
joints; with affine jets about 0.13 s for the pendulum, 1.6 s for two joints, 35 s for
four and 10 minutes for the UR5e's friction box), meant for short runs. It shares with
the certifier only the formula of the perturbation
(:func:`rmijax.methods.certified.planar_perturbation_jets`, or
:func:`rmijax.methods.chain_jets.chain_perturbation_jets` for a loaded arm) and the
jet's chain rule (:class:`rmijax._intervals.Jet`), both run here on
``mpmath`` intervals or :class:`_Form`; the affine arithmetic, the loop matrix and the
generators are its own.

Requires ``mpmath`` (the ``test`` extra).
"""

from __future__ import annotations

from fractions import Fraction
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from rmijax._intervals import Jet
from rmijax.methods.certified import (
    COULOMB_MODES,
    ENCLOSURES,
    _layout,
    paired_variables,
    perturbation_jets,
    solve_matrix,
)
from rmijax.robots.spatial import COULOMB_VELOCITY

try:  # the test extra; _iv() names the install when it is missing
    from mpmath import libmp as _mp
except ImportError:  # pragma: no cover
    _mp = None

__all__ = ["CheckResult", "check_certificate"]


class CheckResult(NamedTuple):
    """Outcome of :func:`check_certificate`.

    Attributes:
        ok: True when every checked inequality holds.
        steps: steps ``k`` whose band was verified (``0..steps-1``).
        reason: the first failed check, or "" when ok.
    """

    ok: bool
    steps: int
    reason: str


_PREC = 53  # bits of the checker's interval ends


def _iv():
    try:
        from mpmath import iv
    except ImportError as error:  # pragma: no cover - mpmath is in the test extra
        raise ImportError("check_certificate needs mpmath (pip install 'rmijax[test]')") from error
    iv.prec = _PREC
    return iv


def _tanh(iv, x):
    """``tanh`` on an ``mpmath`` interval: ``1 - 2 / (exp(2x) + 1)``, ``x`` once (mpmath's
    interval context has no ``tanh``)."""
    return 1 - 2 / (iv.exp(2 * x) + 1)


class _MpBackend:
    def __init__(self, iv):
        self.iv = iv

    def tanh(self, x):
        return _tanh(self.iv, x)

    def sin(self, x):
        return self.iv.sin(x)

    def cos(self, x):
        return self.iv.cos(x)

    def recip(self, x):
        return 1 / x

    def sqr(self, x):
        return x**2

    def is_interval(self, x):
        return isinstance(x, (self.iv.mpf, np.ndarray))

    def zeros(self, shape, like=None):
        return np.full(shape, self.iv.mpf(0), dtype=object)

    def outer(self, a, b):
        return np.multiply.outer(a, b)

    def point(self, value):
        return value if isinstance(value, self.iv.mpf) else self.iv.mpf(float(value))


class _Unbounded(ArithmeticError):
    """An affine ``1/x`` over a range that holds 0."""


class _Form:
    """An affine form ``c + a . eps + e [-1, 1]`` with ``mpmath`` interval coefficients.

    For every ``eps`` in ``[-1, 1]^K`` the value lies in the interval expression
    ``c + sum_i a_i eps_i + [-e, e]`` (``c``, ``a_i``: intervals, ``e``: an interval
    whose upper end bounds the error), so each operation below is sound by interval
    arithmetic alone. The linearisations are the ones of :mod:`rmijax._affine`
    (written again here, on ``mpmath``): products bound the quadratic part by the product
    of radii intersected with a polarisation bound (:func:`_bilinear`), squares by the
    square of the radius, ``1/x`` is the min-range linearisation, ``sin`` and
    ``cos`` the first-order Taylor form with ``|f''| <= 1``. ``zero`` marks the exact
    zero (most Hessian entries), which every operation short-cuts.
    """

    __slots__ = ("c", "a", "e", "zero")

    def __init__(self, c, a, e, zero=False):
        self.c, self.a, self.e, self.zero = c, a, e, zero

    @staticmethod
    def point(iv, value, k):
        value = value if isinstance(value, iv.mpf) else iv.mpf(float(value))
        return _Form(value, np.full(k, iv.mpf(0), dtype=object), iv.mpf(0))

    @staticmethod
    def nil(iv, k):
        return _Form(iv.mpf(0), np.full(k, iv.mpf(0), dtype=object), iv.mpf(0), True)

    def rad(self):
        """Upper bound of ``|x - c|`` (a point interval): ``e + sum_i |a_i|`` in interval
        arithmetic, its upper end (:func:`_upper_sum_of_abs`)."""
        iv = _iv()
        total = _upper_sum_of_abs(iv.convert(self.e)._mpi_[1], self.a)
        return iv.make_mpf((total, total))

    def interval(self):
        r = self.rad()
        return (self.c - r).a, (self.c + r).b

    def _const(self, other):
        """``other`` (a float or an ``mpmath`` interval) as an interval, or None for a form."""
        if isinstance(other, _Form):
            return None
        if isinstance(other, np.ndarray):
            return NotImplemented
        return other if isinstance(other, _iv().mpf) else _iv().mpf(float(other))

    def __add__(self, other):
        k = self._const(other)
        if k is NotImplemented:
            return NotImplemented
        if k is not None:
            return type(self)(self.c + k, self.a, self.e)
        if self.zero:
            return other
        if other.zero:
            return self
        return type(self)(self.c + other.c, self.a + other.a, self.e + other.e)

    __radd__ = __add__

    def __neg__(self):
        if self.zero:
            return self
        return type(self)(-self.c, -self.a, self.e)

    def __sub__(self, other):
        if isinstance(other, np.ndarray):
            return NotImplemented
        return self + (-other)

    def __rsub__(self, other):
        return (-self) + other

    def __mul__(self, other):
        k = self._const(other)
        if k is NotImplemented:
            return NotImplemented
        if self.zero:
            return self
        if k is not None:
            return type(self)(self.c * k, self.a * k, self.e * abs(k).b)
        if other.zero:
            return other
        carried, centre, radius = self._quadratic(other)
        e = abs(self.c).b * other.e + abs(other.c).b * self.e + radius
        a = _combine(self.a, other.c, other.a, self.c, carried)
        return type(self)(self.c * other.c + centre, a, e)

    def _quadratic(self, other):
        """``(carried, centre, radius)`` of the product's quadratic part: nothing carried
        (else ``{symbol: raw interval}``, added to the product's coefficients),
        :func:`_bilinear`'s bound."""
        return (None, *_bilinear(self, other))

    __rmul__ = __mul__

    def __truediv__(self, other):
        k = self._const(other)
        if k is NotImplemented:
            return NotImplemented
        if k is None:
            return self * _recip(other)
        return self * (1 / k)

    def __rtruediv__(self, other):
        return _recip(self) * other


def _combine(a, c, b, d, carried=None):
    """``a * c + b * d`` (object arrays ``a``, ``b`` of intervals, intervals ``c``, ``d``),
    plus ``carried[i]`` (raw intervals) where given, by ``mpmath.libmp``'s ``mpi_mul`` and
    ``mpi_add`` on the raw ends: the same intervals as the object arrays' arithmetic
    gives, without ``mpmath.iv``'s per-operation cost. (Adding an exact zero, as the
    arrays' ``+ carried`` did where nothing is carried, changes no 53-bit end.)"""
    iv, (c, d) = _iv(), (c._mpi_, d._mpi_)
    carried = carried or {}
    out = np.empty(len(a), dtype=object)
    for i, (u, v) in enumerate(zip(a, b, strict=True)):
        w = _mp.mpi_add(_mp.mpi_mul(u._mpi_, c, _PREC), _mp.mpi_mul(v._mpi_, d, _PREC), _PREC)
        out[i] = iv.make_mpf(w if i not in carried else _mp.mpi_add(w, carried[i], _PREC))
    return out


def _bilinear(x, y):
    """``(centre, radius)``, both exact: ``(L_x + E_x)(L_y + E_y)`` lies in ``centre +
    [-radius, radius]`` for every ``eps``. The product of radii intersected with the
    polarisation ``uv = ((l u + v / l)^2 - (l u - v / l)^2) / 4`` (any real ``l != 0``):
    ``[-P^2 / 4, Q^2 / 4]`` with ``Q, P = sum_i |l a_i +- b_i / l| + l e_x + e_y / l``, as
    :mod:`rmijax._affine`, for ``l = 2^j``, ``j = sign(t) floor(|t| + 1/4)``, ``t = (log2
    s_y - log2 s_x) / 2``, ``s = sum_i |a_i|`` of the coefficients' midpoints; within
    ``1e-6`` of a step of ``floor`` every neighbour (the certifier's floats differ from
    these by ulps), the bounds intersected. Symmetric: ``x * y`` and ``y * x`` give the
    same bound."""
    # mpmath's interval functions (libmp.mpi_*, _PREC bits) on the raw ends: the same floats
    # as on mpmath.iv's objects, whose overhead was most of the checker's affine time.
    iv = _iv()
    ex, ey = iv.convert(x.e)._mpi_, iv.convert(y.e)._mpi_
    rx, ry = _upper_sum_of_abs(ex[1], x.a), _upper_sum_of_abs(ey[1], y.a)
    plain = _mp.mpi_mul((rx, rx), (ry, ry), _PREC)[1]
    if _mp.to_float(plain) == 0.0 or not np.isfinite(_mp.to_float(plain)):
        return iv.mpf(0), iv.make_mpf((plain, plain))
    sx, sy = _parts(x.a), _parts(y.a)  # the symbols' parts, as the certifier's scale
    if sx == 0.0 or sy == 0.0:
        return iv.mpf(0), iv.make_mpf((plain, plain))
    t = 0.5 * (np.log2(sy) - np.log2(sx))
    steps = {int(np.sign(u) * np.floor(abs(u) + 0.25)) for u in (t - 1e-6, t, t + 1e-6)}
    hi, lo = plain, _mp.mpf_neg(plain)
    two, four = (_mp.from_float(2.0),) * 2, (_mp.from_float(4.0),) * 2
    for j in sorted(steps):
        j = min(max(j, -400), 400)
        scale = (_mp.from_float(2.0**j),) * 2
        own = _mp.mpi_add(_mp.mpi_mul(ex, scale, _PREC), _mp.mpi_div(ey, scale, _PREC), _PREC)[1]
        q, p = _upper_polarised_sums(own, x.a, y.a, j)
        top = _mp.mpi_div(_mp.mpi_mul((q, q), (q, q), _PREC), four, _PREC)[1]
        bottom = _mp.mpf_neg(_mp.mpi_div(_mp.mpi_mul((p, p), (p, p), _PREC), four, _PREC)[1])
        hi = top if _mp.mpf_lt(top, hi) else hi
        lo = bottom if _mp.mpf_lt(lo, bottom) else lo
    middle = _mp.from_float(
        _mp.to_float(_mp.mpi_div(_mp.mpi_add((hi, hi), (lo, lo), _PREC), two, _PREC)[0])
    )
    centre = (middle, middle)
    up, down = _mp.mpi_sub((hi, hi), centre, _PREC)[1], _mp.mpi_sub(centre, (lo, lo), _PREC)[1]
    return iv.make_mpf(centre), iv.make_mpf((down,) * 2 if _mp.mpf_lt(up, down) else (up,) * 2)


def _parts(coefficients):
    """``sum_i |float(a_i.mid)|`` (Python floats), on the raw ends."""
    return sum(abs(_mp.to_float(_mp.mpi_mid(a._mpi_, _PREC))) for a in coefficients)


def _upper_sum_of_abs(start, coefficients):
    """Upper end (raw ``mpf``) of ``start + |a_1| + ... + |a_n|`` in ``mpmath`` interval
    arithmetic (``a_i`` intervals, ``start`` a raw upper end): the same float as the
    interval sum's ``.b``, computed on the raw ends instead of through ``mpmath.iv``'s
    objects, which cost most of the checker's time in its affine products. An interval
    sum's upper end depends on its operands' upper ends only (rounded up at 53 bits, NaN
    read as +inf, as ``mpmath.libmp.mpi_add``), and ``|[lo, hi]|``'s is ``max(-lo, hi)``
    (``mpi_abs``; exact)."""
    total = start
    for a in coefficients:
        total = _mp.mpf_add(total, _upper_abs(*a._mpi_), _PREC, _mp.round_ceiling)
        if total == _mp.fnan:
            total = _mp.finf
    return total


def _upper_abs(lo, hi):
    """Upper end (raw ``mpf``, exact) of ``|[lo, hi]|`` (``lo <= hi``): ``max(-lo, hi)``,
    as ``mpmath.libmp.mpi_abs``, with NaN ends read as infinite (as ``mpi_add`` leaves
    them). An end's sign is its tuple's first entry: a range on one side of 0 needs no
    comparison (most coefficients)."""
    if lo == _mp.fnan or hi == _mp.fnan:
        return _mp.finf  # -(-inf) or +inf: infinite either way
    if not lo[0]:  # 0 <= lo <= hi
        return hi
    neg = _mp.mpf_neg(lo)
    if hi[0]:  # lo <= hi < 0
        return neg
    return hi if _mp.mpf_lt(neg, hi) else neg


def _upper_polarised_sums(own, xa, ya, j):
    """``(Q, P)``, raw ``mpf``: the upper ends of ``own + sum_i |2^j a_i + 2^-j b_i|`` and
    ``own + sum_i |2^j a_i - 2^-j b_i|`` in ``mpmath`` interval arithmetic (``own`` a raw
    upper end, ``a_i``, ``b_i`` intervals), the same floats as that arithmetic gives,
    on the raw ends (:func:`_upper_sum_of_abs`): ``2^{+-j}`` scales the ends exactly, the
    sum ``[u0 + v0, u1 + v1]`` and difference ``[u0 - v1, u1 - v0]`` round outward at 53
    bits (``mpmath.libmp.mpi_add``, ``mpi_sub``)."""
    q = p = own
    for a, b in zip(xa, ya, strict=True):
        (a0, a1), (b0, b1) = a._mpi_, b._mpi_
        u0, u1 = _mp.mpf_shift(a0, j), _mp.mpf_shift(a1, j)
        v0, v1 = _mp.mpf_shift(b0, -j), _mp.mpf_shift(b1, -j)
        plus = _upper_abs(
            _mp.mpf_add(u0, v0, _PREC, _mp.round_floor),
            _mp.mpf_add(u1, v1, _PREC, _mp.round_ceiling),
        )
        minus = _upper_abs(
            _mp.mpf_sub(u0, v1, _PREC, _mp.round_floor),
            _mp.mpf_sub(u1, v0, _PREC, _mp.round_ceiling),
        )
        q = _mp.mpf_add(q, plus, _PREC, _mp.round_ceiling)
        p = _mp.mpf_add(p, minus, _PREC, _mp.round_ceiling)
        q = _mp.finf if q == _mp.fnan else q
        p = _mp.finf if p == _mp.fnan else p
    return q, p


def _recip(x):
    """``1/x`` by the min-range linearisation ``alpha x + zeta``, ``zeta`` over ``x``'s range.

    For a negative range ``1/x = -1/(-x) = alpha x - zeta(-x)``.
    """
    if x.zero:
        raise _Unbounded("1/x of the exact zero")
    lo, hi = x.interval()
    sign = 1
    if hi < 0:
        sign, lo, hi = -1, -hi, -lo
    elif not lo > 0:
        raise _Unbounded("1/x over a range that holds 0")
    iv = _iv()
    alpha = -1.0 / float(hi) ** 2  # any exact slope is sound; this one is min-range
    mag = iv.mpf(-alpha)
    zeta_hi = max((1 / lo + mag * lo).b, (1 / hi + mag * hi).b)
    zeta_lo = (2 * iv.sqrt(mag)).a  # 1/t + |alpha| t >= 2 sqrt(|alpha|) for every t > 0
    mid = iv.mpf(float((zeta_lo + zeta_hi).a) / 2)
    zeta_rad = max(abs(zeta_hi - mid).b, abs(mid - zeta_lo).b)
    return type(x)(x.c * alpha + mid * sign, x.a * alpha, mag * x.e + zeta_rad)


def _sqr(x):
    """``x^2 = c^2 + 2c (L + E) + (L + E)^2``, the last in ``[0, rad^2]``."""
    if x.zero:
        return x
    if isinstance(x, _PairedForm):
        return x * x
    r = x.rad()
    half = r * r / 2
    return _Form(x.c * x.c + half, x.a * (2 * x.c), 2 * abs(x.c).b * x.e + half)


def _trig(x, fn, slope):
    """``fn(c + d) = fn(c) + fn'(c) d + rho``, ``|rho| <= d^2 / 2``."""
    r = x.rad()
    s = slope(x.c)
    return type(x)(fn(x.c), x.a * s, abs(s).b * x.e + r * r / 2)


class _PairedForm(_Form):
    """:class:`rmijax._affine.PairedForm` on ``mpmath``: ``k`` first-order symbols, then
    one per pair ``i <= j`` (``eps_i eps_j``, and ``2 eps_i^2 - 1`` for ``i = j``) of the
    paired ones (all ``k``, or those of :func:`_paired_kind`) in ``np.triu_indices``
    order. A product carries ``(a_S . eps_S)(b_S . eps_S)`` in them exactly (interval
    coefficients) and bounds the rest: pairing all, by ``rad_x rad_y - A B``; pairing some,
    ``A_S rad(U_y) + rad(U_x) B_S`` for the products with the other part ``U`` (the
    unpaired symbols and the error), :func:`_bilinear` for ``U_x U_y``."""

    __slots__ = ()
    pairing = None  # (k, paired indices); None: every one of _first_order(K)

    def _quadratic(self, other):
        # on the raw ends (mpmath.libmp's mpi_* at _PREC bits, the same operations in the
        # same order as mpmath.iv's objects would do them, so the same floats)
        iv = _iv()
        if self.pairing is None:
            k = _first_order(len(self.a))
            index = list(range(k))
        else:
            k, index = self.pairing
        a, b = [self.a[i]._mpi_ for i in index], [other.a[i]._mpi_ for i in index]
        zero, two = (_mp.fzero, _mp.fzero), (_mp.from_float(2.0),) * 2
        carried, centre = {}, zero
        for t, (i, j) in enumerate(zip(*np.triu_indices(len(index)), strict=True)):
            if i == j:
                half = _mp.mpi_div(_mp.mpi_mul(a[i], b[i], _PREC), two, _PREC)
                carried[k + t] = half
                centre = _mp.mpi_add(centre, half, _PREC)
            else:
                carried[k + t] = _mp.mpi_add(
                    _mp.mpi_mul(a[i], b[j], _PREC), _mp.mpi_mul(a[j], b[i], _PREC), _PREC
                )
        if self.pairing is None:  # every first-order symbol paired: rad_x rad_y - A B
            low_a, low_b = zero, zero  # sum_i |a_i| from below
            for u, v in zip(a, b, strict=True):
                low_u, low_v = _mp.mpi_abs(u, _PREC)[0], _mp.mpi_abs(v, _PREC)[0]
                low_a = _mp.mpi_add(low_a, (low_u, low_u), _PREC)
                low_b = _mp.mpi_add(low_b, (low_v, low_v), _PREC)
            rx, ry = self.rad()._mpi_, other.rad()._mpi_
            rest = _mp.mpi_sub(_mp.mpi_mul(rx, ry, _PREC), _mp.mpi_mul(low_a, low_b, _PREC), _PREC)[
                1
            ]
            rest = _mp.fzero if _mp.mpf_lt(rest, _mp.fzero) else rest
            return carried, iv.make_mpf(centre), iv.make_mpf((rest, rest))
        # the rest, with x = c + L_S + U (U: the other symbols' part and the own error):
        # L_Sx U_y + U_x L_Sy, at most A_S rad(U_y) + rad(U_x) B_S, and U_x U_y by
        # _bilinear (as rmijax._affine.PairedForm's classes of paired_over)
        size_a = _upper_sum_of_abs(_mp.fzero, [self.a[i] for i in index])  # from above
        size_b = _upper_sum_of_abs(_mp.fzero, [other.a[i] for i in index])
        ux, uy = _unpaired(self, index), _unpaired(other, index)
        centre_u, radius_u = _bilinear(ux, uy)
        rux, ruy = ux.rad()._mpi_, uy.rad()._mpi_
        cross = _mp.mpi_add(
            _mp.mpi_mul((size_a, size_a), ruy, _PREC),
            _mp.mpi_mul(rux, (size_b, size_b), _PREC),
            _PREC,
        )
        radius = _mp.mpi_add(cross, radius_u._mpi_, _PREC)[1]
        centre = _mp.mpi_add(centre, centre_u._mpi_, _PREC)
        return carried, iv.make_mpf(centre), iv.make_mpf((radius, radius))

    @classmethod
    def point(cls, iv, value, k):
        form = _Form.point(iv, value, k)
        return cls(form.c, form.a, form.e)

    @classmethod
    def nil(cls, iv, k):
        form = _Form.nil(iv, k)
        return cls(form.c, form.a, form.e, True)


def _unpaired(x, index):
    """``x`` less its paired symbols' part: the paired coefficients set to exact zeros."""
    a = x.a.copy()
    for i in index:
        a[i] = _iv().mpf(0)
    return _Form(x.c, a, x.e)


def _paired_kind(k, index):
    """The :class:`_PairedForm` class over ``k`` first-order symbols pairing ``index``."""
    index = tuple(int(i) for i in index)
    if index == tuple(range(k)):
        return _PairedForm
    attrs = {"__slots__": (), "pairing": (k, index)}
    return type(f"_PairedForm{k}of{len(index)}", (_PairedForm,), attrs)


def _first_order(total):
    """``k`` with ``k + k (k + 1) / 2 == total`` (:func:`rmijax._affine.pair_count`)."""
    k = int((np.sqrt(8 * total + 9) - 3) / 2 + 0.5)
    if k + k * (k + 1) // 2 != total:
        raise ValueError(f"{total} symbols is not k + k (k + 1) / 2 for any k")
    return k


class _MpAffineBackend:
    """The operations :class:`rmijax._intervals.Jet` needs, on ``form`` (:class:`_Form`
    or :class:`_PairedForm`) over ``k`` symbols."""

    def __init__(self, iv, k, form=_Form):
        self.iv, self.k, self.form = iv, k, form

    def sin(self, x):
        return _trig(x, self.iv.sin, self.iv.cos)

    def cos(self, x):
        return _trig(x, self.iv.cos, lambda t: -self.iv.sin(t))

    def tanh(self, x):  # |tanh''| <= 4 / (3 sqrt 3) < 1
        return _trig(x, lambda t: _tanh(self.iv, t), lambda t: 1 - _tanh(self.iv, t) ** 2)

    def recip(self, x):
        return _recip(x)

    def sqr(self, x):
        return _sqr(x)

    def is_interval(self, x):
        return isinstance(x, _Form)

    def zeros(self, shape, like=None):
        out = np.empty(shape, dtype=object)
        for index in np.ndindex(shape):
            out[index] = self.form.nil(self.iv, self.k)
        return out

    def outer(self, a, b):
        return np.multiply.outer(a, b)

    def point(self, value):
        return self.form.point(self.iv, value, self.k)


def _arr(iv, values):
    """An object array of point intervals from a float array."""
    values = np.asarray(values, np.float64)
    out = np.empty(values.shape, dtype=object)
    for index in np.ndindex(values.shape):
        out[index] = iv.mpf(float(values[index]))
    return out


def _mag(x):
    return abs(x).b


def _evaluate(backend, state, grad_d, sens2, th, noise, consts, p, n, noisy):
    """``gv`` jets (lists) in the variables (d, R[, eta]).

    ``state`` (n, 2), ``grad_d`` (n, 2, p), ``th`` (p,), ``noise`` (n, 2) or None: object
    arrays of the backend's values (``mpmath`` intervals, or :class:`_Form`);
    ``sens2`` (n, 2, p, p) intervals, the state's second derivative in ``d``. ``d`` and
    ``th`` hold the uncertain parameters only (``p`` of them); with ``consts["free"]``
    (their indices) the others enter as the constants ``consts["fixed"]``.
    """
    m = p + 2 * n + (2 * n if noisy else 0)

    def unit(index):
        grad = backend.zeros((m,))
        grad[index] = backend.point(1.0)
        return grad

    q, qd = [], []
    for i in range(n):
        for s, target in ((0, q), (1, qd)):
            grad = unit(p + 2 * i + s)
            grad[:p] = grad_d[i, s]
            hess = backend.zeros((m, m))
            for b in range(p):
                for c in range(p):
                    hess[b, c] = backend.point(sens2[i, s][b, c])
            target.append(Jet(state[i, s], grad, hess, backend))
    th_jets = [Jet(th[b], unit(b), backend.zeros((m, m)), backend) for b in range(p)]
    if consts.get("free") is not None:  # the certain parameters enter as constants
        free, fixed = consts["free"], consts["fixed"]
        given = dict(zip(free, th_jets, strict=True))
        th_jets = [
            given[b]
            if b in given
            else Jet(backend.point(fixed[b]), backend.zeros((m,)), backend.zeros((m, m)), backend)
            for b in range(len(fixed))
        ]
    noise_jets = None
    if noisy:
        eq, eqd = [], []
        for i in range(n):
            for s, target in ((0, eq), (1, eqd)):
                col = p + 2 * n + 2 * i + s
                target.append(Jet(noise[i, s], unit(col), backend.zeros((m, m)), backend))
        noise_jets = (eq, eqd)
    extra = {}
    zero_g, zero_h = backend.zeros((m,)), backend.zeros((m, m))
    if consts.get("precond") is not None:  # constant jets of the backend
        extra["precond"] = [
            [Jet(backend.point(v), zero_g, zero_h, backend) for v in row]
            for row in consts["precond"]
        ]
    if consts.get("sign") is not None:  # intervals: constant jets that hold each sign
        extra["sign"] = [Jet(backend.point(v), zero_g, zero_h, backend) for v in consts["sign"]]
    if consts.get("keep") is not None:
        extra["keep"] = [Jet(backend.point(v), zero_g, zero_h, backend) for v in consts["keep"]]
    return consts["jets"](
        q,
        qd,
        th_jets,
        consts["nominal"],
        consts["u"],
        consts["kp"],
        consts["kd"],
        noise_jets,
        **extra,
    )


def _preconditioner(setup, state, center):
    """The solve's preconditioner at a centre state, ``A(q_c; th_c)^-1`` in float64 as
    the certifier takes it (any matrix is sound there: it only keeps the pivots of the
    solve near 1), as ``n x n`` floats; None for the articulated solve."""
    if setup["matrix_fn"] is None:
        return None
    th = np.asarray(setup["fixed"], np.float64)
    th[setup["free"]] = center
    matrix = np.asarray(setup["matrix_fn"](jnp.asarray(state[:, 0]), jnp.asarray(th)))
    inverse = np.linalg.inv(matrix)
    return [[float(v) for v in row] for row in inverse]


def _poly_range(iv, sens, sens2, d_box):
    """Enclosure of ``s' d + 1/2 d' Q d`` over the box (object arrays (p,), (p, p))."""
    p = len(d_box)
    total = iv.mpf(0)
    for b in range(p):
        s, c = sens[b], sens2[b][b] / 2
        lo, hi = iv.mpf(d_box[b].a), iv.mpf(d_box[b].b)
        values = [s * lo + c * lo**2, s * hi + c * hi**2]
        if not (c.a == 0 and c.b == 0):
            vertex = -s / (2 * c)
            if vertex.b >= d_box[b].a and vertex.a <= d_box[b].b:
                values.append(-(s**2) / (4 * c))
        low = min(v.a for v in values)
        high = max(v.b for v in values)
        total = total + iv.mpf([low, high])
    for a in range(p):
        for b in range(a + 1, p):
            total = total + (sens2[a][b] + sens2[b][a]) / 2 * (d_box[a] * d_box[b])
    return total


def _tiling_error(cert, params):
    """ "" when the pieces tile the box, else why not.

    Any set of boxes (a product grid or an adaptive bisection): every piece inside the
    box, no two pieces' interiors meeting, and their volumes (exact rationals of the
    floats, over the uncertain parameters) summing to the box's. Then their union is
    the box: it is closed, and a point of the box outside it would leave an open part
    of the box uncovered, so the volumes would fall short.
    """
    lo, hi = np.asarray(params.lo, np.float64), np.asarray(params.hi, np.float64)
    plo, phi = np.asarray(cert.lo, np.float64), np.asarray(cert.hi, np.float64)
    centers = np.asarray(cert.center, np.float64)
    if plo.ndim != 2 or plo.shape != phi.shape or plo.shape[1] != lo.size:
        return f"the pieces' bounds have shapes {plo.shape} and {phi.shape}, not (P, {lo.size})"
    outside = np.flatnonzero(np.any((plo < lo) | (phi > hi) | (plo > phi), axis=1))
    if outside.size:
        return f"piece {int(outside[0])} is not a box inside the parameter box"
    free = np.flatnonzero(hi > lo)
    # interiors meet where every uncertain range overlaps with positive length
    meet = np.ones((plo.shape[0],) * 2, dtype=bool)
    for b in free:
        meet &= np.maximum(plo[:, None, b], plo[None, :, b]) < np.minimum(
            phi[:, None, b], phi[None, :, b]
        )
    np.fill_diagonal(meet, False)
    if np.any(meet):
        i, j = (int(k) for k in np.argwhere(meet)[0])
        return f"pieces {i} and {j} overlap"

    def volume(low, high):
        total = Fraction(1)
        for b in free:
            total *= Fraction(float(high[b])) - Fraction(float(low[b]))
        return total

    covered = sum((volume(plo[i], phi[i]) for i in range(plo.shape[0])), Fraction(0))
    whole = volume(lo, hi)
    if covered != whole:
        return (
            f"no tiling: the pieces cover {float(covered):.17g} of the box's volume "
            f"{float(whole):.17g}"
        )
    if np.any((centers < plo) | (centers > phi)):
        return "a piece's centre lies outside the piece"
    return ""


def check_certificate(cert, traj, params, *, steps: int | None = None, pieces=None) -> CheckResult:
    """Re-verify a certificate with outward-rounded ``mpmath`` interval arithmetic.

    Every pair of ``enclosure`` (``"interval"``, ``"affine"``, ``"paired"``) and
    ``propagate`` (``"kernel"``, ``"carried"``) is verified: the Hessian over the tube by
    the same kind of enclosure (interval jets, or affine or paired jets on ``mpmath``),
    the remainder by the kernel's sums or by generators that the checker carries itself.

    Args:
        cert: the :class:`~rmijax.methods.certified.Certificate` of
            :func:`rmijax.methods.certified.certified_bounds` for ``traj`` and ``params``.
        traj, params: the run and the robot it certifies.
        steps: verify the band at steps ``0..steps`` (default: the whole run; a
            few dozen steps take a minute for two joints with interval jets; affine
            jets are slower, a few seconds a step for one joint).
        pieces: indices of the pieces to verify (default: all).

    Returns:
        :class:`CheckResult`; ``ok`` is False with the first failed check in ``reason``.

    Raises:
        ValueError: a certificate whose ``enclosure``, ``propagate`` or ``solve`` is
            not one of the above.
    """
    if cert.enclosure not in ENCLOSURES or cert.propagate not in ("kernel", "carried"):
        raise ValueError(
            f"check_certificate: cert.enclosure must be one of {ENCLOSURES} and "
            f"cert.propagate 'kernel' or 'carried', got {cert.enclosure!r} and "
            f"{cert.propagate!r}: pass the Certificate that certified_bounds returned"
        )
    if cert.solve not in ("articulated", "preconditioned"):
        raise ValueError(
            "check_certificate: cert.solve must be 'articulated' or 'preconditioned', got "
            f"{cert.solve!r}: pass the Certificate that certified_bounds returned"
        )
    layout = _layout(params)
    ranged = cert.coulomb in ("range", "auto")
    if (
        cert.coulomb not in COULOMB_MODES
        or (ranged and (layout is None or "coulomb" not in layout.friction))
        or ((cert.coulomb == "auto") != (cert.keep is not None))
    ):
        raise ValueError(
            "check_certificate: cert.coulomb must be 'taylor', or 'range' or 'auto' (with "
            f"cert.keep) for a chain with Coulomb parameters, got {cert.coulomb!r}: pass "
            "the Certificate that certified_bounds returned for these params"
        )
    # the choice of sign per joint and step is the certificate's (either is sound), but
    # only 0 (enclose the sign's range) and 1 (keep the Taylor sign) mean anything
    if cert.keep is not None:
        keep_all = np.asarray(cert.keep, np.float64)
        bad = np.argwhere((keep_all != 0) & (keep_all != 1))
        if bad.size:
            return CheckResult(False, 0, f"cert.keep{[int(i) for i in bad[0]]} is not 0 or 1")
    iv = _iv()
    backend = _MpBackend(iv)
    n = traj.n_joints
    # the certain parameters (lo == hi) are constants, not variables: p counts the others
    box_lo, box_hi = np.asarray(params.lo, np.float64), np.asarray(params.hi, np.float64)
    free = [b for b in range(params.n_params) if box_lo[b] < box_hi[b]]
    p = len(free)
    total = int(np.asarray(cert.state).shape[1]) - 1
    steps = total if steps is None else min(int(steps), total)
    reason = _tiling_error(cert, params)
    if reason:
        return CheckResult(False, 0, reason)
    dt = float(traj.dt)
    kp = [float(v) for v in np.asarray(traj.kp)]
    kd = [float(v) for v in np.asarray(traj.kd)]
    u_all = np.asarray(traj.u_d, np.float64)
    x0 = np.asarray(traj.x_n, np.float64)[0]
    nominal = [iv.mpf(float(v)) for v in np.asarray(params.nominal)]
    noise_lo = np.asarray(cert.noise_lo, np.float64)
    noise_hi = np.asarray(cert.noise_hi, np.float64)
    noisy = bool(np.any(noise_lo != 0) or np.any(noise_hi != 0))
    setup = dict(
        dt=dt,
        kp=kp,
        kd=kd,
        nominal=nominal,
        noise_lo=noise_lo,
        noise_hi=noise_hi,
        noisy=noisy,
        segments=int(cert.segments),
        enclosure=cert.enclosure,
        paired=paired_variables(cert.enclosure, layout, n, p, free, noisy),
        carried=cert.propagate == "carried",
        n=n,
        p=p,
        jets=perturbation_jets(layout),
        ranged=ranged,
        matrix_fn=solve_matrix(params) if cert.solve == "preconditioned" else None,
        free=free,
        fixed=[float(v) for v in box_lo],
    )
    lower, upper = np.asarray(cert.lower, np.float64), np.asarray(cert.upper, np.float64)
    powers = None if setup["carried"] else _powers(iv, kp, kd, dt, n, steps)
    chosen = range(cert.n_pieces) if pieces is None else pieces
    for piece in chosen:
        data = {
            key: np.asarray(getattr(cert, key)[piece], np.float64)
            for key in ("state", "sens", "sens2", "injected", "remainder", "center")
        }
        data["keep"] = None if cert.keep is None else np.asarray(cert.keep[piece], np.float64)
        injected, remainder, center = data["injected"], data["remainder"], data["center"]
        # below, d and its coefficients: the uncertain parameters only (the tiling check
        # above holds every piece's centre in it, so a certain one's is its value, d = 0)
        center = center[free]
        sens2 = data["sens2"][..., free, :][..., free]
        data |= dict(center=center, sens=data["sens"][..., free], sens2=sens2)
        state, sens = data["state"], data["sens"]
        piece_lo, piece_hi = np.asarray(cert.lo[piece]), np.asarray(cert.hi[piece])
        th_box = np.array(
            [iv.mpf([float(piece_lo[b]), float(piece_hi[b])]) for b in free], dtype=object
        )
        d_box = th_box - _arr(iv, center)
        d_rad = [_mag(d) for d in d_box]
        data |= dict(d_box=d_box, d_rad=d_rad)
        if not (np.array_equal(state[0], x0) and not sens[0].any() and not sens2[0].any()):
            return CheckResult(False, 0, f"piece {piece}: the model does not start at x_d(0)")
        if np.any(remainder < 0) or np.any(injected < 0):
            return CheckResult(False, 0, f"piece {piece}: a negative remainder bound")
        if remainder[0].any():
            return CheckResult(False, 0, f"piece {piece}: the remainder does not start at 0")
        # carried: R_k = G eps + sum_b d_b G^b eps, the checker's own generators
        gens = np.empty((2 * n, 0), dtype=object)
        gens_d = np.empty((p, 2 * n, 0), dtype=object)
        for k in range(steps + 1):
            # 5. the band at step k
            for i in range(n):
                for s in range(2):
                    enclosure = (
                        iv.mpf(float(state[k, i, s]))
                        + _poly_range(iv, _arr(iv, sens[k, i, s]), _arr(iv, sens2[k, i, s]), d_box)
                        + iv.mpf([-float(remainder[k, i, s]), float(remainder[k, i, s])])
                        + iv.mpf([float(noise_lo[i, s]), float(noise_hi[i, s])])
                    )
                    if not (enclosure.a >= lower[k, i, s] and enclosure.b <= upper[k, i, s]):
                        return CheckResult(
                            False,
                            k,
                            f"piece {piece}, step {k}, joint {i} sensor {s}: the band "
                            f"[{lower[k, i, s]!r}, {upper[k, i, s]!r}] does not hold the "
                            f"enclosure {enclosure}",
                        )
            if k == steps:
                break
            # 3. the inputs w_k
            try:
                reason, centre = _check_step(iv, backend, k, data, u_all[k], gens_d, setup)
            except _Unbounded as error:
                reason = f"the affine Hessian is unbounded over the tube ({error})"
            if reason:
                return CheckResult(False, k, f"piece {piece}, step {k}: {reason}")
            # 4. the remainder bound of step k+1
            if setup["carried"]:
                gens, gens_d, bound = _carry(
                    iv, centre, gens, gens_d, injected[k], remainder[k], d_rad, setup
                )
            else:
                bound = _kernel_bound(iv, powers, injected, k, n)
            for i in range(n):
                for s in range(2):
                    if not bound[i][s].b <= remainder[k + 1, i, s]:
                        return CheckResult(
                            False,
                            k,
                            f"piece {piece}, step {k + 1}, joint {i} sensor {s}: remainder "
                            f"bound {remainder[k + 1, i, s]!r} below the recomputed "
                            f"{bound[i][s]}",
                        )
    return CheckResult(True, steps, "")


def _sign_range(iv, state, sens, sens2, d_box, remainder, keep=None):
    """Per joint an ``mpmath`` interval holding ``tanh(qd_j / v_s)`` over the tube of one
    step (``x_c + range(S d + 1/2 Q[d, d]) + [-r, r]``), as the jets write it
    (``qd * (1 / v_s)``, the float ``1 / v_s``); 0 where ``keep`` is 1 (the sign keeps its
    expansion there)."""
    out = []
    for i in range(state.shape[0]):
        if keep is not None and keep[i] == 1:
            out.append(iv.mpf(0))
            continue
        qd = (
            iv.mpf(float(state[i, 1]))
            + _poly_range(iv, _arr(iv, sens[i, 1]), _arr(iv, sens2[i, 1]), d_box)
            + iv.mpf([-float(remainder[i, 1]), float(remainder[i, 1])])
        )
        out.append(_tanh(iv, qd * iv.mpf(1.0 / COULOMB_VELOCITY)))
    return out


def _powers(iv, kp, kd, dt, n, steps):
    """Powers ``A_i^m``, ``m = 0..steps``, of every joint's PD loop (interval matrices)."""
    powers = []
    for i in range(n):
        a_mat = np.array(
            [[iv.mpf(1), iv.mpf(dt)], [-iv.mpf(kp[i]) * dt, 1 - iv.mpf(kd[i]) * dt]], dtype=object
        )
        joint = [np.array([[iv.mpf(1), iv.mpf(0)], [iv.mpf(0), iv.mpf(1)]], dtype=object)]
        for _ in range(steps):
            joint.append(a_mat.dot(joint[-1]))
        powers.append(joint)
    return powers


def _kernel_bound(iv, powers, injected, k, n):
    """``sum_{j <= k} |A^(k-j)| w_j`` per joint and sensor (no truncation)."""
    out = []
    for i in range(n):
        row = []
        for s in range(2):
            bound = iv.mpf(0)
            for j in range(k + 1):
                power = powers[i][k - j]
                bound = bound + _mag(power[s, 0]) * float(injected[j, i, 0])
                bound = bound + _mag(power[s, 1]) * float(injected[j, i, 1])
            row.append(bound)
        out.append(row)
    return out


def _float_mid(x):
    """A float inside the interval ``x`` (taken as an exact real)."""
    return float(x.mid)


def _loop_matrix(iv, centre, setup):
    """The centre's linearised loop in ``R``: ``A_c`` (floats, taken as exact reals) and
    ``|A_true - A_c|`` over the enclosure of ``gv_R``, both (2n, 2n) object arrays."""
    n, p, dt = setup["n"], setup["p"], setup["dt"]
    size = 2 * n
    a_c = np.full((size, size), iv.mpf(0), dtype=object)
    a_err = np.full((size, size), iv.mpf(0), dtype=object)
    for i in range(n):
        a_c[2 * i, 2 * i] = iv.mpf(1)
        a_c[2 * i, 2 * i + 1] = iv.mpf(dt)  # q + dt qd: exact reals
        for t in range(size):
            true = centre[i].g[p + t] * dt
            if t == 2 * i:
                true = true - iv.mpf(setup["kp"][i]) * dt
            elif t == 2 * i + 1:
                true = true + (1 - iv.mpf(setup["kd"][i]) * dt)
            mid = iv.mpf(_float_mid(true))
            a_c[2 * i + 1, t] = mid
            a_err[2 * i + 1, t] = abs(true - mid).b
    return a_c, a_err


def _mixed(iv, centre, setup):
    """``H_b`` rows: the float midpoints of the centre's ``d``-``R`` Hessian block,
    ``mixed[i][b][t]``."""
    n, p = setup["n"], setup["p"]
    return [
        [[iv.mpf(_float_mid(centre[i].h[b, p + t])) for t in range(2 * n)] for b in range(p)]
        for i in range(n)
    ]


def _carry(iv, centre, gens, gens_d, injected, remainder, d_rad, setup):
    """One step of the checker's own generators: ``G <- A_c G``, ``G^b <- A_c G^b + dt
    e2 H_b G`` (in interval arithmetic, then rebased on floats), and ``2n`` new ones:
    ``w_k`` (the verified claim), ``|A_true - A_c| r_k`` and the rebased radii. Returns
    the new generators and ``|R_(k+1)|``'s bound per joint and sensor."""
    n, p, dt = setup["n"], setup["p"], setup["dt"]
    size = 2 * n
    a_c, a_err = _loop_matrix(iv, centre, setup)
    mixed = _mixed(iv, centre, setup)
    columns = gens.shape[1]
    new = np.empty((size, columns + size), dtype=object)
    new_d = np.empty((p, size, columns + size), dtype=object)
    if columns:
        new[:, :columns] = a_c.dot(gens)
        for b in range(p):
            new_d[b, :, :columns] = a_c.dot(gens_d[b])
            for i in range(n):
                pushed = sum(
                    (gens[t] * mixed[i][b][t] for t in range(size)),
                    start=np.full(columns, iv.mpf(0), dtype=object),
                )
                new_d[b, 2 * i + 1, :columns] = new_d[b, 2 * i + 1, :columns] + pushed * dt
    # rebase: the carried generators become floats (exact reals), their intervals'
    # radii go into the new generators, so interval widths do not compound over steps
    slack = [iv.mpf(0)] * size
    for r in range(size):
        for j in range(columns):
            mid = iv.mpf(_float_mid(new[r, j]))
            slack[r] = slack[r] + abs(new[r, j] - mid).b
            new[r, j] = mid
            for b in range(p):
                mid = iv.mpf(_float_mid(new_d[b, r, j]))
                slack[r] = slack[r] + abs(new_d[b, r, j] - mid).b * d_rad[b]
                new_d[b, r, j] = mid
    r_flat = [float(v) for v in remainder.reshape(-1)]
    w_flat = [float(v) for v in injected.reshape(-1)]
    new[:, columns:] = iv.mpf(0)
    new_d[:, :, columns:] = iv.mpf(0)
    for r in range(size):
        box = iv.mpf(w_flat[r]) + slack[r]
        for t in range(size):
            box = box + a_err[r, t] * r_flat[t]
        new[r, columns + r] = box
    bound = []
    for i in range(n):
        row = []
        for s in range(2):
            r = 2 * i + s
            total = iv.mpf(0)
            for value in new[r]:
                total = total + abs(value)
            for b in range(p):
                part = iv.mpf(0)
                for value in new_d[b, r]:
                    part = part + abs(value)
                total = total + part * d_rad[b]
            row.append(total)
        bound.append(row)
    return new, new_d, bound


def _affine_hessians(iv, xc, s1, s2, center, d_rad, rhat, eta_hat, s_hi, consts, setup):
    """``gv``'s Hessians in ``z = (d, R[, eta])`` over the box ``s_hi Z``, enclosed by
    affine jets on ``mpmath`` (one symbol per variable): per joint an (m, m) object array
    of intervals. The state is ``x_c + S d + R`` exact in the symbols (``1/2 Q[d, d]`` in
    the error term), its ``d``-gradient ``S + Q d``."""
    n, p, noisy = setup["n"], setup["p"], setup["noisy"]
    m = p + 2 * n + (2 * n if noisy else 0)
    index = setup["paired"]  # None: affine forms
    paired = index is not None
    total = m + len(index) * (len(index) + 1) // 2 if paired else m
    kind = _paired_kind(m, index) if paired else _Form
    backend = _MpAffineBackend(iv, total, kind)
    radii = list(d_rad) + list(rhat) + (list(eta_hat) if noisy else [])
    rho = [(iv.mpf(r) * s_hi).b for r in radii]  # each symbol's exact radius, rounded up
    pair_index = {}
    if paired:
        rows, cols = np.triu_indices(len(index))
        pairs = enumerate(zip(rows, cols, strict=True))
        pair_index = {(index[i], index[j]): m + t for t, (i, j) in pairs}

    def form(c, coefficients, e=None):
        a = np.full(total, iv.mpf(0), dtype=object)
        for index, value in coefficients.items():
            a[index] = value
        c = c if isinstance(c, iv.mpf) else iv.mpf(float(c))
        return kind(c, a, iv.mpf(0) if e is None else e)

    state = np.empty((n, 2), dtype=object)
    grad_d = np.empty((n, 2, p), dtype=object)
    for i in range(n):
        for s in range(2):
            col = p + 2 * i + s
            coefficients = {b: s1[i, s][b] * rho[b] for b in range(p)}
            coefficients[col] = rho[col]
            q = s2[i, s]
            if paired:  # 1/2 Q[d, d] in the pair symbols of d (d_b = rho_b eps_b) where
                # both are paired, in the error term elsewhere
                centre = xc[i, s] if isinstance(xc[i, s], iv.mpf) else iv.mpf(float(xc[i, s]))
                quad = iv.mpf(0)
                for b in range(p):
                    for c in range(b, p):
                        weight = rho[b] * rho[c]
                        if (b, c) not in pair_index:
                            both = abs(q[b, c]) + (abs(q[c, b]) if b != c else 0)
                            quad = quad + both * weight
                        elif b == c:
                            coefficients[pair_index[b, b]] = q[b, b] * weight / 4
                            centre = centre + q[b, b] * weight / 4
                        else:
                            coefficients[pair_index[b, c]] = (q[b, c] + q[c, b]) * weight / 2
                state[i, s] = form(centre, coefficients, (quad / 2).b)
            else:
                quad = iv.mpf(0)
                for b in range(p):
                    for c in range(p):
                        quad = quad + abs(q[b, c]) * (rho[b] * rho[c])
                state[i, s] = form(xc[i, s], coefficients, (quad / 2).b)
            for b in range(p):
                grad_d[i, s, b] = form(s1[i, s][b], {c: s2[i, s][b, c] * rho[c] for c in range(p)})
    th = np.array([form(center[b], {b: rho[b]}) for b in range(p)], dtype=object)
    noise = None
    if noisy:
        noise = np.empty((n, 2), dtype=object)
        for i in range(n):
            for s in range(2):
                col = p + 2 * n + 2 * i + s
                noise[i, s] = form(iv.mpf(0), {col: rho[col]})
    gv = _evaluate(backend, state, grad_d, s2, th, noise, consts, p, n, noisy)
    out = []
    for jet in gv:
        h = np.empty((m, m), dtype=object)
        for a in range(m):
            for b in range(m):
                lo, hi = jet.h[a, b].interval()
                h[a, b] = iv.mpf([lo.a, hi.b])
        out.append(h)
    return out


def _check_step(iv, backend, k, data, u, gens_d, setup):
    """Verify ``w_k`` (``injected[k]``) of one piece (``data``: its certificate arrays,
    ``d_box`` and ``d_rad``); returns ``(reason, centre jets)``."""
    state, sens, sens2 = data["state"], data["sens"], data["sens2"]
    injected, remainder, center = data["injected"], data["remainder"], data["center"]
    d_box, d_rad = data["d_box"], data["d_rad"]
    n, p, dt = setup["n"], setup["p"], setup["dt"]
    kp, kd, noisy, carried = setup["kp"], setup["kd"], setup["noisy"], setup["carried"]
    noise_lo, noise_hi = setup["noise_lo"], setup["noise_hi"]
    segments = setup["segments"]
    consts = dict(
        jets=setup["jets"],
        free=setup["free"],
        fixed=setup["fixed"],
        nominal=setup["nominal"],
        u=[iv.mpf(float(v)) for v in u],
        kp=[iv.mpf(v) for v in kp],
        kd=[iv.mpf(v) for v in kd],
        precond=_preconditioner(setup, state[k], center),
    )
    if setup["ranged"]:  # the Coulomb signs' enclosures over the tube of step k
        keep = None if data["keep"] is None else data["keep"][k]
        consts["sign"] = _sign_range(iv, state[k], sens[k], sens2[k], d_box, remainder[k], keep)
        if keep is not None:  # the certificate's choice (0 or 1, checked above): any is sound
            consts["keep"] = [iv.mpf(float(v)) for v in keep]
    zero = iv.mpf(0)
    xc, s1, s2 = _arr(iv, state[k]), _arr(iv, sens[k]), _arr(iv, sens2[k])
    noise0 = np.full((n, 2), zero, dtype=object) if noisy else None
    centre = _evaluate(backend, xc, s1, s2, _arr(iv, center), noise0, consts, p, n, noisy)
    m = p + 2 * n + (2 * n if noisy else 0)
    rhat = [float(v) for v in remainder[k].reshape(-1)]
    eta_hat = [
        max(abs(a), abs(b)) for a, b in zip(noise_lo.reshape(-1), noise_hi.reshape(-1), strict=True)
    ]
    v_hat = list(d_rad) + rhat + (eta_hat if noisy else [])
    # the Lagrange remainder: Hessians over the nested boxes (j / J) Z, their spread
    # about the centre's (the d-d block only with the kernel, every block when carried)
    spread = [np.full((m, m), zero, dtype=object) for _ in range(n)]
    noise_box = np.array(
        [
            [
                iv.mpf([min(float(noise_lo[i, s]), 0.0), max(float(noise_hi[i, s]), 0.0)])
                for s in range(2)
            ]
            for i in range(n)
        ],
        dtype=object,
    )
    for j in range(segments):
        s_hi = iv.mpf(j + 1) / segments
        s_lo = iv.mpf(j) / segments
        weight = (s_hi - s_lo) - (s_hi**2 - s_lo**2) / 2
        if setup["enclosure"] != "interval":  # affine or paired forms
            hessians = _affine_hessians(
                iv, xc, s1, s2, center, d_rad, rhat, eta_hat, s_hi, consts, setup
            )
        else:
            sd = d_box * s_hi
            tube = np.empty((n, 2), dtype=object)
            grad_d = np.empty((n, 2, p), dtype=object)
            for i in range(n):
                for s in range(2):
                    tube[i, s] = (
                        xc[i, s]
                        + _poly_range(iv, s1[i, s], s2[i, s], sd)
                        + iv.mpf([-rhat[2 * i + s], rhat[2 * i + s]]) * s_hi
                    )
                    grad_d[i, s] = s1[i, s] + s2[i, s].dot(sd)
            th = _arr(iv, center) + sd
            box = _evaluate(
                backend,
                tube,
                grad_d,
                s2,
                th,
                noise_box * s_hi if noisy else None,
                consts,
                p,
                n,
                noisy,
            )
            hessians = [jet.h for jet in box]
        for i in range(n):
            diff = hessians[i].copy()
            if carried:
                diff = diff - centre[i].h
            else:
                diff[:p, :p] = diff[:p, :p] - centre[i].h[:p, :p]
            for a in range(m):
                for b in range(m):
                    spread[i][a, b] = spread[i][a, b] + iv.mpf(_mag(diff[a, b])) * weight
    mixed = _mixed(iv, centre, setup) if carried else None
    for i in range(n):
        w = iv.mpf(0)
        for a in range(p + 2 * n if carried else p, m):  # carried: R's linear part is in A_c
            w = w + iv.mpf(_mag(centre[i].g[a])) * v_hat[a]
        for a in range(m):
            for b in range(m):
                w = w + spread[i][a, b] * (iv.mpf(v_hat[a]) * v_hat[b])
        if carried:
            # 1/2 z' mid(H(0)) z over the blocks that are not carried (R-R, the noise's)
            for a in range(m):
                for b in range(m):
                    if a < p + 2 * n and b < p + 2 * n and (a < p or b < p):
                        continue
                    mid = iv.mpf(_float_mid(centre[i].h[a, b]))
                    w = w + abs(mid) * (iv.mpf(v_hat[a]) * v_hat[b]) / 2
            # sum_(b, c) d_b d_c H_b R^c, with R^c = G^c eps the checker's generators
            for b in range(p):
                for c in range(p):
                    through = iv.mpf(0)
                    for col in range(gens_d.shape[-1]):
                        entry = iv.mpf(0)
                        for t in range(2 * n):
                            entry = entry + mixed[i][b][t] * gens_d[c, t, col]
                        through = through + abs(entry)
                    w = w + through * (iv.mpf(d_rad[b]) * d_rad[c])
        # the next model against the exact coefficients c0, c1, c2
        q, qd = xc[i, 0], xc[i, 1]
        c0 = (q + qd * dt, qd + ((consts["u"][i] - qd * kd[i] - q * kp[i]) + centre[i].v) * dt)
        c1q = s1[i, 0] + s1[i, 1] * dt
        c1d = s1[i, 1] + (s1[i, 1] * (-kd[i]) + s1[i, 0] * (-kp[i]) + centre[i].g[:p]) * dt
        c2q = s2[i, 0] + s2[i, 1] * dt
        c2d = s2[i, 1] + (s2[i, 1] * (-kd[i]) + s2[i, 0] * (-kp[i]) + centre[i].h[:p, :p]) * dt
        for s, (a0, a1, a2) in enumerate(((c0[0], c1q, c2q), (c0[1], c1d, c2d))):
            err = iv.mpf(_mag(a0 - float(state[k + 1, i, s])))
            for b in range(p):
                err = err + iv.mpf(_mag(a1[b] - float(sens[k + 1, i, s, b]))) * d_rad[b]
                for c in range(p):
                    err = err + iv.mpf(_mag(a2[b, c] - float(sens2[k + 1, i, s, b, c]))) * (
                        iv.mpf(d_rad[b]) * d_rad[c] / 2
                    )
            need = err + (w * dt if s == 1 else 0)
            if not need.b <= injected[k, i, s]:
                return (
                    f"joint {i} sensor {s}: the remainder input {injected[k, i, s]!r} is below "
                    f"the recomputed bound {need}",
                    centre,
                )
    return "", centre
