"""Desired joint paths, the time grid and the nominal closed-loop trajectory (SPEC 3, 6)."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from rmijax import _checks
from rmijax.control import closed_loop_step, feedforward, servo_command

__all__ = ["PATHS", "Trajectory", "trajectory", "trajectory_from_samples", "waypoint_trajectory"]


def _sine(t):
    return jnp.sin(t)


def _ramp(t):
    return t


def _composite(t):
    return jnp.sin(t) + jnp.cos(0.5 * t) + 0.1 * (15.0 - t)


def _slow_sine(t):
    return jnp.sin(0.2 * t)


def _hold(t):
    return jnp.zeros_like(t)


PATHS: dict[str, Callable] = {
    "sine": _sine,
    "ramp": _ramp,
    "composite": _composite,
    "slow_sine": _slow_sine,
    "hold": _hold,
}
"""The paper's desired joint paths (rad) as functions of time (s), SPEC section 6."""


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Trajectory:
    """A desired motion on a time grid, with its nominal closed-loop response.

    Attributes:
        t: (T+1,) sample times ``t_k = k dt`` in s.
        q_d, qd_d, qdd_d: (T+1, n) desired positions (rad), velocities (rad/s)
            and accelerations (rad/s^2).
        u_d: (T+1, n) feed-forward ``qdd_d + Kd qd_d + Kp q_d``.
        x_n: (T+1, n, 2) nominal state ``(q_n, qd_n)`` per joint: the closed
            loop with ``gv = 0`` from ``x_n(0) = x_d(0)``.
        qdd_n: (T+1, n) nominal acceleration ``u_d - Kd qd_n - Kp q_n``.
        kp, kd: (n,) proportional (1/s^2) and derivative (1/s) gains.
        dt: the step in s (static).
        labels: a name per joint's path, for reports (static).
    """

    t: jax.Array
    q_d: jax.Array
    qd_d: jax.Array
    qdd_d: jax.Array
    u_d: jax.Array
    x_n: jax.Array
    qdd_n: jax.Array
    kp: jax.Array
    kd: jax.Array
    dt: float = dataclasses.field(metadata=dict(static=True))
    labels: tuple[str, ...] = dataclasses.field(default=(), metadata=dict(static=True))

    @property
    def n_joints(self) -> int:
        """Number of joints ``n``."""
        return self.u_d.shape[-1]

    @property
    def n_steps(self) -> int:
        """Number of steps ``T`` (there are ``T+1`` samples)."""
        return self.u_d.shape[-2] - 1

    @property
    def dtype(self):
        return self.u_d.dtype


@functools.partial(jax.jit, static_argnames=("dt",))
def _nominal(q_d, qd_d, qdd_d, kp, kd, dt):
    """Feed-forward, nominal state and nominal acceleration from desired samples."""
    u_d = feedforward(q_d, qd_d, qdd_d, kp[None, :], kd[None, :])

    def step(state, u):
        q, qd = state
        nxt = closed_loop_step(q, qd, u, 0.0, kp, kd, dt)
        return nxt, jnp.stack(nxt, axis=-1)

    _, rest = jax.lax.scan(step, (q_d[0], qd_d[0]), u_d[:-1])
    x_n = jnp.concatenate([jnp.stack([q_d[0], qd_d[0]], axis=-1)[None], rest], axis=0)
    qdd_n = servo_command(x_n[..., 0], x_n[..., 1], u_d, kp[None, :], kd[None, :])
    return u_d, x_n, qdd_n


def trajectory_from_samples(q_d, qd_d, qdd_d, *, dt, kp=100.0, kd=20.0, labels=None):
    """A :class:`Trajectory` from sampled desired positions, velocities, accelerations.

    Args:
        q_d, qd_d, qdd_d: (T+1, n) on the grid ``t_k = k dt``, in rad, rad/s, rad/s^2.
        dt: the step in s.
        kp, kd: gains, scalar or (n,); the discrete closed loop of every joint
            must be stable (spectral radius of ``A_i`` below 1).
        labels: optional name per joint's path.

    Raises:
        ValueError: on shape mismatches, NaN/inf samples, ``T < 1``, a
            non-positive ``dt`` or unstable gains.
    """
    q_d = _checks.numbers("q_d", q_d, None)
    if q_d.ndim != 2:
        raise ValueError(f"q_d must have shape (T+1, n), got shape {q_d.shape}")
    dtype = q_d.dtype if jnp.issubdtype(q_d.dtype, jnp.floating) else _checks.default_float()
    samples = {}
    for name, value in (("q_d", q_d), ("qd_d", qd_d), ("qdd_d", qdd_d)):
        samples[name] = _checks.float_array(name, value, q_d.shape, dtype=dtype)
    n_samples, n = q_d.shape
    if n_samples < 2:
        raise ValueError(f"q_d needs at least 2 samples (T >= 1), got {n_samples}")
    dt = _checks.real("dt", dt, positive=True, unit="s")
    kp = _checks.per_joint("kp", kp, n, dtype)
    kd = _checks.per_joint("kd", kd, n, dtype)
    _checks.check_stable(kp, kd, dt)
    u_d, x_n, qdd_n = _nominal(samples["q_d"], samples["qd_d"], samples["qdd_d"], kp, kd, dt)
    t = jnp.arange(n_samples, dtype=dtype) * jnp.asarray(dt, dtype)
    labels = tuple(labels) if labels is not None else ("samples",) * n
    if len(labels) != n:
        raise ValueError(f"labels has {len(labels)} entries for {n} joints")
    return Trajectory(
        t=t,
        q_d=samples["q_d"],
        qd_d=samples["qd_d"],
        qdd_d=samples["qdd_d"],
        u_d=u_d,
        x_n=x_n,
        qdd_n=qdd_n,
        kp=kp,
        kd=kd,
        dt=dt,
        labels=labels,
    )


