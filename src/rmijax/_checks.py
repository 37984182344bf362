"""Input validation shared by the public entry points.

Every check raises an error that names the argument and says how to fix it.
Value checks run only on concrete arrays; under a user's ``jax.jit`` the
arrays are tracers and only shapes can be checked.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


class ProblemTooLargeError(MemoryError):
    """The problem cannot be done here: one batch exceeds the memory budget, or the
    estimated run time is hours where the caller asked for no progress bar.

    The message gives the estimate and the fixes. Re-exported as
    ``rmijax.ProblemTooLargeError``.
    """


MAX_SILENT_SECONDS = 600.0
"""Longest estimated run (s) a method starts without ``progress=True``."""


def check_time(what, seconds, *, progress, fixes):
    """Refuse, at once, a run estimated over :data:`MAX_SILENT_SECONDS` without a progress bar.

    Args:
        what: the work, e.g. ``"constant_corners: 16777216 corners x 1501 steps"``.
        seconds: the estimate, taken optimistic (a fast machine): a refusal
            means the run is hopeless here, not merely slow.
        progress: the caller's ``progress`` flag; True runs it anyway (the bar
            shows the real ETA).
        fixes: what to change instead, one sentence.
    """
    if progress or seconds <= MAX_SILENT_SECONDS:
        return
    raise ProblemTooLargeError(
        f"{what} would take at least {_duration(seconds)} (estimated for a fast machine, "
        f"before starting). {fixes} Or pass progress=True to run it anyway with a "
        "progress bar and its ETA."
    )


def _duration(seconds):
    for unit, size in (("days", 86400.0), ("hours", 3600.0), ("minutes", 60.0)):
        if seconds >= 2 * size:
            return f"{seconds / size:.3g} {unit}"
    return f"{seconds:.3g} s"


def is_concrete(value) -> bool:
    """True when ``value`` holds actual numbers (not a JAX tracer)."""
    return not isinstance(value, jax.core.Tracer)


def default_float():
    """The default float dtype: float64 when x64 is enabled, float32 otherwise."""
    return jnp.result_type(float)


def float_array(name, value, shape, *, dtype=None):
    """``value`` as a float JAX array of exactly ``shape``, finite if concrete."""
    if dtype is None:
        dtype = getattr(value, "dtype", None)
        if dtype is None or not jnp.issubdtype(dtype, jnp.floating):
            dtype = default_float()
        elif jnp.dtype(dtype).itemsize < 4:  # float16 inputs: computed in the default float
            dtype = jnp.promote_types(dtype, default_float())
    else:
        dtype = float_dtype(dtype)
    if isinstance(value, (str, bytes)):
        raise TypeError(f"{name} must be an array of numbers, got {value!r}")
    try:
        array = jnp.asarray(value, dtype=dtype)
    except (TypeError, ValueError) as err:
        raise TypeError(f"{name} must be an array of numbers, got {value!r}") from err
    if array.shape != tuple(shape):
        raise ValueError(f"{name} must have shape {tuple(shape)}, got {array.shape}")
    check_finite(name, array)
    return array


def check_finite(name, array):
    """Raise if a concrete ``array`` holds NaN or inf, naming the first bad entry."""
    if not is_concrete(array):
        return
    values = np.asarray(array)
    bad = ~np.isfinite(values)
    if bad.any():
        where = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValueError(
            f"{name} contains a non-finite value ({values[where]!r}) at index {where}; "
            "every entry must be a finite number"
        )


def first_non_finite(*arrays):
    """Index of the first NaN/inf entry over same-shaped concrete ``arrays``, else None.

    None too when any array is a tracer (nothing to inspect under ``jit``).
    """
    if not all(is_concrete(a) for a in arrays):
        return None
    finite = np.logical_and.reduce([np.isfinite(np.asarray(a)) for a in arrays])
    if finite.all():
        return None
    return tuple(int(i) for i in np.argwhere(~finite)[0])


def numbers(name, value, dtype):
    """``value`` as a JAX array of ``dtype``; strings and other non-numbers refused by name."""
    if isinstance(value, (str, bytes)) or (
        hasattr(value, "dtype")
        and not jnp.issubdtype(value.dtype, jnp.number)
        and not jnp.issubdtype(value.dtype, jnp.bool_)
    ):
        raise TypeError(f"{name} must be a number or an array of numbers, got {value!r}")
    try:
        return jnp.asarray(value, dtype=dtype)
    except (TypeError, ValueError) as err:
        raise TypeError(f"{name} must be a number or an array of numbers, got {value!r}") from err


def per_joint(name, value, n, dtype):
    """A scalar or ``(n,)`` gain as an ``(n,)`` array."""
    array = numbers(name, value, dtype)
    if array.ndim == 0:
        array = jnp.full((n,), array, dtype=dtype)
    if array.shape != (n,):
        raise ValueError(
            f"{name} must be a scalar or have shape ({n},) (one per joint), got shape {array.shape}"
        )
    check_finite(name, array)
    return array


def closed_loop_radius(kp, kd, dt):
    """Spectral radius of each joint's ``A_i = [[1, dt], [-kp dt, 1 - kd dt]]``, (n,)."""
    kp = np.atleast_1d(np.asarray(kp, dtype=np.float64))
    kd = np.atleast_1d(np.asarray(kd, dtype=np.float64))
    radii = []
    for kp_i, kd_i in zip(kp, kd, strict=True):
        with np.errstate(over="ignore", invalid="ignore"):
            a = np.array([[1.0, dt], [-kp_i * dt, 1.0 - kd_i * dt]])
        # an entry that overflows (huge gains times a huge step) is unstable, not an error
        radii.append(np.max(np.abs(np.linalg.eigvals(a))) if np.all(np.isfinite(a)) else np.inf)
    return np.array(radii)


