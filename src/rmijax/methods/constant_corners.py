"""Bounds from constant corners: the envelope of the closed loop run once per corner.

The physical robot has constant parameters. This method runs the true coupled
plant under the nominal computed-torque controller (fault-free, noise-free,
exactly as :func:`rmijax.simulate` steps it) once per corner of the parameter
box held constant, and takes per step and output the min and max over the
``K = 2^p`` corners. Unlike RMI it has ``K`` tracks (not ``4n K``
evaluations per step) and no step-wise maximiser, so its bands are as tight
as the corner runs themselves.

What it does not promise: an interior parameter vector is covered only where
every output is monotone in every parameter over the run; where an output is
not monotone, an interior robot can leave the envelope. And a constant error
makes the tachometer's impulse response cancel, so the velocity bands are
narrow: there are no sign-alternating tachometer bands as in RMI, where the
step-wise maximiser adds both lobes (SPEC section 10).

Shape of the computation: corners are built from their index in chunks
(never the ``(K, p)`` tensor nor ``(K, T+1, n, 2)`` states: ``n = 8`` has
65536 corners); a chunk is one ``vmap`` of the plant over corners and time is
a ``lax.scan``; the envelope is reduced chunk by chunk in a ``lax.scan`` over
chunks, all ``jit``-compiled (or chunk by chunk with a progress bar).
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from rmijax import _checks
from rmijax.methods.base import Bounds, DivergedError, check_types
from rmijax.plant import _NEVER, DIVERGENCE_LIMIT, _fault_tables, _plant_start, _plant_step, _run
from rmijax.robots.box import UncertainRobot, uncertain_indices
from rmijax.robots.check import check_model
from rmijax.trajectory import Trajectory

__all__ = ["HORIZONS", "constant_corner_bounds", "corner_of_index"]

HORIZONS = ("run", "window")
"""``run``: whole runs from ``x(0) = x_d(0)``; ``window``: per end step, from ``x_n(k0)``."""

_CHUNK_BUDGET = 256 * 2**20
"""Bytes allowed for one chunk of whole runs (states and readings of every corner)."""

_MAX_CHUNK = 1024
"""Most corners per chunk."""

_WINDOW_LANES = 4096
"""(corner, end step) pairs advanced together in the ``window`` horizon."""

PLANT_STEPS_PER_SECOND = 2e7
"""Plant steps per second, weighted by ``n^2``, that the time estimate assumes: a fast
machine (a 2-core CPU measured 2e6 to 6e6)."""

_MAX_PARAMS = 30
"""Corners are indexed by int32: at most ``2^30`` of them."""


def corner_of_index(index, lo, hi, indices=None):
    """Corner ``index`` of the box: ``hi[b]`` where bit ``b`` of ``index`` is set, else ``lo[b]``.

    Args:
        index: int32 scalar, ``0 <= index < 2^p``.
        lo, hi: (p,) the box.
        indices: None, or a static tuple of the parameters the bits stand for
            (bit ``j`` sets parameter ``indices[j]``; the others stay at ``lo``).

    Returns:
        (p,) the corner, row ``index`` of :func:`rmijax.corner_tensor` (with the same ``indices``).
    """
    if indices is None:
        bits = (index >> jnp.arange(lo.shape[0], dtype=jnp.int32)) & 1
        return jnp.where(bits == 1, hi, lo)
    chosen = np.asarray(indices, int)
    bits = (index >> jnp.arange(chosen.size, dtype=jnp.int32)) & 1
    return lo.at[chosen].set(jnp.where(bits == 1, hi[chosen], lo[chosen]))


def _n_corners(params, uncertain):
    return params.n_corners if uncertain is None else 2 ** len(uncertain)


def _chunk_corners(params, first, size, uncertain):
    """Corners ``first .. first + size - 1`` (clipped to the last one: duplicates are harmless)."""
    last = _n_corners(params, uncertain) - 1
    index = jnp.minimum(first + jnp.arange(size, dtype=jnp.int32), last)
    return jax.vmap(corner_of_index, in_axes=(0, None, None, None))(
        index, params.lo, params.hi, uncertain
    )


def _run_chunk(traj, params, tables, first, *, size, uncertain):
    """Min and max over one chunk of corners of whole runs: (T+1, n, 2) each."""
    th = _chunk_corners(params, first, size, uncertain)
    noise = jnp.zeros_like(traj.x_n)
    states, _, _ = jax.vmap(_run, in_axes=(None, None, 0, None, None, None))(
        traj, params, th, noise, tables, DIVERGENCE_LIMIT
    )
    return jnp.min(states, axis=0), jnp.max(states, axis=0)


def _window_final(x0, u_win, active, th, params, kp, kd, dt, tables):
    """The plant's state (n, 2) after one window from ``x0``, corner ``th`` held; NaN if diverged.

    The window is aligned at its end like RMI's: step ``s`` is inactive while
    ``t_f - N + s < 0``. Fault-free, so the step index passed to the plant is
    the window's own ``s``.
    """
    step = functools.partial(
        _plant_step,
        params=params,
        th=th,
        kp=kp,
        kd=kd,
        dt=dt,
        tables=tables,
        limit=DIVERGENCE_LIMIT,
    )
    zero_noise = jnp.zeros_like(x0)
    zero_time = jnp.zeros((), x0.dtype)

    def body(carry, inputs):
        s, u, on = inputs
        new, _ = step(carry, (s, zero_time, u, zero_noise))
        return jax.tree_util.tree_map(lambda a, b: jnp.where(on, a, b), new, carry), None

    window = u_win.shape[0]
    steps = jnp.arange(window, dtype=jnp.int32)
    (x, _, diverged), _ = jax.lax.scan(body, _plant_start(x0), (steps, u_win, active))
    return jnp.where(diverged == _NEVER, x, jnp.nan)


def _window_chunk(traj, params, tables, first, *, size, window, batch, uncertain):
    """Min and max over one chunk of corners at every end step, windows from ``x_n(k0)``."""
    th = _chunk_corners(params, first, size, uncertain)
    u_pad = jnp.concatenate([jnp.zeros((window, traj.n_joints), traj.dtype), traj.u_d], axis=0)

    def end_step(t_f):
        u_win = jax.lax.dynamic_slice_in_dim(u_pad, t_f, window, 0)
        active = (t_f - window + jnp.arange(window)) >= 0
        x0 = traj.x_n[jnp.maximum(t_f - window, 0)]
        finals = jax.vmap(
            _window_final, in_axes=(None, None, None, 0, None, None, None, None, None)
        )(x0, u_win, active, th, params, traj.kp, traj.kd, traj.dt, tables)
        return jnp.min(finals, axis=0), jnp.max(finals, axis=0)

    return jax.lax.map(end_step, jnp.arange(traj.n_steps + 1), batch_size=batch)


def _chunk_fn(horizon, size, window, batch, uncertain):
    if horizon == "run":
        return functools.partial(_run_chunk, size=size, uncertain=uncertain)
    return functools.partial(
        _window_chunk, size=size, window=window, batch=batch, uncertain=uncertain
    )


@functools.partial(
    jax.jit, static_argnames=("horizon", "size", "n_chunks", "window", "batch", "uncertain")
)
def _envelope_all(traj, params, tables, *, horizon, size, n_chunks, window, batch, uncertain):
    chunk = _chunk_fn(horizon, size, window, batch, uncertain)

    def body(carry, first):
        low, high = chunk(traj, params, tables, first)
        return (jnp.minimum(carry[0], low), jnp.maximum(carry[1], high)), None

    init = (jnp.full_like(traj.x_n, jnp.inf), jnp.full_like(traj.x_n, -jnp.inf))
    firsts = jnp.arange(n_chunks, dtype=jnp.int32) * size
    (low, high), _ = jax.lax.scan(body, init, firsts)
    return low, high


@functools.partial(jax.jit, static_argnames=("horizon", "size", "window", "batch", "uncertain"))
def _envelope_chunk(traj, params, tables, first, *, horizon, size, window, batch, uncertain):
    return _chunk_fn(horizon, size, window, batch, uncertain)(traj, params, tables, first)


def _envelope_with_progress(
    traj, params, tables, *, horizon, size, n_chunks, window, batch, uncertain
):
    from tqdm.auto import tqdm

    low = jnp.full_like(traj.x_n, jnp.inf)
    high = jnp.full_like(traj.x_n, -jnp.inf)
    total = _n_corners(params, uncertain)
    desc = f"constant corners ({horizon}) n={traj.n_joints}"
    with tqdm(total=total, desc=desc, unit="corner") as bar:
        for chunk in range(n_chunks):
            first = jnp.asarray(chunk * size, jnp.int32)
            chunk_low, chunk_high = _envelope_chunk(
                traj,
                params,
                tables,
                first,
                horizon=horizon,
                size=size,
                window=window,
                batch=batch,
                uncertain=uncertain,
            )
            low, high = jnp.minimum(low, chunk_low), jnp.maximum(high, chunk_high)
            low.block_until_ready()
            bar.update(min(size, total - chunk * size))
    return low, high


def _validate(traj, params, horizon, window, noise_lo, noise_hi, chunk_size):
    check_types(traj, params)
    if horizon not in HORIZONS:
        raise ValueError(f"unknown horizon {horizon!r}; choose one of {HORIZONS}")
    window = _checks.positive_int("window", window, "steps")
    chunk_size = _checks.chunk_size(chunk_size, "corners")
    n = traj.n_joints
    if params.n_joints != n:
        raise ValueError(
            f"traj has {n} joints but params describes a {params.n_joints}-joint robot; "
            "give one path per joint of the robot"
        )
    uncertain = uncertain_indices(params)
    count = params.n_params if uncertain is None else len(uncertain)
    if count > _MAX_PARAMS:
        raise ValueError(
            f"constant_corners runs the plant once per corner: 2^{count} corners "
            f"are out of reach (at most 2^{_MAX_PARAMS}); make parameters certain "
            "(lo == hi) or use a method that scales (rmijax.bounds)"
        )
    dtype = jnp.result_type(traj.dtype, params.dtype)
    for name in ("u_d", "x_n", "kp", "kd"):
        _checks.check_finite(f"traj.{name}", getattr(traj, name))
    _checks.check_stable(traj.kp, traj.kd, traj.dt)
    lo, hi = _checks.noise_interval(noise_lo, noise_hi, n, dtype)
    check_model(params, traj)
    return dtype, window, chunk_size, lo, hi


def _chunking(traj, params, horizon, chunk_size, itemsize, uncertain):
    """Corners per chunk, number of chunks and (window horizon) end steps per batch."""
    n_corners, n_samples = _n_corners(params, uncertain), traj.n_steps + 1
    if chunk_size is None:
        if horizon == "run":  # states, readings and their NaN-masked copies per corner
            per_corner = 4 * n_samples * traj.n_joints * 2 * itemsize
            chunk_size = max(1, min(_MAX_CHUNK, _CHUNK_BUDGET // per_corner))
        else:
            chunk_size = 256
    size = min(int(chunk_size), n_corners)
    batch = max(1, min(n_samples, _WINDOW_LANES // size))
    return size, math.ceil(n_corners / size), batch


def _check_finite_envelope(low, high, dt):
    where = _checks.first_non_finite(low, high)
    if where is not None:
        step, joint, sensor = where
        raise DivergedError.at(
            where,
            f"a constant-corner run diverged (|state| > {DIVERGENCE_LIMIT:g} or non-finite) "
            f"by step {step} (t = {step * dt:.2f} s, joint {joint} "
            f"{DivergedError.SENSORS[sensor]}): the closed loop is unstable for "
            "some corner of the box. Narrow the parameter box (lo, hi) or use stiffer "
            "gains (kp, kd).",
        )


def constant_corner_bounds(
    traj: Trajectory,
    params: UncertainRobot,
    *,
    horizon: str = "run",
    window: int = 100,
    noise_lo=0.0,
    noise_hi=0.0,
    chunk_size: int | None = None,
    progress: bool = False,
) -> Bounds:
    """Bounds as the envelope of the closed loop run once per constant corner.

    Every corner of the box is held constant in the true coupled plant under
    the nominal computed-torque controller, fault-free and noise-free,
    stepped exactly as :func:`rmijax.simulate` steps it; the bounds are the
    min and max over corners per step and output, plus the sensor noise as
    :func:`rmijax.rmi` adds it. So every constant-corner run lies inside by
    construction. No guarantee for interior parameters where an output is
    not monotone in the parameters; and the tachometer band is the corner
    runs' own (narrow) spread: no sign-alternating tachometer bands as RMI's
    step-wise maximiser builds (see the module docstring).

    Args:
        traj: the desired motion and its nominal response (T+1 samples).
        params: the robot and its parameter box (``K = 2^p`` corners, p <= 30).
        horizon: ``"run"`` (default): whole runs from the known start
            ``x(0) = x_d(0)``; ``"window"``: for each end step ``t_f`` every
            corner runs over RMI's window ``k0 = max(0, t_f - N) .. t_f`` from
            ``x_n(k0)``, and the envelope is taken at ``t_f``.
        window: ``N`` in steps (>= 1), used by ``horizon="window"`` only.
        noise_lo, noise_hi: sensor noise bounds ``[V_lo, V_hi]``, scalar,
            ``(2,)`` (encoder rad, tachometer rad/s) or ``(n, 2)``.
        chunk_size: corners per chunk; default from a 256 MiB working set
            (``run``, at most 1024) or 256 (``window``).
        progress: show a progress bar over corners (eager calls only).

    Returns:
        :class:`~rmijax.methods.base.Bounds` with ``lower``, ``upper``, ``nominal``
        (the nominal output ``c x_n(t_f)``) and ``crossed``, each (T+1, n, 2).

    Raises:
        TypeError, ValueError: invalid inputs (the message names the argument):
            unknown ``horizon``, ``window`` or ``chunk_size`` < 1, mismatched
            joints, ``noise_lo > noise_hi``, more than 30 parameters.
        DivergedError: a corner's run diverged (checked outside ``jit`` only).
    """
    dtype, window, chunk_size, lo, hi = _validate(
        traj, params, horizon, window, noise_lo, noise_hi, chunk_size
    )
    progress = _checks.boolean("progress", progress)
    traj, params = _checks.cast_tree(traj, dtype), _checks.cast_tree(params, dtype)
    tables = _fault_tables((), traj.n_joints, traj.n_steps, traj.dt, dtype)
    uncertain = uncertain_indices(params)  # certain parameters add no corners
    itemsize = jnp.dtype(dtype).itemsize
    size, n_chunks, batch = _chunking(traj, params, horizon, chunk_size, itemsize, uncertain)
    n_corners = _n_corners(params, uncertain)
    per_corner = traj.n_steps + 1
    if horizon == "window":
        per_corner *= min(window, traj.n_steps)
    steps = n_corners * per_corner
    _checks.check_time(
        f"constant_corners over {n_corners} corners x {traj.n_steps + 1} steps"
        + (f" x {min(window, traj.n_steps)}-step windows" if horizon == "window" else ""),
        steps * traj.n_joints**2 / PLANT_STEPS_PER_SECOND,
        progress=progress,
        fixes="Make parameters certain (lo == hi: each halves the corners), shorten the run, "
        "or use a method that scales (rmijax.bounds with method='linearized' or "
        "'corner_search').",
    )
    window = min(window, traj.n_steps)  # a longer window gives the same windows
    if horizon == "run":  # no window: one compiled program whatever ``window`` is
        window, batch = 0, 0
    options = dict(
        horizon=horizon,
        size=size,
        n_chunks=n_chunks,
        window=window,
        batch=batch,
        uncertain=uncertain,
    )
    leaves = jax.tree_util.tree_leaves((traj, params))
    if progress and all(_checks.is_concrete(a) for a in leaves):
        low, high = _envelope_with_progress(traj, params, tables, **options)
    else:
        low, high = _envelope_all(traj, params, tables, **options)
    _check_finite_envelope(low, high, traj.dt)
    upper = high + jnp.broadcast_to(hi[None], high.shape)
    lower = low + jnp.broadcast_to(lo[None], low.shape)
    return Bounds(lower=lower, upper=upper, nominal=traj.x_n, crossed=upper < lower, dt=traj.dt)