def _resolve_path(path, joint):
    if isinstance(path, str):
        if path not in PATHS:
            raise ValueError(
                f"unknown path {path!r} for joint {joint}; choose one of "
                f"{sorted(PATHS)} or pass a function of time"
            )
        return path, PATHS[path]
    if callable(path):
        return getattr(path, "__name__", "custom"), path
    raise TypeError(
        f"paths[{joint}] must be a path name {sorted(PATHS)} or a function of time, got {path!r}"
    )


def _derivatives(fn, t):
    """Position, velocity and acceleration of a scalar path by forward-mode autodiff."""
    velocity = jax.grad(fn)
    acceleration = jax.grad(velocity)
    return jax.vmap(fn)(t), jax.vmap(velocity)(t), jax.vmap(acceleration)(t)


@functools.partial(jax.jit, static_argnames=("fn", "dtype"))
def _path_samples(t, *, fn, dtype):
    """:func:`_derivatives` of one path as one compiled program per (path, length, dtype).

    Run op by op, the three derivatives compiled a dozen small XLA programs per path and
    run length; a named path is a module-level function, so its program is reused by
    every trajectory of the same length.
    """
    return _derivatives(lambda s: jnp.asarray(fn(s), dtype), t)


def trajectory(
    paths: str | Callable | Sequence[str | Callable],
    *,
    duration: float = 15.0,
    dt: float = 0.01,
    kp=100.0,
    kd=20.0,
    dtype=None,
) -> Trajectory:
    """A :class:`Trajectory` from desired paths given by name or as functions of time.

    Args:
        paths: one entry per joint: a name from :data:`PATHS` (``"sine"``,
            ``"ramp"``, ``"composite"``, ``"slow_sine"``, ``"hold"``) or a
            function ``q_d(t) -> float`` in rad of a scalar time in s. A single
            name or function means a one-joint robot. Velocities and
            accelerations come from autodiff (exact, no finite differences).
        duration: length in s; ``T = round(duration / dt)`` steps.
        dt: the step in s.
        kp, kd: gains, scalar or one per joint.
        dtype: float dtype; default float64 when x64 is enabled, else float32.

    Raises:
        ValueError: unknown path names, a path that returns NaN/inf or not a
            scalar, a gain shape that does not match the number of paths,
            ``T < 1``, or unstable gains/step.
    """
    if isinstance(paths, str) or callable(paths):
        paths = [paths]
    if not isinstance(paths, (list, tuple)):
        raise TypeError(
            f"paths must be a path name {sorted(PATHS)}, a function of time, or a list of "
            f"them (one per joint), got {paths!r}"
        )
    paths = list(paths)
    if not paths:
        raise ValueError("paths must name at least one joint's path")
    dtype = _checks.float_dtype(dtype)
    dt = _checks.real("dt", dt, positive=True, unit="s")
    duration = _checks.real("duration", duration, positive=True, unit="s")
    n_steps = int(round(duration / dt))
    if n_steps < 1:
        raise ValueError(
            f"duration={duration!r} s with dt={dt!r} s gives {n_steps} steps; "
            "the trajectory needs at least one step"
        )
    t = jnp.arange(n_steps + 1, dtype=dtype) * jnp.asarray(dt, dtype)
    columns, labels = [], []
    for joint, path in enumerate(paths):
        label, fn = _resolve_path(path, joint)
        probe = jax.eval_shape(fn, jax.ShapeDtypeStruct((), dtype))
        if probe.shape != ():
            raise ValueError(
                f"paths[{joint}] must return a scalar angle for a scalar time, "
                f"got shape {probe.shape}"
            )
        columns.append(_path_samples(t, fn=fn, dtype=jnp.dtype(dtype)))
        labels.append(label)
    q_d, qd_d, qdd_d = (jnp.stack([c[i] for c in columns], axis=-1) for i in range(3))
    for name, value in (("q_d", q_d), ("qd_d", qd_d), ("qdd_d", qdd_d)):
        if not np.all(np.isfinite(np.asarray(value))):  # NumPy: no XLA program per shape
            raise ValueError(
                f"the desired path gives a non-finite {name}; check the functions "
                "passed in paths over [0, duration]"
            )
    n = len(paths)
    for name, gain in (("kp", kp), ("kd", kd)):
        if np.ndim(gain) not in (0,) and np.shape(gain) != (n,):
            raise ValueError(
                f"{name} has shape {np.shape(gain)} but paths has {n} joints: give a "
                f"scalar or one gain per joint"
            )
    return trajectory_from_samples(q_d, qd_d, qdd_d, dt=dt, kp=kp, kd=kd, labels=labels)


