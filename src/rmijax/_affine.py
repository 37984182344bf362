"""Affine arithmetic in JAX with rounding bounded, and its second-order jets on a tape.

An :class:`AffineForm` stands for the set of reals

    x = c + sum_i a_i eps_i + e eps',    eps_i in [-1, 1] shared by every form, eps' its own,

with ``c``, ``a_i`` and ``e >= 0`` floats taken as exact reals. Unlike an
interval, two forms built from the same symbols ``eps_i`` remember how they move
together (``x - x`` is exactly 0, a mass that enters the articulated solve many
times is the same mass each time), which is what makes enclosures of the closed
loop's Hessian over a box tight enough at 4 links (``benchmarks/certified_enclosure.py
--tube`` measured 3-8x the sampled spread, against 50-250x for intervals).

Soundness: every operation returns a form that contains the exact real result of
the operation on every pair of reals in its operands (for the same ``eps_i``). The
float computation of ``c`` and ``a_i`` is rounded to nearest; each result's error
is at most an ulp of it, and the operation adds ``2^-50`` (4 ulps) of the
magnitudes it computed to ``e``; sums of non-negative bounds are scaled up by
``(1 + (k + 8) 2^-52)`` for ``k`` terms. ``sin``/``cos`` add ``2^-44`` absolute
for XLA's float64 ``sin``/``cos`` (as :mod:`rmijax._intervals` does; ``tanh``
``2^-42``), ``1/x`` uses
the min-range linearisation with an interval remainder computed with outward
rounding, ``x^2`` the exact square of the linear part. A product's quadratic part is
bounded by the product of radii intersected with a polarisation bound
(:func:`_bilinear`: about half of it where the two forms move along the same symbols,
as the Hessian jets' factors do; the UR5e's certified tachometer band 0.90x at the median
in 4 pieces, ``docs/methods.md``); no Chebyshev refinement. :class:`PairedForm` adds a
symbol per pair of symbols and carries the product of two forms' first-order parts there
instead (``certified_bounds(..., enclosure="paired")``).

:func:`run_affine_tape` replays a :class:`rmijax._intervals.Tape` on second-order
jets whose value, gradient and Hessian entries are affine forms: with the leaves'
values given as forms over a box (every symbol in ``[-1, 1]``), the outputs'
Hessian entries enclose the Hessian at every point of the box.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from rmijax._intervals import Jet, PackedHessians, down, jet_branches, replay, up

__all__ = [
    "AffineForm",
    "AffineBackend",
    "PairedForm",
    "pair_count",
    "paired_over",
    "run_affine_tape",
]

_EPS = 2.0**-52
_REL = 2.0**-50
_TINY = 2.0**-1000
_TRIG_ABS = 2.0**-44


def _up(x, terms=1):
    """Above the exact sum of ``terms`` non-negative float products that ``x`` rounds."""
    return x * (1.0 + (terms + 8) * _EPS) + _TINY


def _abs_sum(a):
    """Upper bound of ``sum_i |a_i|`` over the last axis."""
    return _up(jnp.sum(jnp.abs(a), axis=-1), a.shape[-1])


def _lift(x, ndim):
    """``x`` with leading unit axes up to ``ndim`` (explicit broadcasting)."""
    return jnp.reshape(x, (1,) * (ndim - x.ndim) + x.shape)


def _align(x, y):
    """Two forms with the same number of axes (leading unit axes added), of the class of
    ``x`` (the tape's forms are all of one class)."""
    ndim = max(x.c.ndim, y.c.ndim)
    form = type(x)
    return (
        form(_lift(x.c, ndim), _lift(x.a, ndim + 1), _lift(x.e, ndim)),
        form(_lift(y.c, ndim), _lift(y.a, ndim + 1), _lift(y.e, ndim)),
    )


@jax.tree_util.register_pytree_node_class
class AffineForm:
    """``c + a . eps + e [-1, 1]`` elementwise; ``c`` (...), ``a`` (..., K), ``e`` (...) >= 0."""

    __array_priority__ = 1000

    def __init__(self, c, a, e):
        self.c, self.a, self.e = c, a, e

    def tree_flatten(self):
        return (self.c, self.a, self.e), None

    @classmethod
    def tree_unflatten(cls, aux, children):
        return cls(*children)

    @property
    def shape(self):
        return self.c.shape

    @property
    def n_symbols(self):
        return self.a.shape[-1]

    @classmethod
    def point(cls, value, k):
        """The exact float ``value`` (any shape) as a form over ``k`` symbols."""
        value = jnp.asarray(value)
        return cls(
            value, jnp.zeros(value.shape + (k,), value.dtype), jnp.zeros(value.shape, value.dtype)
        )

    def _of(self, other):
        if isinstance(other, AffineForm):
            return other
        return type(self).point(jnp.asarray(other, self.c.dtype), self.n_symbols)

    def rad(self):
        """Upper bound of ``|x - c|``."""
        return _up(_abs_sum(self.a) + self.e, 2)

    def bounds(self):
        """``(lo, hi)`` floats enclosing every value of the form."""
        r = self.rad()
        return down(self.c - r), up(self.c + r)

    def __getitem__(self, index):
        index = index if isinstance(index, tuple) else (index,)
        return type(self)(self.c[index], self.a[index + (slice(None),)], self.e[index])

    def _rounded(self, c, a, e):
        """The form ``(c, a, e)`` with the rounding of ``c`` and ``a`` added to ``e``."""
        slack = (jnp.abs(c) + jnp.sum(jnp.abs(a), axis=-1)) * _REL
        return type(self)(c, a, _up(e + slack, 3))

    def __add__(self, other):
        x, o = _align(self, self._of(other))
        return x._rounded(x.c + o.c, x.a + o.a, x.e + o.e)

    __radd__ = __add__

    def __neg__(self):
        return type(self)(-self.c, -self.a, self.e)

    def __sub__(self, other):
        x, o = _align(self, self._of(other))
        return x._rounded(x.c - o.c, x.a - o.a, x.e + o.e)

    def __rsub__(self, other):
        return self._of(other) - self

    def __mul__(self, other):
        if not isinstance(other, AffineForm):  # an exact float constant
            s = jnp.asarray(other, self.c.dtype)
            if s.ndim == 0:
                return self._rounded(self.c * s, self.a * s, self.e * jnp.abs(s))
            other = type(self).point(s, self.n_symbols)
        x, o = _align(self, other)
        part_x = x.a * o.c[..., None]
        part_y = o.a * x.c[..., None]
        a = part_x + part_y
        products = jnp.sum(jnp.abs(part_x) + jnp.abs(part_y), axis=-1) * _REL
        rad_x, rad_y = x.rad(), o.rad()
        carried, centre, radius = x._quadratic(o, rad_x, rad_y)
        if carried is not None:  # exact products of the symbols, computed with rounding
            a = a + carried
        plain = x.c * o.c
        c = plain + centre
        e = (
            jnp.abs(x.c) * o.e
            + jnp.abs(o.c) * x.e
            + radius
            + (jnp.abs(plain) + jnp.abs(centre) + jnp.abs(c) + jnp.sum(jnp.abs(a), axis=-1)) * _REL
            + products
        )
        return type(x)(c, a, _up(e, 6))

    __rmul__ = __mul__

    def _quadratic(self, o, rad_x, rad_y):
        """``(carried, centre, radius)``: the product's quadratic part ``(L_x + E_x)(L_y +
        E_y)`` lies in ``carried . eps + centre + [-radius, radius]`` (``carried`` a
        coefficient per symbol); here ``carried`` is None (nothing carried,
        :func:`_bilinear`'s bound)."""
        return (None, *_bilinear(self, o, rad_x, rad_y))

    def __truediv__(self, other):
        return self * recip(self._of(other))

    def __rtruediv__(self, other):
        return self._of(other) * recip(self)


def _power_of_two_balance(rad_x, rad_y):
    """``lambda = 2^j`` with ``lambda^2`` within a factor ``2^(+-1.5)`` of ``rad_y / rad_x``
    (1 where either is 0 or not finite; :func:`_bilinear` passes the sums ``sum_i |a_i|``
    of the two forms): scaling by it is exact. ``j = sign(t) floor(|t| +
    1/4)``, ``t = (log2 rad_y - log2 rad_x) / 2``: swapping the factors negates ``t``
    exactly, so ``x * y`` and ``y * x`` are the same floats (the packed Hessians rely on
    it), and the steps of ``floor`` sit away from the ratios the jets make exactly (powers
    of two), where the checker's own radii, ulps off these, could pick another ``j`` (it
    takes both candidates near a step)."""
    ok = (rad_x > 0) & (rad_y > 0) & jnp.isfinite(rad_x) & jnp.isfinite(rad_y)
    t = 0.5 * (jnp.log2(jnp.where(ok, rad_y, 1.0)) - jnp.log2(jnp.where(ok, rad_x, 1.0)))
    j = jnp.sign(t) * jnp.floor(jnp.abs(t) + 0.25)
    j = jnp.clip(j, -400, 400).astype(jnp.int32)
    return jnp.where(ok, jnp.ldexp(jnp.ones_like(rad_x), j), 1.0)


def _bilinear(x, o, rad_x, rad_y):
    """``(centre, radius)``: ``(L_x + E_x)(L_y + E_y)`` (``L = a . eps``, ``|E| <= e``) lies
    in ``centre + [-radius, radius]`` for every ``eps``, rounding included.

    Two bounds, intersected: ``[-rad_x rad_y, rad_x rad_y]``, and the polarisation
    ``uv = ((lambda u + v / lambda)^2 - (lambda u - v / lambda)^2) / 4``, exact for every
    real ``lambda != 0``, with ``0 <= (lambda u +- v / lambda)^2 <= (sum_i |lambda a_i +-
    b_i / lambda| + lambda e_x + e_y / lambda)^2 = Q^2`` or ``P^2``: the product lies in
    ``[-P^2 / 4, Q^2 / 4]``. Where the two forms move along the same symbols one of ``P``,
    ``Q`` is small (``x y`` with ``y = x`` gives ``[0, rad^2]``, as :func:`sqr`), where
    their symbols differ it is the plain bound. ``lambda`` a power of two: the scaled
    coefficients are exact, each sum ``lambda a_i +- b_i / lambda`` rounds once.
    """
    # the scale from the symbols' parts alone: the error terms hold the rounding, which the
    # checker carries in its coefficients' widths instead
    lam = _power_of_two_balance(jnp.sum(jnp.abs(x.a), -1), jnp.sum(jnp.abs(o.a), -1))
    su, sv = x.a * lam[..., None], o.a / lam[..., None]  # exact
    own = x.e * lam + o.e / lam  # exact products, one rounded sum: _up below
    count = x.a.shape[-1] + 1
    q_sum = jnp.sum(jnp.abs(su + sv), axis=-1)
    p_sum = jnp.sum(jnp.abs(su - sv), axis=-1)
    q_raw, p_raw = q_sum + own, p_sum + own
    q = _up(_up(q_sum * (1.0 + _EPS), count) + own, 2)
    p = _up(_up(p_sum * (1.0 + _EPS), count) + own, 2)
    product = rad_x * rad_y
    plain = _up(product)
    hi = jnp.minimum(_up(0.25 * q * q), plain)
    lo = -jnp.minimum(_up(0.25 * p * p), plain)
    # the centre from the floats as computed (any float is sound: the radius is about it),
    # close to the checker's, whose exact ends these are within ulps of
    centre = 0.5 * (jnp.minimum(0.25 * q_raw * q_raw, product))
    centre = centre - 0.5 * jnp.minimum(0.25 * p_raw * p_raw, product)
    centre = jnp.where(jnp.isfinite(centre), centre, 0.0)  # e = inf: keep c finite
    radius = _up(jnp.maximum(hi - centre, centre - lo), 2)
    return centre, radius


def pair_count(k, paired=None):
    """How many symbols a :class:`PairedForm` over ``k`` first-order symbols has: ``k``
    and the ``s (s + 1) / 2`` products ``eps_i eps_j``, ``i <= j``, of the ``s`` paired ones
    (``paired``: their count; default all ``k``)."""
    s = k if paired is None else paired
    return k + s * (s + 1) // 2


def _first_order(total):
    """``k`` with ``pair_count(k) == total``."""
    k = int((np.sqrt(8 * total + 9) - 3) / 2 + 0.5)
    if pair_count(k) != total:
        raise ValueError(f"{total} symbols is not k + k (k + 1) / 2 for any k")
    return k


@functools.cache
def _pairs(k):
    """The rows ``(i, j)``, ``i <= j``, of the pair symbols, in order (``np.triu_indices``)."""
    return np.triu_indices(k)


@jax.tree_util.register_pytree_node_class
class PairedForm(AffineForm):
    """An affine form whose symbols are ``k`` first-order ``eps_i`` and, after them, one
    symbol per pair ``i <= j``: ``eps_i eps_j`` (``i < j``) and ``2 eps_i^2 - 1``
    (``i = j``), each in ``[-1, 1]``; in the order of ``np.triu_indices(k)``.

    Every operation of :class:`AffineForm` is sound on it (the pair symbols are treated as
    independent symbols in ``[-1, 1]``, which the set of their values lies in), and a
    product carries the product of the two first-order parts exactly in the pair symbols:
    ``(a . eps)(b . eps) = sum_(i < j) (a_i b_j + a_j b_i) eps_i eps_j + sum_i a_i b_i (1 +
    (2 eps_i^2 - 1)) / 2``. Only the rest is bounded: with ``x = c_x + L_x + U_x`` (``U``:
    the pair symbols' part and the error), by ``rad_x rad_y - A B`` (``A = sum_i |a_i|``
    over the first-order symbols), which is ``A rad(U_y) + rad(U_x) B + rad(U_x)
    rad(U_y)``; the classes of :func:`paired_over`, whose ``U`` holds the unpaired
    first-order symbols too, bound ``U_x U_y`` by :func:`_bilinear` instead. So products
    of forms that move along different symbols keep how they move together, which
    :func:`_bilinear` loses. ``pair_count(k)`` symbols: 31 first-order symbols (the UR5e's
    box and remainder) make 527.
    """

    #: ``(k, index)``: the first-order symbols' count and the paired ones (sorted), for
    #: the classes of :func:`paired_over`; None: every one of ``k = _first_order(K)``
    pairing = None

    def _quadratic(self, o, rad_x, rad_y):
        if self.pairing is None:
            k = _first_order(self.n_symbols)
            index = slice(0, k)
        else:
            k, index = self.pairing
        a, b = self.a[..., index], o.a[..., index]
        s = a.shape[-1]
        rows, cols = _pairs(s)
        outer = a[..., :, None] * b[..., None, :]
        upper = outer[..., rows, cols] + outer[..., cols, rows]
        carried = jnp.where(rows == cols, 0.25 * upper, upper)  # i = j: a_i b_i / 2 (exact)
        # every symbol's: 0 on the first-order ones
        carried = jnp.concatenate([jnp.zeros(a.shape[:-1] + (k,), a.dtype), carried], axis=-1)
        centre = 0.5 * jnp.sum(jnp.diagonal(outer, axis1=-2, axis2=-1), axis=-1)
        size_a, size_b = _abs_sum(a), _abs_sum(b)
        # the rounding of every a_i b_j and of their pairwise sums (2^-51 A B), of the
        # centre's sum over s terms (s 2^-53 A B)
        rounding = size_a * size_b * ((s + 16) * _EPS)
        if self.pairing is None:
            # every first-order symbol paired: U holds only the pair symbols and the error,
            # second-order small, where polarising U_x U_y moved no band (preset_arm(4),
            # 1 s, 2 splits: the same to 3 decimals) and cost time (987 s against 845 s,
            # same host), so the rest is bounded by rad_x rad_y - A B = A rad(U_y) +
            # rad(U_x) B + rad(U_x) rad(U_y) (sum_ij |a_i b_j| = A B from below)
            known = size_a * size_b * (1.0 - (s + 10) * _EPS)
            rest = jnp.maximum(_up(rad_x * rad_y) - known, 0.0)
            return carried, centre, _up(rest + rounding, 2)
        # the rest, with x = c + L_S + U (U: the other symbols' part and the own error):
        # L_Sx U_y + U_x L_Sy, at most A_S rad(U_y) + rad(U_x) B_S, and U_x U_y, bounded
        # as an affine product (polarisation, _bilinear: U holds unpaired first-order
        # symbols here)
        ux = type(self)(self.c, self.a.at[..., index].set(0.0), self.e)
        uy = type(o)(o.c, o.a.at[..., index].set(0.0), o.e)
        rad_ux, rad_uy = ux.rad(), uy.rad()
        centre_u, radius_u = _bilinear(ux, uy, rad_ux, rad_uy)
        cross = _up(size_a * rad_uy + rad_ux * size_b, 2)
        return carried, centre + centre_u, _up(cross + radius_u + rounding, 3)


@functools.cache
def paired_over(k, paired):
    """The :class:`PairedForm` class over ``k`` first-order symbols that pairs only those of
    ``paired`` (a sorted tuple of indices in ``range(k)``): its symbols are the ``k``
    first-order ones, then one per pair of ``paired`` in ``np.triu_indices(len(paired))``
    order, ``pair_count(k, len(paired))`` in all. A product carries ``(a_S . eps_S)(b_S .
    eps_S)`` over the paired symbols ``S`` and bounds the rest by ``A_S rad(U_y) + rad(U_x)
    B_S`` and :func:`_bilinear`'s ``U_x U_y``, the unpaired first-order symbols in ``U``
    (polarised where they move together). Every ``paired`` is sound; all of
    ``range(k)`` gives :class:`PairedForm` itself."""
    paired = tuple(int(i) for i in paired)
    if list(paired) != sorted(set(paired)) or (paired and not 0 <= paired[0] <= paired[-1] < k):
        raise ValueError(f"paired must be sorted distinct indices in range({k}), got {paired}")
    if paired == tuple(range(k)):
        return PairedForm
    cls = type(f"PairedForm{k}of{len(paired)}", (PairedForm,), {})
    cls.pairing = (k, np.asarray(paired, dtype=np.int32))
    return jax.tree_util.register_pytree_node_class(cls)


def _recip_positive(x):
    """``1/x`` for forms whose range is in ``(0, inf)``; ``e = inf`` where it is not."""
    lo, hi = x.bounds()
    ok = lo > 0
    lo = jnp.where(ok, lo, 1.0)
    hi = jnp.where(ok, hi, 1.0)
    alpha = -1.0 / (hi * hi)  # any float slope is sound; this one is min-range
    mag = -alpha

    # 1/t - alpha t = 1/t + |alpha| t on [lo, hi]: convex, its max at an end, its min
    # at least 2 sqrt(|alpha|) (AM-GM, for every t > 0)
    def upper(t):
        return _up(1.0 / t * (1.0 + _REL) + mag * t * (1.0 + _REL), 2)

    zeta_hi = jnp.maximum(upper(lo), upper(hi))
    zeta_lo = 2.0 * jnp.sqrt(mag) * (1.0 - _REL) - _TINY
    zeta_mid = 0.5 * (zeta_lo + zeta_hi)
    zeta_rad = _up(jnp.maximum(zeta_hi - zeta_mid, zeta_mid - zeta_lo), 2)
    c = alpha * x.c + zeta_mid
    a = x.a * alpha[..., None]
    slack = (jnp.abs(c) + jnp.abs(alpha * x.c) + jnp.sum(jnp.abs(a), axis=-1)) * _REL
    e = _up(mag * x.e + zeta_rad + slack, 4)
    return type(x)(c, a, jnp.where(ok, e, jnp.inf))


def recip(x: AffineForm) -> AffineForm:
    """``1/x``; a form whose range holds 0 gives ``e = inf``."""
    negative = x.c < 0
    sign = jnp.where(negative, -1.0, 1.0).astype(x.c.dtype)
    flipped = type(x)(x.c * sign, x.a * sign[..., None], x.e)  # exact
    r = _recip_positive(flipped)
    return type(x)(r.c * sign, r.a * sign[..., None], r.e)


def sqr(x: AffineForm) -> AffineForm:
    """``x^2 = c^2 + 2c (L + E) + (L + E)^2``, the last in ``[0, rad^2]`` (a
    :class:`PairedForm`: ``x * x``, whose first-order square is carried)."""
    if isinstance(x, PairedForm):
        return x * x
    r = x.rad()
    half = 0.5 * r * r
    c = x.c * x.c + half
    a = x.a * (2.0 * x.c)[..., None]
    slack = (jnp.abs(c) + x.c * x.c + half + jnp.sum(jnp.abs(a), axis=-1)) * _REL
    return type(x)(c, a, _up(2.0 * jnp.abs(x.c) * x.e + half * (1.0 + _REL) + slack, 4))


def _trig(x, fn, slope_fn, library=None):
    """``fn(c + d) = fn(c) + fn'(c) d + rho``, ``|rho| <= d^2 / 2`` (``|fn''| <= 1``).

    ``library`` bounds the float error of ``fn(c)`` and of the slope (default: XLA's
    ``sin``/``cos``, ``2^-44`` plus ``|c| 2^-50`` for the argument's reduction).
    """
    r = x.rad()
    c = fn(x.c)
    s = slope_fn(x.c)
    a = x.a * s[..., None]
    if library is None:
        library = _TRIG_ABS + jnp.abs(x.c) * _REL  # XLA's error in fn(c) and in the slope
    slack = jnp.sum(jnp.abs(a), axis=-1) * _REL
    e = jnp.abs(s) * x.e + 0.5 * r * r * (1.0 + _REL) + library * (1.0 + r) + slack
    return type(x)(c, a, _up(e, 6))


def sin(x: AffineForm) -> AffineForm:
    return _trig(x, jnp.sin, jnp.cos)


def cos(x: AffineForm) -> AffineForm:
    return _trig(x, jnp.cos, lambda t: -jnp.sin(t))


def tanh(x: AffineForm) -> AffineForm:
    """``tanh`` by the same first-order form (``|tanh''| <= 4 / (3 sqrt 3) < 1``); the slope
    ``1 - t^2`` is computed from the float ``t = tanh(c)`` (within ``2^-44`` of the exact
    value, see :func:`rmijax._intervals.tanh`), so both are within ``2^-42``."""
    return _trig(x, jnp.tanh, lambda t: 1.0 - jnp.tanh(t) ** 2, library=4 * _TRIG_ABS)


def _expand(x: AffineForm, axis: int) -> AffineForm:
    """Insert a length-1 axis at ``axis`` (0 or 1) of a form of rank <= 1."""
    index = (None, slice(None)) if axis == 0 else (slice(None), None)
    return type(x)(x.c[index], x.a[index + (slice(None),)], x.e[index])


class AffineBackend:
    """The operations :class:`rmijax._intervals.Jet` needs, on arrays of ``form``
    (:class:`AffineForm` or :class:`PairedForm`) over ``k`` symbols."""

    sin = staticmethod(sin)
    cos = staticmethod(cos)
    tanh = staticmethod(tanh)
    recip = staticmethod(recip)
    sqr = staticmethod(sqr)

    def __init__(self, k, form=AffineForm):
        self.k, self.form = k, form

    @staticmethod
    def is_interval(x):
        return isinstance(x, AffineForm)

    def zeros(self, shape, like=None):
        return self.form.point(jnp.zeros(shape), self.k)

    @staticmethod
    def outer(a, b):
        return _expand(a, 1) * _expand(b, 0)

    def point(self, value):
        return self.form.point(value, self.k)


def run_affine_tape(tape_arrays, leaves, outputs, form=AffineForm):
    """Replay a tape on second-order jets of affine forms.

    Args:
        tape_arrays: ``(ops, args, lits)`` from :meth:`rmijax._intervals.Tape.arrays`.
        leaves: three :class:`AffineForm` jets parts of the ``L`` leaves: value
            ``(L,)``, gradient ``(L, m)``, Hessian ``(L, m, m)``, each over ``K`` symbols.
        outputs: (r,) rows wanted.
        form: the forms' class: :class:`PairedForm` carries the products' first-order
            parts in its pair symbols (the leaves then over ``pair_count(k)`` symbols).

    Returns:
        ``(value, grad, hess)`` :class:`AffineForm` of shapes (r,), (r, m), (r, m, m).
    """
    value, grad, hess = leaves
    m, k = grad.c.shape[1], value.n_symbols
    dtype = value.c.dtype
    backend = PackedHessians(m, AffineBackend(k, form))  # the upper triangles only
    size = backend.size
    hess = AffineForm(backend.pack(hess.c), backend.pack(hess.a), backend.pack(hess.e))

    def jet(row):
        return Jet(form(*row[0:3]), form(*row[3:6]), form(*row[6:9]), backend)

    def flat(j):
        return tuple(leaf for part in (j.v, j.g, j.h) for leaf in (part.c, part.a, part.e))

    def const(lit):
        zero = jnp.zeros((), dtype)
        rows = (lit, jnp.zeros((k,), dtype), zero)
        rows += (jnp.zeros((m,), dtype), jnp.zeros((m, k), dtype), jnp.zeros((m,), dtype))
        rows += (jnp.zeros((size,), dtype), jnp.zeros((size, k), dtype))
        return rows + (jnp.zeros((size,), dtype),)

    flat_leaves = [leaf for part in (value, grad, hess) for leaf in (part.c, part.a, part.e)]
    out = replay(tape_arrays, flat_leaves, jet_branches(jet, flat, const), outputs)
    h = form(*(backend.unpack(x) for x in out[6:9]))
    return form(*out[0:3]), form(*out[3:6]), h
