"""Input validation shared by the public entry points.

Every check raises an error that names the argument and says how to fix it.
Value checks run only on concrete arrays; under a user's ``jax.jit`` the
arrays are tracers and only shapes can be checked.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


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


def per_joint(name, value, n, dtype):
    """A scalar or ``(n,)`` gain as an ``(n,)`` array."""
    array = jnp.asarray(value, dtype=dtype)
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
        a = np.array([[1.0, dt], [-kp_i * dt, 1.0 - kd_i * dt]])
        radii.append(np.max(np.abs(np.linalg.eigvals(a))))
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
    array = jnp.asarray(value, dtype=dtype)
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
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        what = f"an integer number of {unit} >= 1" if unit else "an integer >= 1"
        raise ValueError(f"{name} must be {what}, got {value!r}")
    return int(value)


def tolerance(tol) -> float:
    """A detection tolerance: finite and >= 0."""
    if not (np.isfinite(tol) and tol >= 0):
        raise ValueError(f"tol must be a finite number >= 0, got {tol!r}")
    return float(tol)


def cast_tree(tree, dtype):
    """Every array leaf of a pytree as ``dtype``."""
    return jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), tree)