def check_stable(kp, kd, dt):
    """Reject gains and step for which a joint's discrete closed loop is not stable."""
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive finite step in s, got {dt!r}")
    if not (is_concrete(kp) and is_concrete(kd)):
        return
    radii = closed_loop_radius(kp, kd, dt)
    bad = np.flatnonzero(radii >= 1.0)
    if bad.size:
        i = int(bad[0])
        kp_i = float(np.atleast_1d(np.asarray(kp))[i])
        kd_i = float(np.atleast_1d(np.asarray(kd))[i])
        raise ValueError(
            f"unstable closed loop on joint {i}: kp={kp_i:g}, kd={kd_i:g}, dt={dt:g} give "
            f"A_i a spectral radius of {radii[i]:.4g} (RMI needs < 1). Use a smaller dt "
            "or smaller gains (with the defaults kp=100, kd=20 the step must be "
            "below 0.2 s)"
        )


def noise_bounds(name, value, n, dtype):
    """Sensor-noise bound as an ``(n, 2)`` array, from a scalar, ``(2,)`` or ``(n, 2)``."""
    array = numbers(name, value, dtype)
    if array.shape == ():
        array = jnp.full((n, 2), array, dtype=dtype)
    elif array.shape == (2,):
        array = jnp.broadcast_to(array[None, :], (n, 2))
    elif array.shape != (n, 2):
        raise ValueError(
            f"{name} must be a scalar, shape (2,) (encoder, tachometer) or shape "
            f"({n}, 2) (per joint and sensor); got shape {array.shape}"
        )
    check_finite(name, array)
    return array


def noise_interval(noise_lo, noise_hi, n, dtype):
    """Both sensor-noise bounds as ``(n, 2)`` arrays, checked for ``noise_lo <= noise_hi``."""
    lo = noise_bounds("noise_lo", noise_lo, n, dtype)
    hi = noise_bounds("noise_hi", noise_hi, n, dtype)
    if is_concrete(lo) and is_concrete(hi):
        bad = np.argwhere(np.asarray(lo) > np.asarray(hi))
        if bad.size:
            i, s = (int(v) for v in bad[0])
            raise ValueError(
                f"noise_lo > noise_hi for joint {i} {'encoder' if s == 0 else 'tachometer'}"
                f" ({float(lo[i, s])!r} > {float(hi[i, s])!r}); the noise interval "
                "must satisfy noise_lo <= noise_hi (noise_lo is usually <= 0)"
            )
    return lo, hi


def positive_int(name, value, unit="") -> int:
    """``value`` as an int >= 1 (bools refused), or an error naming ``name``."""
    return integer(name, value, minimum=1, unit=unit)


