"""What the certificate checker's interval arithmetic costs per operation, by library.

A chain checker step (``check_certificate``) spends its time in ``mpmath``'s pure-Python
interval operations themselves (a cProfile of the UR5e's step, stop 57: ``mpf_add``,
``mpi_mul``, ``mpi_add``, ``mpf_sign`` take most of the self time), not in the wrapper
around them. This times the operations those profiles name, on the same random
intervals, in each library that could carry the checker's ends:

- ``mpmath_libmp``: ``mpmath.libmp``'s ``mpi_*`` on raw ends at 53 bits, what the checker
  runs now (:func:`rmijax.methods.certificate_check._upper_sum_of_abs` for the sum);
- ``mpmath_iv``: ``mpmath.iv`` objects, what the checker ran before stop 56;
- ``flint_arb``: ``python-flint``'s ``arb`` balls at 53 bits (C; skipped when
  ``python-flint`` is not installed: it is no dependency of rmijax);
- ``numpy_nextafter``: float64 arrays, each result stepped one ulp outward with
  ``np.nextafter`` (vectorised over the operands; not correctly rounded, so its ends are
  up to one ulp wider than the others').

Two kernels, ``N`` operands each: ``chain``, the dot product ``sum_i x_i y_(i+1)`` (one
interval product and one sum per term), and ``abs_sum``, the upper end of ``sum_i |x_i|``
(the radius of an affine form). Each backend's result is checked to contain the exact
value (``fractions.Fraction``) before it is timed; the figure is the best of ``--reps``
repeats, in microseconds per term. These are the elementary costs only: a checker on
another library would also rebuild the forms around them, so the ratio bounds what a port
could gain rather than measuring a port.

    python benchmarks/interval_backends.py --json benchmarks/results/interval_backends_cpu.json
"""

from __future__ import annotations

import argparse
import timeit
from fractions import Fraction

import numpy as np
from _common import run_meta, table, write_json

from rmijax.methods import certificate_check as checker


def _operands(n, seed):
    """``n`` intervals ``[lo, hi]`` (float64 ends): a third straddle 0, the rest one-sided,
    magnitudes ``1e-6`` to ``1e3``."""
    rng = np.random.default_rng(seed)
    mid = rng.choice([-1.0, 1.0], n) * 10.0 ** rng.uniform(-6, 3, n)
    rad = np.abs(mid) * np.where(rng.random(n) < 1 / 3, 2.0, rng.uniform(0, 0.5, n))
    return mid - rad, mid + rad


def _exact(lo, hi):
    """The exact ``chain`` and ``abs_sum`` over the interval ends (the values at the ends'
    midpoints for ``chain``, which every sound enclosure holds)."""
    mids = [(Fraction(a) + Fraction(b)) / 2 for a, b in zip(lo, hi, strict=True)]
    chain = sum(mids[i] * mids[i + 1] for i in range(len(mids) - 1))
    abs_sum = sum(max(-Fraction(a), Fraction(b)) for a, b in zip(lo, hi, strict=True))
    return chain, abs_sum


def _libmp(lo, hi):
    mp, prec = checker._mp, checker._PREC
    ends = [(mp.from_float(float(a)), mp.from_float(float(b))) for a, b in zip(lo, hi, strict=True)]
    iv = checker._iv()
    objects = np.array([iv.make_mpf(e) for e in ends], dtype=object)

    def chain():
        acc = (mp.fzero, mp.fzero)
        for i in range(len(ends) - 1):
            acc = mp.mpi_add(acc, mp.mpi_mul(ends[i], ends[i + 1], prec), prec)
        return acc

    def abs_sum():
        return checker._upper_sum_of_abs(mp.fzero, objects)

    def ends_of(value, kind):
        if kind == "chain":
            return Fraction(*mp.to_rational(value[0])), Fraction(*mp.to_rational(value[1]))
        return None, Fraction(*mp.to_rational(value))

    return chain, abs_sum, ends_of


def _operator_kernels(xs, zero):
    """``chain`` and ``abs_sum`` on interval objects with ``+``, ``*`` and ``abs`` (both
    ``mpmath.iv`` and ``flint.arb``), starting from ``zero``."""

    def chain():
        acc = zero
        for i in range(len(xs) - 1):
            acc = acc + xs[i] * xs[i + 1]
        return acc

    def abs_sum():
        acc = zero
        for x in xs:
            acc = acc + abs(x)
        return acc

    return chain, abs_sum


def _mp_iv(lo, hi):
    iv = checker._iv()
    xs = [iv.mpf([float(a), float(b)]) for a, b in zip(lo, hi, strict=True)]

    chain, abs_sum = _operator_kernels(xs, iv.mpf(0))

    def ends_of(value, kind):
        lo_, hi_ = (Fraction(*checker._mp.to_rational(e)) for e in value._mpi_)
        return (lo_, hi_) if kind == "chain" else (None, hi_)

    return chain, abs_sum, ends_of


def _arb(lo, hi):
    import flint

    flint.ctx.prec = checker._PREC
    # the ball holding [lo, hi]: its midpoint rounded, its radius rounded up (arb's own)
    xs = [flint.arb(float(a)).union(flint.arb(float(b))) for a, b in zip(lo, hi, strict=True)]

    chain, abs_sum = _operator_kernels(xs, flint.arb(0))

    def exact(point):
        man, exp = (int(v) for v in point.man_exp())
        return Fraction(man) * Fraction(2) ** exp

    def ends_of(value, kind):
        lo_, hi_ = exact(value.lower()), exact(value.upper())
        return (lo_, hi_) if kind == "chain" else (None, hi_)

    return chain, abs_sum, ends_of


