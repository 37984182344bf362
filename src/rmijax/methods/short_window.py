"""Short-window RMI from the measured state: the paper's section 4 proposal.

RMI (:func:`rmijax.rmi`) starts every window at the nominal state ``x_n(k0)``
and needs a long window (``N = 100``) to forget that start; its cost grows
with ``N``. The paper proposes instead to restart each window from the
*measured* state: for end step ``t_f`` the tracks start at ``x(k0) = y(k0)``,
``k0 = max(0, t_f - N)``, with ``N`` a few steps (default 2), and run the
unchanged RMI recursion (same costate weights, same corner choice, both
modes). The engine does the work (:func:`rmijax.methods.rmi._rmi_from_starts`);
this module validates the readings and accounts for their noise.

Sensor noise: a reading ``y`` carries noise in ``[V_lo, V_hi]``, so the true
start lies in ``[y - V_hi, y - V_lo]``. That start error is propagated
through the linear part of the closed loop over the window, per joint
``A_i^m`` with ``m = t_f - k0`` steps, in interval arithmetic, and widens the
bounds; the output noise is then added as :func:`rmijax.rmi` adds it. The
start error's effect on the perturbation ``gv`` (a product of a small state
error and a small parameter error) is ignored: it is second order. Like RMI,
the window's closed loop runs on the true state (SPEC section 3): that the
controller acts on noisy readings inside the window is not modelled.

Like RMI, the greedy step-wise corner choice gives no containment guarantee
(on the two-joint paper run, fault-free and noise-free, 2 of 36 box robots
had a tachometer sample outside, by at most 0.2% of the band width).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from rmijax import _checks
from rmijax.methods.base import Bounds
from rmijax.methods.rmi import (
    DEFAULT_MEMORY_BUDGET,
    _cast,
    _check_result,
    _rmi_from_starts,
    _validate,
)
from rmijax.trajectory import Trajectory

__all__ = [
    "DEFAULT_WINDOW",
    "STARTS",
    "check_readings",
    "short_window_bounds",
    "start_error_bounds",
    "transition_powers",
]

DEFAULT_WINDOW = 2
"""Steps per short window ``N`` when none is given."""

STARTS = ("measured", "nominal")
"""Where the windows start: the readings ``y(k0)`` (the paper's proposal) or ``x_n(k0)``."""

_SENSORS = ("encoder", "tachometer")


@functools.partial(jax.jit, static_argnames=("dt", "window"))
def transition_powers(kp, kd, dt, window):
    """Powers of every joint's closed-loop matrix: ``A_i^m`` for ``m = 0..N``.

    Args:
        kp, kd: (n,) gains (1/s^2, 1/s).
        dt: the step in s.
        window: ``N`` in steps.

    Returns:
        (N+1, n, 2, 2) ``[m, joint]``, ``A_i = [[1, dt], [-kp dt, 1 - kd dt]]``,
        state order (position rad, velocity rad/s).
    """
    zeros = jnp.zeros_like(kp)
    row_q = jnp.stack([zeros + 1.0, zeros + dt], axis=-1)  # (n, 2)
    row_qd = jnp.stack([-kp * dt, 1.0 - kd * dt], axis=-1)
    matrix = jnp.stack([row_q, row_qd], axis=-2)  # (n, 2, 2)
    eye = jnp.broadcast_to(jnp.eye(2, dtype=kp.dtype), matrix.shape)

    def times_a(power, _):
        nxt = jnp.einsum("nij,njk->nik", matrix, power)
        return nxt, power

    _, powers = jax.lax.scan(times_a, eye, None, length=int(window) + 1)
    return powers


def start_error_bounds(powers, noise_lo, noise_hi):
    """Interval of the output error caused by reading noise at the window start.

    The true start is ``y - e`` with the reading noise ``e`` in
    ``[noise_lo, noise_hi]``, so the start error ``x - y`` lies in
    ``[-noise_hi, -noise_lo]``; after ``m`` linear steps it is ``A_i^m`` times
    that, bounded per output in interval arithmetic.

    Args:
        powers: (..., n, 2, 2) ``A_i^m`` (from :func:`transition_powers`).
        noise_lo, noise_hi: (n, 2) sensor noise bounds (rad, rad/s).

    Returns:
        ``(low, high)``, each (..., n, 2): bounds of ``c A_i^m (x - y)`` for
        the encoder (``[..., 0]``, rad) and tachometer (``[..., 1]``, rad/s).
    """
    lead = (1,) * (powers.ndim - 3)
    error_lo = jnp.reshape(-noise_hi, lead + (noise_hi.shape[0], 1, 2))
    error_hi = jnp.reshape(-noise_lo, lead + (noise_lo.shape[0], 1, 2))
    at_lo, at_hi = powers * error_lo, powers * error_hi
    low = jnp.sum(jnp.minimum(at_lo, at_hi), axis=-1)
    high = jnp.sum(jnp.maximum(at_lo, at_hi), axis=-1)
    return low, high


@functools.partial(jax.jit, static_argnames=("dt", "window", "n_samples"))
def _noise_offsets(kp, kd, noise_lo, noise_hi, *, dt, window, n_samples):
    """Output noise plus the start error at every end step: (T+1, n, 2) lower and upper."""
    powers = transition_powers(kp, kd, dt, window)
    steps = jnp.minimum(jnp.arange(n_samples), window)  # t_f - k0
    error_lo, error_hi = start_error_bounds(powers[steps], noise_lo, noise_hi)
    offset_lo = jnp.broadcast_to(noise_lo[None], error_lo.shape) + error_lo
    offset_hi = jnp.broadcast_to(noise_hi[None], error_hi.shape) + error_hi
    return offset_lo, offset_hi


def check_readings(readings, n_samples, n, dtype):
    """The readings as a ``(T+1, n, 2)`` array of ``dtype``; finite if concrete.

    Raises:
        ValueError: wrong shape, or a NaN/inf reading (naming its step and
            output: a diverged plant run must be cut before it).
    """
    try:
        array = jnp.asarray(readings, dtype=dtype)
    except (TypeError, ValueError) as err:
        raise TypeError(f"readings must be an array of numbers, got {readings!r}") from err
    if array.shape != (n_samples, n, 2):
        raise ValueError(
            f"readings must have shape (T+1, n, 2) = ({n_samples}, {n}, 2) for this "
            f"trajectory and robot ([..., 0] encoder in rad, [..., 1] tachometer in rad/s), "
            f"got shape {array.shape}"
        )
    if _checks.is_concrete(array):
        bad = ~np.isfinite(np.asarray(array))
        if bad.any():
            step, joint, sensor = (int(v) for v in np.argwhere(bad)[0])
            raise ValueError(
                f"readings are not finite from step {step} on (joint {joint} "
                f"{_SENSORS[sensor]}: {float(array[step, joint, sensor])!r}). A diverged run "
                "(rmijax.simulate returns NaN after divergence) must be cut before that "
                "step: pass a trajectory and readings that end before it"
            )
    return array


def short_window_bounds(
    traj: Trajectory,
    params,
    readings,
    *,
    mode: str = "coupled",
    window: int = DEFAULT_WINDOW,
    start: str = "measured",
    noise_lo=0.0,
    noise_hi=0.0,
    memory_budget: int = DEFAULT_MEMORY_BUDGET,
    chunk_size: int | None = None,
    progress: bool = False,
) -> Bounds:
    """RMI bounds over short windows that start from the measured state.

    For end step ``t_f`` the window is ``k0 = max(0, t_f - N) .. t_f``; its
    max and min tracks start at ``y(k0)`` (``start="measured"``) or at
    ``x_n(k0)`` (``start="nominal"``; with ``window=100`` this is exactly
    :func:`rmijax.rmi`) and follow RMI's recursion. In ``per_joint`` mode a
    track's own joint starts from its reading and the other joints follow the
    nominal trajectory, as in RMI. With reading noise the bounds are widened
    by the start error propagated through ``A_i^(t_f - k0)`` (see the module
    docstring; its effect on ``gv`` is ignored, second order), then the
    output noise is added.

    The bounds at ``t_f`` use the reading at ``k0 < t_f`` only (for
    ``t_f = 0`` the start is the reading itself, so the band at step 0 is that
    reading widened by the noise interval both ways). Like RMI, the greedy
    corner choice carries no containment guarantee.

    Args:
        traj: the desired motion and its nominal response (T+1 samples).
        params: the robot and its parameter box.
        readings: (T+1, n, 2) measured outputs, ``[..., 0]`` encoder (rad),
            ``[..., 1]`` tachometer (rad/s); required for
            ``start="measured"``, unused (may be None) for ``"nominal"``.
        mode: ``"coupled"`` (default) or ``"per_joint"``.
        window: ``N``, steps per window (>= 1), default 2.
        start: ``"measured"`` or ``"nominal"`` (:data:`STARTS`).
        noise_lo, noise_hi: sensor noise bounds ``[V_lo, V_hi]``, scalar,
            ``(2,)`` (encoder rad, tachometer rad/s) or ``(n, 2)``.
        memory_budget, chunk_size, progress: batching, as :func:`rmijax.rmi`.

    Returns:
        :class:`~rmijax.methods.base.Bounds` with ``lower``, ``upper``, ``nominal``
        (the nominal output ``c x_n(t_f)``) and ``crossed``, each (T+1, n, 2).

    Raises:
        TypeError, ValueError: invalid inputs, the message names the argument
            (readings of the wrong shape or not finite, unknown ``start``,
            missing readings, ``noise_lo > noise_hi``, ...).
        ProblemTooLargeError: one end step cannot fit in ``memory_budget``.
        DivergedError: the bounds are not finite.
    """
    dtype, lo, hi = _validate(traj, params, mode, window, noise_lo, noise_hi)
    if start not in STARTS:
        raise ValueError(f"unknown start {start!r}; choose one of {STARTS}")
    traj, params = _cast(traj, params, dtype)
    n_samples, n = traj.n_steps + 1, traj.n_joints
    if start == "measured":
        if readings is None:
            raise ValueError(
                "readings are required with start='measured' (the windows start from "
                "them); pass the (T+1, n, 2) measured outputs, or use start='nominal'"
            )
        starts = check_readings(readings, n_samples, n, dtype)
        offset_lo, offset_hi = _noise_offsets(
            traj.kp, traj.kd, lo, hi, dt=traj.dt, window=int(window), n_samples=n_samples
        )
    else:
        if readings is not None:
            check_readings(readings, n_samples, n, dtype)
        starts, offset_lo, offset_hi = None, lo, hi
    bounds = _rmi_from_starts(
        traj,
        params,
        starts,
        offset_lo,
        offset_hi,
        mode=mode,
        window=window,
        memory_budget=memory_budget,
        chunk_size=chunk_size,
        progress=progress,
        search="auto",
    )
    _check_result(bounds)
    return bounds