def integer(name, value, *, minimum=None, unit="") -> int:
    """``value`` as a Python int (a real integer type, bools refused), ``>= minimum``.

    A float such as ``2.0`` or ``2.7`` and a string such as ``"3"`` are refused,
    not coerced: a count that is not an integer is a mistake somewhere upstream.
    """
    ok = _scalar_of(value, (int, np.integer), jnp.integer)
    if not ok or (minimum is not None and value < minimum):
        what = f"an integer number of {unit}" if unit else "an integer"
        if minimum is not None:
            what += f" >= {minimum}"
        raise ValueError(f"{name} must be {what}, got {value!r}")
    return int(value)


def _scalar_of(value, types, dtypes) -> bool:
    """A concrete real scalar of the given Python/NumPy ``types``, or a concrete 0-d array of
    one of ``dtypes`` (a NumPy or JAX scalar array); bools never."""
    if isinstance(value, (bool, np.bool_)):
        return False
    if isinstance(value, types):
        return True
    dtype = getattr(value, "dtype", None)
    if dtype is None or not is_concrete(value) or np.ndim(value) != 0:
        return False
    kinds = dtypes if isinstance(dtypes, tuple) else (dtypes,)
    return any(jnp.issubdtype(dtype, kind) for kind in kinds)


def real(name, value, *, minimum=None, positive=False, unit="") -> float:
    """``value`` as a finite Python float (real numbers only: strings and bools refused).

    Args:
        minimum: refuse values below it; positive: refuse values <= 0.
        unit: named in the message (``"s"``, ``"bytes"``).
    """
    ok = _scalar_of(value, (int, float, np.integer, np.floating), (jnp.integer, jnp.floating))
    if ok:
        number = float(value)
        ok = np.isfinite(number)
        ok = ok and (minimum is None or number >= minimum) and (not positive or number > 0)
    if not ok:
        what = "a finite number"
        if positive:
            what = "a positive finite number"
        elif minimum is not None:
            what = f"a finite number >= {minimum:g}"
        if unit:
            what += f" (in {unit})"
        raise ValueError(f"{name} must be {what}, got {value!r}")
    return number


def boolean(name, value) -> bool:
    """``value`` as a bool: only True/False (and NumPy bools) are accepted."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def memory_budget(value) -> int:
    """A memory budget in bytes: a positive finite number (``4 * 2**30`` is 4 GiB)."""
    ok = _scalar_of(value, (int, float, np.integer, np.floating), (jnp.integer, jnp.floating))
    if not ok or not np.isfinite(value) or value < 1:
        raise ValueError(
            f"memory_budget must be a positive number of bytes (e.g. 4 * 2**30 for 4 GiB), "
            f"got {value!r}"
        )
    return int(value)


def seed(value) -> int:
    """A random seed: an integer >= 0."""
    return integer("seed", value, minimum=0)


def chunk_size(value, unit) -> int | None:
    """``None`` or an integer >= 1 (``unit``: what a chunk counts, e.g. ``"end steps"``)."""
    if value is None:
        return None
    return integer("chunk_size", value, minimum=1, unit=unit)


def tolerance(tol) -> float:
    """A detection tolerance: finite and >= 0."""
    return real("tol", tol, minimum=0)


def cast_tree(tree, dtype):
    """Every array leaf of a pytree as ``dtype``."""
    return jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), tree)


def float_dtype(dtype):
    """The ``dtype`` option: None (the default float) or a floating dtype, else an error."""
    if dtype is None:
        return default_float()
    try:
        resolved = jnp.dtype(dtype)
    except TypeError as err:
        raise TypeError(f"dtype must be a float dtype such as jnp.float64, got {dtype!r}") from err
    if not jnp.issubdtype(resolved, jnp.floating):
        raise TypeError(
            f"dtype must be a float dtype (jnp.float32 or jnp.float64), got {resolved}; "
            "the dynamics are not defined on integers"
        )
    if resolved.itemsize < 4:
        raise TypeError(
            f"dtype {resolved} is too coarse for the dynamics (the corner tie tolerance "
            "alone is eps^(2/3) ~ 1e-2); use jnp.float32 or jnp.float64"
        )
    return resolved
