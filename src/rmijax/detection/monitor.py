"""An online fault monitor for a control loop: a pure ``(init, update)`` pair.

In the style of optax's ``GradientTransformation``: :func:`monitor` closes over
the robot, gains and settings and returns two pure functions. The state is a
pytree of fixed-size buffers (the last ``window`` feed-forward values, nominal
states and nominal accelerations), so it can be carried through ``lax.scan``,
``jit``-ed and ``vmap``-ed over many robots, and its memory does not grow with
the run. Tick ``k``'s bounds are RMI's end step ``k``: they use the
feed-forward up to tick ``k-1`` and equal :func:`rmijax.rmi` at every tick.

With ``method="short_window"`` the state also buffers the last ``window``
readings: tick ``k``'s window starts from the reading of tick
``k0 = max(0, k - N)``, and the bounds equal
:func:`rmijax.methods.short_window.short_window_bounds` at every tick.

For a planned motion whose band was computed beforehand (for example
``certified``, whose band covers the whole run and is too costly to compute
tick by tick), :func:`monitor_from_bounds` streams that band with the same
alarm rule; its alarms equal :func:`rmijax.detect` on the band.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from rmijax import _checks
from rmijax.control import closed_loop_step, feedforward, servo_command
from rmijax.methods.base import Bounds
from rmijax.methods.rmi import MODES, check_memory, window_constants, window_extremes
from rmijax.methods.short_window import start_error_bounds, transition_powers
from rmijax.robots.box import UncertainRobot, uncertain_indices
from rmijax.robots.check import check_model

__all__ = [
    "METHODS",
    "BandMonitorState",
    "Monitor",
    "MonitorOutput",
    "MonitorState",
    "monitor",
    "monitor_from_bounds",
]

METHODS = ("rmi", "short_window")
"""Bound methods the monitor can run: exact RMI, and short windows from the readings."""

DEFAULT_WINDOWS = {"rmi": 100, "short_window": 2}
"""The window ``N`` (ticks) of each method when ``window`` is not given."""


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class MonitorState:
    """What the monitor carries from tick to tick (all fixed-size arrays).

    Attributes:
        tick: the next tick ``k`` (int32).
        x_nominal: (n, 2) nominal state ``x_n(k)``.
        x_first: (n, 2) ``x_n(0)``, the window start while ``k <= N``.
        u_buffer: (N, n) ``u_d(k-N .. k-1)``, zeros before the run.
        x_buffer: (N, n, 2) ``x_n(k-N .. k-1)``.
        qdd_buffer: (N, n) ``qdd_n(k-N .. k-1)``.
        y_buffer: (N, n, 2) readings ``y(k-N .. k-1)`` (``short_window``;
            zeros before the run), (0, n, 2) for ``rmi``.
        y_first: (n, 2) the reading of tick 0, the window start while
            ``k <= N`` (``short_window``; zeros for ``rmi``).
        run_length: (n, 2) int32 consecutive out-of-band ticks per output.
        first_alarm: int32 tick of the first alarm so far, -1 if none.
        invalid_left: int32 ticks still flagged ``desired_invalid`` after a
            non-finite desired sample (0 when none is in the window).
    """

    tick: jax.Array
    x_nominal: jax.Array
    x_first: jax.Array
    u_buffer: jax.Array
    x_buffer: jax.Array
    qdd_buffer: jax.Array
    y_buffer: jax.Array
    y_first: jax.Array
    run_length: jax.Array
    first_alarm: jax.Array
    invalid_left: jax.Array


class MonitorOutput(NamedTuple):
    """One tick's verdict. Shapes (n, 2): ``[..., 0]`` encoder, ``[..., 1]`` tachometer.

    Attributes:
        lower, upper: the bounds for this tick (rad, rad/s).
        nominal: the nominal output ``c x_n(k)``.
        alarm: bool, outside its band (by more than ``tol``) for
            ``persistence`` consecutive ticks.
        outside: bool, outside its band at this tick (no persistence).
        nan_reading: bool, the reading was NaN (counts as outside).
        first_alarm: int32 tick of the first alarm so far, -1 if none.
        tick: int32 this tick ``k``.
        desired_invalid: bool scalar, a desired sample (``q_d``, ``qd_d``,
            ``qdd_d``) of this tick or of the last ``window`` ticks was NaN/inf
            (only possible inside ``jit``; outside it is refused). The bounds
            are then NaN and nothing alarms: the monitor cannot know what the
            controller did; it is its own condition, not a fault. The
            non-finite sample's feed-forward is replaced by the previous tick's
            so the nominal stays finite, and the flag clears once the window
            has passed the sample.
    """

    lower: jax.Array
    upper: jax.Array
    nominal: jax.Array
    alarm: jax.Array
    outside: jax.Array
    nan_reading: jax.Array
    first_alarm: jax.Array
    tick: jax.Array
    desired_invalid: jax.Array


class Monitor(NamedTuple):
    """The pure functions of a monitor (see :func:`monitor`)."""

    init: callable
    update: callable


def monitor(
    params: UncertainRobot,
    *,
    kp=100.0,
    kd=20.0,
    dt: float = 0.01,
    method: str = "rmi",
    mode: str = "coupled",
    window: int | None = None,
    noise_lo=0.0,
    noise_hi=0.0,
    persistence: int = 1,
    tol: float = 1e-9,
) -> Monitor:
    """An online fault monitor: ``init(q_d0, qd_d0)`` and ``update(state, desired, y_meas)``.

    Args:
        params: the robot and its parameter box.
        kp, kd: the controller's gains, scalar or (n,).
        dt: the tick in s.
        method: ``"rmi"`` (exhaustive corners, the exact paper algorithm) or
            ``"short_window"`` (the paper's section 4: each window starts
            from the reading ``N`` ticks back; see
            :func:`rmijax.methods.short_window.short_window_bounds`). Inside ``jit``
            a NaN reading used as a window start makes the bounds of the
            ticks that start from it NaN, so every output alarms there.
        mode: ``"coupled"`` (default) or ``"per_joint"``.
        window: window ``N`` in ticks; default 100 for ``rmi``, 2 for
            ``short_window`` (:data:`DEFAULT_WINDOWS`).
        noise_lo, noise_hi: sensor noise bounds, scalar, (2,) or (n, 2).
            ``short_window`` also widens its bounds by their effect on the
            window start.
        persistence: consecutive out-of-band ticks for an alarm.
        tol: how far outside a band a reading must be.

    Returns:
        A :class:`Monitor`. ``update`` takes ``desired = (q_d, qd_d, qdd_d)``
        at this tick, (n,) each, and ``y_meas`` (n, 2), and returns
        ``(state, MonitorOutput)``.

    Example::

        mon = rmijax.monitor(rmijax.paper_arm2())
        state = mon.init(q_d[0], qd_d[0])
        step = jax.jit(mon.update)
        for k in range(T + 1):
            state, out = step(state, (q_d[k], qd_d[k], qdd_d[k]), y_meas[k])
    """
    if not isinstance(params, UncertainRobot):
        raise TypeError(f"params must be a rmijax.UncertainRobot, got {type(params).__name__}")
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; the monitor runs {METHODS}")
    if mode not in MODES:
        raise ValueError(f"unknown mode {mode!r}; choose one of {MODES}")
    window = DEFAULT_WINDOWS[method] if window is None else window
    window = _checks.positive_int("window", window, "ticks")
    persistence = _checks.positive_int("persistence", persistence)
    tol = _checks.tolerance(tol)
    n, dtype = params.n_joints, params.dtype
    dt = _checks.real("dt", dt, positive=True, unit="s")
    kp = _checks.per_joint("kp", kp, n, dtype)
    kd = _checks.per_joint("kd", kd, n, dtype)
    _checks.check_stable(kp, kd, dt)
    lo, hi = _checks.noise_interval(noise_lo, noise_hi, n, dtype)
    check_model(params)
    check_memory(params, mode=mode, window=window)  # one tick holds one end step's window
    consts = window_constants(params, kp, kd, dt, window, uncertain=uncertain_indices(params))
    model = params.model
    measured_start = method == "short_window"
    if measured_start:
        error_lo, error_hi = start_error_bounds(transition_powers(kp, kd, dt, window), lo, hi)
    readings_kept = window if measured_start else 0

    def init(q_d0, qd_d0) -> MonitorState:
        q0 = _checks.float_array("q_d0", q_d0, (n,), dtype=dtype)
        qd0 = _checks.float_array("qd_d0", qd_d0, (n,), dtype=dtype)
        x0 = jnp.stack([q0, qd0], axis=-1)
        return MonitorState(
            tick=jnp.zeros((), jnp.int32),
            x_nominal=x0,
            x_first=x0,
            u_buffer=jnp.zeros((window, n), dtype),
            x_buffer=jnp.zeros((window, n, 2), dtype),
            qdd_buffer=jnp.zeros((window, n), dtype),
            y_buffer=jnp.zeros((readings_kept, n, 2), dtype),
            y_first=jnp.zeros((n, 2), dtype),
            run_length=jnp.zeros((n, 2), jnp.int32),
            first_alarm=jnp.full((), -1, jnp.int32),
            invalid_left=jnp.zeros((), jnp.int32),
        )

    def update(state: MonitorState, desired, y_meas):
        q_d, qd_d, qdd_d = desired
        for name, value in (("q_d", q_d), ("qd_d", qd_d), ("qdd_d", qdd_d)):
            if jnp.shape(value) != (n,):
                raise ValueError(f"desired {name} must have shape ({n},), got {jnp.shape(value)}")
        if jnp.shape(y_meas) != (n, 2):
            raise ValueError(f"y_meas must have shape ({n}, 2), got {jnp.shape(y_meas)}")
        for name, value in (("q_d", q_d), ("qd_d", qd_d), ("qdd_d", qdd_d)):
            if _checks.is_concrete(value) and not bool(jnp.all(jnp.isfinite(value))):
                raise ValueError(
                    f"desired {name} contains NaN/inf at tick {int(state.tick)}: the monitor "
                    "cannot know what the controller did with it. Fix the desired path "
                    "(inside jit such a sample sets desired_invalid for the next window)"
                )
        if _checks.is_concrete(y_meas) and not bool(jnp.all(jnp.isfinite(y_meas))):
            raise ValueError(
                "y_meas contains NaN/inf; outside jit the monitor refuses it (inside jit a "
                "NaN reading raises the alarm of its output)"
            )
        k = state.tick
        y = jnp.asarray(y_meas, dtype)

        # Bounds of end step k: the window k-N .. k-1 is what the buffers hold.
        active = (k - window + jnp.arange(window)) >= 0
        x_start = jnp.where(k >= window, state.x_buffer[0], state.x_first)
        if measured_start:  # short_window: from the reading of tick max(0, k - N)
            y_first = jnp.where(k == 0, y, state.y_first)
            x_start = jnp.where(k >= window, state.y_buffer[0], y_first)
        extremes = window_extremes(
            state.u_buffer,
            state.x_buffer,
            state.qdd_buffer,
            active,
            x_start,
            consts,
            model=model,
            mode=mode,
            dt=dt,
        )
        if measured_start:  # widened by the start reading's noise over t_f - k0 steps
            steps = jnp.minimum(k, window)
            upper = extremes[0] + (hi + error_hi[steps])
            lower = extremes[1] + (lo + error_lo[steps])
        else:
            upper, lower = extremes[0] + hi, extremes[1] + lo

        # A non-finite desired sample (possible inside jit only) flags this tick
        # and the next ``window`` ticks, whose windows hold it: no bounds, no alarm.
        desired_ok = jnp.all(
            jnp.stack([jnp.all(jnp.isfinite(jnp.asarray(d))) for d in (q_d, qd_d, qdd_d)])
        )
        invalid_left = jnp.where(desired_ok, state.invalid_left, window + 1)
        desired_invalid = invalid_left > 0
        upper = jnp.where(desired_invalid, jnp.nan, upper)
        lower = jnp.where(desired_invalid, jnp.nan, lower)

        # Detection with persistence; NaN is outside.
        nan_reading = jnp.isnan(y)
        inside = (y >= lower - tol) & (y <= upper + tol)
        outside = ~inside & ~desired_invalid
        run_length = jnp.where(outside, state.run_length + 1, 0)
        alarm = run_length >= persistence
        first_alarm = jnp.where(
            (state.first_alarm < 0) & jnp.any(alarm), k, state.first_alarm
        ).astype(jnp.int32)

        # Advance the nominal closed loop and the buffers by this tick.
        x_nom = state.x_nominal
        u = feedforward(
            jnp.asarray(q_d, dtype), jnp.asarray(qd_d, dtype), jnp.asarray(qdd_d, dtype), kp, kd
        )
        u = jnp.where(desired_ok, u, state.u_buffer[-1])  # hold: the nominal stays finite
        qdd_nom = servo_command(x_nom[:, 0], x_nom[:, 1], u, kp, kd)
        nxt = jnp.stack(closed_loop_step(x_nom[:, 0], x_nom[:, 1], u, 0.0, kp, kd, dt), -1)
        new_state = MonitorState(
            tick=k + 1,
            x_nominal=nxt,
            x_first=state.x_first,
            u_buffer=jnp.concatenate([state.u_buffer[1:], u[None]], axis=0),
            x_buffer=jnp.concatenate([state.x_buffer[1:], x_nom[None]], axis=0),
            qdd_buffer=jnp.concatenate([state.qdd_buffer[1:], qdd_nom[None]], axis=0),
            y_buffer=(
                jnp.concatenate([state.y_buffer[1:], y[None]], axis=0)
                if measured_start
                else state.y_buffer
            ),
            y_first=y_first if measured_start else state.y_first,
            run_length=run_length.astype(jnp.int32),
            first_alarm=first_alarm,
            invalid_left=jnp.maximum(invalid_left - 1, 0).astype(jnp.int32),
        )
        output = MonitorOutput(
            lower=lower,
            upper=upper,
            nominal=x_nom,
            alarm=alarm,
            outside=outside,
            nan_reading=nan_reading,
            first_alarm=first_alarm,
            tick=k,
            desired_invalid=desired_invalid,
        )
        return new_state, output

    return Monitor(init=init, update=update)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class BandMonitorState:
    """What :func:`monitor_from_bounds` carries from tick to tick.

    Attributes:
        tick: the next tick ``k`` (int32).
        run_length: (n, 2) int32 consecutive out-of-band ticks per output.
        first_alarm: int32 tick of the first alarm so far, -1 if none.
    """

    tick: jax.Array
    run_length: jax.Array
    first_alarm: jax.Array


def monitor_from_bounds(bounds: Bounds, *, persistence: int = 1, tol: float = 1e-9) -> Monitor:
    """Stream a precomputed band of a planned motion: ``init`` and ``update`` as :func:`monitor`.

    Tick ``k`` compares the reading with ``bounds.lower[k]``, ``bounds.upper[k]``
    under the same rule as :func:`monitor` and :func:`rmijax.detect` (outside by
    more than ``tol``, NaN counts as outside, ``persistence`` consecutive ticks),
    so the streamed alarms equal ``detect(y_meas, bounds, persistence=..., tol=...)``
    tick by tick. The band must belong to the motion being run (the same desired
    path, gains and ``dt``); nothing here can check that.

    Args:
        bounds: the band, ``lower``, ``upper``, ``nominal`` of shape (T+1, n, 2),
            e.g. from ``rmijax.bounds(traj, params, method="certified")``.
        persistence: consecutive out-of-band ticks for an alarm.
        tol: how far outside a band a reading must be.

    Returns:
        A :class:`Monitor`: ``init(q_d0=None, qd_d0=None)`` (the arguments are
        accepted for drop-in use and ignored) and ``update(state, desired,
        y_meas)`` with ``y_meas`` (n, 2); ``desired`` is accepted and ignored
        (the band already holds the motion). Returns ``(state, MonitorOutput)``.
        Past the band's last tick ``T`` there is no band: outside ``jit`` that
        is refused, inside it the bounds are NaN and every output alarms.

    Example::

        band = rmijax.bounds(traj, params, method="certified")
        mon = rmijax.monitor_from_bounds(band)
        state = mon.init()
        for k in range(T + 1):
            state, out = mon.update(state, None, y_meas[k])
    """
    if not isinstance(bounds, Bounds):
        raise TypeError(
            f"bounds must be a rmijax.Bounds (from rmijax.bounds), got {type(bounds).__name__}"
        )
    lower, upper, nominal = (jnp.asarray(a) for a in (bounds.lower, bounds.upper, bounds.nominal))
    if lower.ndim != 3 or lower.shape[-1] != 2 or upper.shape != lower.shape:
        raise ValueError(
            f"bounds must hold a whole run, lower and upper of shape (T+1, n, 2), got "
            f"{lower.shape} and {upper.shape}"
        )
    persistence = _checks.positive_int("persistence", persistence)
    tol = _checks.tolerance(tol)
    last, n = lower.shape[0] - 1, lower.shape[1]

    def init(q_d0=None, qd_d0=None) -> BandMonitorState:
        return BandMonitorState(
            tick=jnp.zeros((), jnp.int32),
            run_length=jnp.zeros((n, 2), jnp.int32),
            first_alarm=jnp.full((), -1, jnp.int32),
        )

    def update(state: BandMonitorState, desired, y_meas):
        if jnp.shape(y_meas) != (n, 2):
            raise ValueError(f"y_meas must have shape ({n}, 2), got {jnp.shape(y_meas)}")
        k = state.tick
        if _checks.is_concrete(k) and int(k) > last:
            raise ValueError(
                f"tick {int(k)} is past the band's last tick {last}: the planned motion is over"
            )
        planned = k <= last
        row = jnp.minimum(k, last)
        low = jnp.where(planned, lower[row], jnp.nan)
        high = jnp.where(planned, upper[row], jnp.nan)
        y = jnp.asarray(y_meas, lower.dtype)
        nan_reading = jnp.isnan(y)
        outside = ~((y >= low - tol) & (y <= high + tol))
        run_length = jnp.where(outside, state.run_length + 1, 0).astype(jnp.int32)
        alarm = run_length >= persistence
        first_alarm = jnp.where(
            (state.first_alarm < 0) & jnp.any(alarm), k, state.first_alarm
        ).astype(jnp.int32)
        output = MonitorOutput(
            lower=low,
            upper=high,
            nominal=jnp.where(planned, nominal[row], jnp.nan),
            alarm=alarm,
            outside=outside,
            nan_reading=nan_reading,
            first_alarm=first_alarm,
            tick=k,
            desired_invalid=jnp.zeros((), bool),
        )
        return BandMonitorState(k + 1, run_length, first_alarm), output

    return Monitor(init=init, update=update)
