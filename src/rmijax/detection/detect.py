"""Fault detection with bounds, the paper's constant-threshold baseline, containment metrics.

SPEC section 7: an alarm at step ``k`` when a measured output lies outside its
``[lower, upper]`` by more than ``tol``, for ``persistence`` consecutive steps.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from rmijax import _checks
from rmijax.methods.base import Bounds

__all__ = [
    "Detection",
    "containment",
    "detect",
]

SENSORS = ("encoder", "tachometer")


@dataclasses.dataclass(frozen=True)
class Detection:
    """What a detector saw in one run. Times in s; outputs as ``(joint, sensor)``, 0-based.

    Attributes:
        first_alarm: time of the first alarm in the run, or None.
        latency: first alarm at or after ``onset`` minus ``onset``, or None
            (no onset given, or no alarm after it).
        false_alarms: number of alarm steps before ``onset`` (the whole run
            when there is no onset).
        alarm_output: the output that raised the first alarm at or after the
            onset (the first alarm overall when there is no onset), or None.
        true_exit: when the true state first leaves the bounds at or after the
            onset (0 without onset), if ``x_true`` was given; else None.
        true_exit_output: the output whose true state left first, or None.
        alarms: (T+1, n, 2) bool, per output, persistence applied.
        onset: the fault onset in s, or None.
    """

    first_alarm: float | None
    latency: float | None
    false_alarms: int
    alarm_output: tuple[int, int] | None
    true_exit: float | None
    true_exit_output: tuple[int, int] | None
    alarms: np.ndarray
    onset: float | None

    @property
    def detected(self) -> bool:
        """True when an alarm was raised at or after the onset."""
        return self.latency is not None

    def describe_output(self, output) -> str:
        """``"joint 2 encoder"`` (1-based joint, as the paper counts)."""
        if output is None:
            return "-"
        return f"joint {output[0] + 1} {SENSORS[output[1]]}"

    def summary(self) -> str:
        """One line for reports."""
        parts = [f"first alarm {_fmt(self.first_alarm)}"]
        if self.onset is not None:
            parts.append(f"latency {_fmt(self.latency)}")
        parts.append(f"false alarms {self.false_alarms}")
        parts.append(f"by {self.describe_output(self.alarm_output)}")
        if self.true_exit is not None or self.true_exit_output is not None:
            parts.append(f"true state leaves at {_fmt(self.true_exit)}")
        return ", ".join(parts)


def _fmt(seconds):
    return "none" if seconds is None else f"{seconds:.2f} s"


def _outside(values, bounds, tol):
    """(T+1, n, 2) bool: outside ``[lower - tol, upper + tol]``; NaN counts as outside."""
    lower, upper = np.asarray(bounds.lower), np.asarray(bounds.upper)
    inside = (values >= lower - tol) & (values <= upper + tol)
    return ~inside


def _persist(outside, persistence):
    """Alarm where the output has been outside for ``persistence`` consecutive steps."""
    run = np.zeros(outside.shape[1:], dtype=np.int64)
    alarms = np.zeros_like(outside)
    for k in range(outside.shape[0]):
        run = np.where(outside[k], run + 1, 0)
        alarms[k] = run >= persistence
    return alarms


def _first(mask, start):
    """First step >= start where any output is set, and that output (lowest index)."""
    hits = np.flatnonzero(mask[start:].reshape(mask.shape[0] - start, -1).any(axis=1))
    if hits.size == 0:
        return None, None
    step = start + int(hits[0])
    joint, sensor = (int(v) for v in np.argwhere(mask[step])[0])
    return step, (joint, sensor)


def detect(
    y_meas,
    bounds: Bounds,
    *,
    onset: float | None = None,
    persistence: int = 1,
    tol: float = 1e-9,
    x_true=None,
    dt: float | None = None,
) -> Detection:
    """Compare measured outputs with bounds and report alarms (SPEC section 7).

    Args:
        y_meas: (T+1, n, 2) readings, ``[..., 0]`` encoder (rad), ``[..., 1]``
            tachometer (rad/s). A NaN reading counts as outside.
        bounds: from :func:`rmijax.rmi` or :func:`empirical_thresholds`.
        onset: fault onset in s, or None for a fault-free run.
        persistence: consecutive out-of-band steps needed for an alarm (>= 1).
        tol: how far outside a band a reading must be.
        x_true: optional (T+1, n, 2) true states, for ``true_exit``.
        dt: the step in s; defaults to ``bounds.dt``.

    Returns:
        A :class:`Detection`.
    """
    _check_bounds(bounds)
    lower = np.asarray(bounds.lower)
    y = np.asarray(_checks.numbers("y_meas", y_meas, None), dtype=np.float64)
    if lower.ndim != 3 or y.shape != lower.shape:
        raise ValueError(
            f"y_meas must have the bounds' shape {lower.shape} (T+1, n, 2), got {y.shape}"
        )
    if dt is None and bounds.dt is None:
        raise ValueError("these bounds carry no step: pass dt= (s)")
    dt = bounds.dt if dt is None else _checks.real("dt", dt, positive=True, unit="s")
    if bounds.dt is not None and not np.isclose(dt, bounds.dt, rtol=1e-9, atol=0.0):
        raise ValueError(
            f"dt={dt!r} s disagrees with the step of the bounds ({bounds.dt!r} s); leave dt "
            "out to use the bounds' own step"
        )
    persistence = _checks.positive_int("persistence", persistence)
    tol = _checks.tolerance(tol)
    n_samples = y.shape[0]
    start = 0
    if onset is not None:
        onset = _checks.real("onset", onset, minimum=0, unit="s")
        start = int(round(onset / dt))
        if not 0 <= start < n_samples:
            raise ValueError(
                f"onset {onset!r} s is outside the run [0, {(n_samples - 1) * dt:g}] s"
            )
    alarms = _persist(_outside(y, bounds, tol), persistence)
    any_alarm = alarms.reshape(n_samples, -1).any(axis=1)
    first_step, first_output = _first(alarms, 0)
    if onset is None:
        false_alarms = int(any_alarm.sum())
        latency, alarm_output = None, first_output
    else:
        false_alarms = int(any_alarm[:start].sum())
        step, alarm_output = _first(alarms, start)
        latency = None if step is None else (step - start) * dt
    true_exit = true_exit_output = None
    if x_true is not None:
        x = np.asarray(x_true, dtype=np.float64)
        if x.shape != y.shape:
            raise ValueError(f"x_true must have shape {y.shape}, got {x.shape}")
        step, true_exit_output = _first(_outside(x, bounds, tol), start)
        true_exit = None if step is None else step * dt
    return Detection(
        first_alarm=None if first_step is None else first_step * dt,
        latency=latency,
        false_alarms=false_alarms,
        alarm_output=alarm_output,
        true_exit=true_exit,
        true_exit_output=true_exit_output,
        alarms=alarms,
        onset=onset,
    )


def _check_bounds(bounds):
    if not isinstance(bounds, Bounds):
        raise TypeError(
            "bounds must be a rmijax.Bounds (from rmijax.rmi or rmijax.bounds), got "
            f"{type(bounds).__name__}"
        )


def containment(states, bounds: Bounds, *, tol: float = 1e-9) -> dict:
    """How well bands contain runs of the true plant (SPEC section 7).

    Args:
        states: (R, T+1, n, 2) or (T+1, n, 2) true states (or fault-free readings).
        bounds: the bands, (T+1, n, 2).

    Returns:
        ``inside``: fraction of (run, step, output) samples inside;
        ``clean_runs``: fraction of runs with no violation;
        ``worst``: worst violation as a fraction of the band width (where the
        width is > 0); ``runs``: R.
    """
    _check_bounds(bounds)
    tol = _checks.tolerance(tol)
    x = np.asarray(_checks.numbers("states", states, None), dtype=np.float64)
    if x.ndim == 3:
        x = x[None]
    if x.ndim != 4 or x.shape[1:] != np.shape(bounds.lower):
        raise ValueError(
            f"states must have shape (R, T+1, n, 2) or (T+1, n, 2) matching the bounds "
            f"{np.shape(bounds.lower)}, got {np.shape(states)}"
        )
    lower = np.asarray(bounds.lower, np.float64)[None]
    upper = np.asarray(bounds.upper, np.float64)[None]
    violation = np.maximum(np.maximum(lower - x, x - upper), 0.0)
    violation = np.where(np.isnan(violation), np.inf, violation)
    inside = violation <= tol
    width = np.broadcast_to(upper - lower, x.shape)
    relative = np.where(width > 0, violation / np.where(width > 0, width, 1.0), 0.0)
    return {
        "inside": float(inside.mean()),
        "clean_runs": float(inside.reshape(x.shape[0], -1).all(axis=1).mean()),
        "worst": float(relative.max()),
        "runs": int(x.shape[0]),
    }