def _minimum_jerk(tau):
    """The rest-to-rest minimum-jerk profile ``s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5``
    and its first two derivatives in ``tau`` (zero velocity and acceleration at both ends)."""
    s = tau**3 * (10.0 + tau * (-15.0 + 6.0 * tau))
    ds = 30.0 * tau**2 * (1.0 - tau) ** 2
    dds = 60.0 * tau * (1.0 - tau) * (1.0 - 2.0 * tau)
    return s, ds, dds


def waypoint_trajectory(
    waypoints,
    *,
    times=None,
    segment_time: float = 2.0,
    dt: float = 0.01,
    kp=100.0,
    kd=20.0,
    dtype=None,
) -> Trajectory:
    """A smooth point-to-point move through joint-space waypoints (minimum jerk per segment).

    Each segment goes from waypoint ``i`` at ``times[i]`` to waypoint ``i+1`` at
    ``times[i+1]`` along the quintic ``q = q_i + (q_{i+1} - q_i) s(tau)``,
    ``s = 10 tau^3 - 15 tau^4 + 6 tau^5``: it starts and stops at rest (zero
    velocity and acceleration), as a pick-and-place move does. Repeat a
    waypoint to dwell there. Velocities and accelerations are analytic.

    Args:
        waypoints: (W, n) joint positions in rad (rad or m for prismatic joints), W >= 2.
        times: (W,) arrival times in s, strictly increasing from 0; default
            ``segment_time`` per segment.
        segment_time: s per segment when ``times`` is not given.
        dt: the step in s; the run lasts ``times[-1]``.
        kp, kd: gains, scalar or one per joint (the defaults are critically damped).
        dtype: float dtype; default float64 when x64 is enabled, else float32.

    Returns:
        A :class:`Trajectory` of ``T = round(times[-1] / dt)`` steps.

    Raises:
        ValueError: waypoints not (W >= 2, n) or not finite; times not (W,),
            not starting at 0 or not strictly increasing; a bad ``dt``.
    """
    dtype = dtype or _checks.default_float()
    if not _checks.is_concrete(waypoints):
        raise TypeError("waypoints must be concrete (build the trajectory outside jax.jit)")
    points = np.asarray(waypoints, dtype=np.float64)
    if points.ndim != 2 or points.shape[0] < 2:
        raise ValueError(
            f"waypoints must have shape (W, n) with W >= 2 points, got shape {points.shape}"
        )
    if not np.all(np.isfinite(points)):
        raise ValueError("waypoints contain NaN or inf; give finite joint positions in rad")
    if times is None:
        if not (np.isfinite(segment_time) and segment_time > 0):
            raise ValueError(f"segment_time must be a positive time in s, got {segment_time!r}")
        times = float(segment_time) * np.arange(points.shape[0])
    times = np.asarray(times, dtype=np.float64)
    if times.shape != (points.shape[0],):
        raise ValueError(
            f"times has shape {times.shape} but there are {points.shape[0]} waypoints: "
            "give one arrival time per waypoint"
        )
    if not np.all(np.isfinite(times)) or times[0] != 0.0 or np.any(np.diff(times) <= 0):
        raise ValueError(
            f"times must start at 0 and increase strictly (one arrival time per waypoint, "
            f"in s), got {times.tolist()}"
        )
    dt = float(dt)
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive finite step in s, got {dt!r}")
    n_steps = int(round(times[-1] / dt))
    if n_steps < 1:
        raise ValueError(f"the move lasts {times[-1]!r} s, less than one step dt={dt!r} s")
    t = np.arange(n_steps + 1) * dt
    segment = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    length = times[segment + 1] - times[segment]
    tau = np.clip((t - times[segment]) / length, 0.0, 1.0)
    s, ds, dds = _minimum_jerk(tau)
    delta = points[segment + 1] - points[segment]  # (T+1, n)
    q_d = points[segment] + delta * s[:, None]
    qd_d = delta * (ds / length)[:, None]
    qdd_d = delta * (dds / length**2)[:, None]
    labels = tuple(f"waypoints[{j}]" for j in range(points.shape[1]))
    return trajectory_from_samples(
        *(jnp.asarray(x, dtype) for x in (q_d, qd_d, qdd_d)), dt=dt, kp=kp, kd=kd, labels=labels
    )