def _numpy(lo, hi):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)

    def outward(low, high):
        return np.nextafter(low, -np.inf), np.nextafter(high, np.inf)

    def chain():
        a0, a1, b0, b1 = lo[:-1], hi[:-1], lo[1:], hi[1:]
        products = np.stack([a0 * b0, a0 * b1, a1 * b0, a1 * b1])
        p0, p1 = outward(products.min(axis=0), products.max(axis=0))
        # a running sum, each partial sum stepped outward (np.cumsum rounds to nearest)
        s0 = s1 = 0.0
        for u, v in zip(p0, p1, strict=True):
            s0, s1 = np.nextafter(s0 + u, -np.inf), np.nextafter(s1 + v, np.inf)
        return s0, s1

    def abs_sum():
        top = np.maximum(-lo, hi)
        s = 0.0
        for t in top:
            s = np.nextafter(s + t, np.inf)
        return s

    return chain, abs_sum, _float_ends


def _numpy_vector(lo, hi):
    """``numpy_nextafter`` with the sums done by ``np.sum`` and one outward bound of its
    rounding error (``n`` terms: ``|error| <= (n - 1) u sum |t_i|``, ``u = 2^-53``, plus
    a step): no Python loop at all."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    unit = 2.0**-53

    def bounded_sum(terms):
        total = np.sum(terms)
        slack = (len(terms) * unit) * np.sum(np.abs(terms)) * (1 + 4 * len(terms) * unit)
        return total, np.nextafter(slack, np.inf)

    def chain():
        a0, a1, b0, b1 = lo[:-1], hi[:-1], lo[1:], hi[1:]
        products = np.stack([a0 * b0, a0 * b1, a1 * b0, a1 * b1])
        p0 = np.nextafter(products.min(axis=0), -np.inf)
        p1 = np.nextafter(products.max(axis=0), np.inf)
        (t0, e0), (t1, e1) = bounded_sum(p0), bounded_sum(p1)
        return np.nextafter(t0 - e0, -np.inf), np.nextafter(t1 + e1, np.inf)

    def abs_sum():
        t, e = bounded_sum(np.maximum(-lo, hi))
        return np.nextafter(t + e, np.inf)

    return chain, abs_sum, _float_ends


def _float_ends(value, kind):
    """The numpy backends' ends as rationals: ``(lo, hi)`` for ``chain``, ``(None, hi)``
    for ``abs_sum``."""
    if kind == "chain":
        return Fraction(float(value[0])), Fraction(float(value[1]))
    return None, Fraction(float(value))


BACKENDS = {
    "mpmath_libmp": _libmp,
    "mpmath_iv": _mp_iv,
    "flint_arb": _arb,
    "numpy_nextafter": _numpy,
    "numpy_vector": _numpy_vector,
}


def _available(name):
    if name != "flint_arb":
        return True
    try:
        import flint  # noqa: F401
    except ImportError:
        return False
    return True


def run(sizes, reps, seed):
    rows = []
    for n in sizes:
        lo, hi = _operands(n, seed)
        exact = dict(zip(("chain", "abs_sum"), _exact(lo, hi), strict=True))
        for name, make in BACKENDS.items():
            if not _available(name):
                print(f"{name}: not installed, skipped")
                continue
            chain, abs_sum, ends_of = make(lo, hi)
            row = {"backend": name, "n": n}
            for kind, fn in (("chain", chain), ("abs_sum", abs_sum)):
                low, high = ends_of(fn(), kind)
                row[f"{kind}_contains"] = bool(
                    (low is None or low <= exact[kind]) and exact[kind] <= high
                )
                row[f"{kind}_width_rel"] = (
                    float((high - low) / abs(exact[kind])) if low is not None else None
                )
                number = max(1, 20000 // n)
                best = min(timeit.repeat(fn, number=number, repeat=reps)) / number
                row[f"{kind}_us_per_term"] = best / n * 1e6
            rows.append(row)
    base = {r["n"]: r for r in rows if r["backend"] == "mpmath_libmp"}
    for r in rows:
        for kind in ("chain", "abs_sum"):
            r[f"{kind}_speedup"] = base[r["n"]][f"{kind}_us_per_term"] / r[f"{kind}_us_per_term"]
    return rows


COLUMNS = [
    ("backend", "backend", "{:<16}"),
    ("n", "n", "{:>5}"),
    ("chain_us_per_term", "chain us/term", "{:>13.3f}"),
    ("chain_speedup", "x libmp", "{:>8.1f}"),
    ("abs_sum_us_per_term", "abs_sum us/term", "{:>15.3f}"),
    ("abs_sum_speedup", "x libmp", "{:>8.1f}"),
    ("chain_contains", "contains", "{!s:>8}"),
]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[13, 100, 1000])
    parser.add_argument("--reps", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", help="write the results to this JSON file")
    args = parser.parse_args(argv)
    rows = run(args.sizes, args.reps, args.seed)
    print(table(rows, COLUMNS))
    if not all(r["chain_contains"] and r["abs_sum_contains"] for r in rows):
        raise SystemExit("a backend's result does not contain the exact value")
    try:
        import flint

        flint_version = flint.__version__
    except ImportError:
        flint_version = None
    meta = {**run_meta("benchmarks/interval_backends.py", argv, dtype="float64")}
    meta["python_flint"] = flint_version
    import mpmath

    meta["mpmath"] = mpmath.__version__
    write_json(args.json, rows, meta)


if __name__ == "__main__":
    main()
