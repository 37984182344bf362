"""A recorded run on the controller's grid: the :class:`Log`, resampling and its checks.

Every reader (:mod:`rmijax.io.tables` for CSV and NPZ, :mod:`rmijax.io.ros` for
ROS 1 and ROS 2 bags) hands :func:`assemble` two time series in the log's own
clock: the controller's *reference* (desired ``q_d``, ``qd_d`` and optionally
``qdd_d`` per joint) and the *readings* (measured ``q``, ``qd``). They are put
on the grid ``t_k = t_0 + k dt`` of the controller as follows:

- the grid spans the time both series cover: ``t_0`` is the later of their
  first stamps, the end the earlier of their last stamps (what lies outside is
  counted in ``Log.source["trimmed_s"]``);
- the reference is interpolated linearly in time (exact when it was logged on
  the grid); a missing ``qdd_d`` is the central finite difference of the
  interpolated ``qd_d`` (``np.gradient``), and ``Log.source["derived"]`` says so;
- readings are *held* (default, ``reading_rule="hold"``: the latest reading at
  or before ``t_k``, what the controller had at that tick) or taken from the
  *nearest* stamp (``reading_rule="nearest"``). Stamps within ``1e-6 dt`` of a
  grid point count as on it.
- Readings more than ``1.5 dt`` apart are reported in ``Log.gaps``; a gap
  longer than ``max_gap`` (default ``10 dt``) is an error, in either series.

Nothing is dropped silently: non-monotonic or duplicate stamps, a reference
with NaN, joints the robot does not have (or robot joints missing from the
log), too short an overlap and positions that cannot be radians for this robot
(beyond its joint limits by more than ``limit_margin``) raise
:class:`LogError`. A NaN *reading* is kept: it lands in ``Log.nan`` and alarms,
as a NaN reading always does in :func:`rmijax.detect`.
"""

from __future__ import annotations

import dataclasses
import pathlib
import re

import numpy as np

from rmijax.robots.box import UncertainRobot
from rmijax.trajectory import Trajectory, trajectory_from_samples

__all__ = [
    "DEFAULT_POSITION_LIMIT",
    "READING_RULES",
    "Log",
    "LogError",
    "assemble",
    "joint_limits",
    "joint_names",
    "resolve_robot",
    "robot_joint_names",
]

READING_RULES = ("hold", "nearest")
"""How readings go onto the grid: the last one at or before ``t_k``, or the nearest one."""

DEFAULT_POSITION_LIMIT = 100.0
"""|q| (rad) beyond which a position cannot be right for a robot that declares no limits."""

_ON_GRID = 1e-6  # stamps within this fraction of dt of a grid point are on it


class LogError(ValueError):
    """A log that cannot be read as a run of this robot; the message says what and where."""


@dataclasses.dataclass(frozen=True)
class Log:
    """A recorded run resampled onto the controller's grid.

    Attributes:
        traj: the desired motion on the grid (``traj.t`` starts at 0), with
            the controller's gains and step: what :func:`rmijax.rmi` takes.
        robot: the :class:`~rmijax.UncertainRobot` the log was read for.
        readings: (T+1, n, 2) measured encoder (rad) and tachometer (rad/s);
            NaN where the log has a NaN sample.
        time: (T+1,) the grid in the log's own clock, s.
        joint_names: the robot's joint names, in the robot's order.
        gaps: ``(start, end)`` log times (s) of intervals between consecutive
            readings longer than ``1.5 dt``.
        nan: (T+1, n, 2) bool, readings that are NaN.
        source: where it came from and how it was read: ``path``, ``format``,
            ``topics`` (bags), ``reading_rule``, ``derived`` (quantities not in
            the log), ``ignored`` (log columns or joints not used),
            ``trimmed_s`` (time cut at either end), ``samples`` per series.
    """

    traj: Trajectory
    robot: UncertainRobot
    readings: np.ndarray
    time: np.ndarray
    joint_names: tuple[str, ...]
    gaps: tuple[tuple[float, float], ...]
    nan: np.ndarray
    source: dict

    @property
    def dt(self) -> float:
        """The grid step in s."""
        return self.traj.dt

    @property
    def n_steps(self) -> int:
        """Number of steps ``T``."""
        return self.traj.n_steps

    @property
    def nan_samples(self) -> int:
        """Number of NaN readings (sample x joint x sensor)."""
        return int(self.nan.sum())


# --------------------------------------------------------------------------
# The robot: a name or an UncertainRobot; its joint names and limits
# --------------------------------------------------------------------------

_PRESET = re.compile(r"^preset_?(\d+)$")


def resolve_robot(robot) -> UncertainRobot:
    """An :class:`~rmijax.UncertainRobot` from itself or a name.

    Names: ``"paper_pendulum"``, ``"paper_arm2"``, ``"preset<n>"`` (the
    ``n``-link planar preset), the real arms :func:`rmijax.load_robot` ships
    (``"panda"``, ``"iiwa14"``, ``"ur5e"``) or the path of a URDF/MJCF file,
    loaded with its box :func:`rmijax.robots.loaders.default_box`; for another box pass your own
    ``rmijax.load_robot(name, mass=..., payload=..., friction=...)``.

    Raises:
        ValueError: an unknown name (the message lists the known ones).
        TypeError: neither a name nor an UncertainRobot.
    """
    from rmijax.robots import planar
    from rmijax.robots.loaders import SHIPPED, default_box, load_robot

    if isinstance(robot, UncertainRobot):
        return robot
    if isinstance(robot, pathlib.Path):
        robot = str(robot)
    if not isinstance(robot, str):
        raise TypeError(
            f"robot must be a rmijax.UncertainRobot or a robot name, got {type(robot).__name__}"
        )
    name = robot.strip()
    if name in ("paper_pendulum", "paper_arm2"):
        return getattr(planar, name)()
    match = _PRESET.match(name)
    if match:
        return planar.preset_arm(int(match.group(1)))
    try:
        return load_robot(name, **default_box(name))
    except (ValueError, KeyError, FileNotFoundError) as err:
        raise ValueError(
            f"unknown robot {name!r}: {err}; give 'paper_pendulum', 'paper_arm2', "
            f"'preset<n>' (n links), a shipped arm {SHIPPED}, a URDF/MJCF path or a "
            "rmijax.UncertainRobot"
        ) from err


def robot_joint_names(robot) -> tuple[str, ...]:
    """Joint names of a robot given as in :func:`resolve_robot`.

    A real arm's name (or URDF/MJCF path) gives its chain's joint names
    (:func:`rmijax.robots.loaders.load_chain`); anything else :func:`joint_names`.
    """
    params = resolve_robot(robot)  # unknown names are refused here, with the known ones
    name = str(robot).strip() if isinstance(robot, (str, pathlib.Path)) else None
    planar = name is None or _PRESET.match(name) or name in ("paper_pendulum", "paper_arm2")
    if not planar:
        from rmijax.robots.loaders import load_chain

        return tuple(load_chain(name).joint_names)
    return joint_names(params)


def joint_names(params: UncertainRobot) -> tuple[str, ...]:
    """The robot's joint names: those its model declares, else ``joint1..jointn``."""
    for owner in (params, params.model, getattr(params.model, "structure", None)):
        names = getattr(owner, "joint_names", None)
        if names:
            names = tuple(str(v) for v in names)
            if len(names) == params.n_joints:
                return names
    return tuple(f"joint{i + 1}" for i in range(params.n_joints))


def joint_limits(params: UncertainRobot):
    """``(lower, upper)`` position limits (n,) in rad that the robot declares, or None."""
    for owner in (params, params.model, getattr(params.model, "structure", None)):
        limits = getattr(owner, "joint_limits", None)
        if limits is None:
            continue
        lower, upper = (np.asarray(v, np.float64).reshape(-1) for v in limits)
        if lower.shape == upper.shape == (params.n_joints,):
            return lower, upper
    return None


# --------------------------------------------------------------------------
# Checks of the raw series
# --------------------------------------------------------------------------


def _check_stamps(name, stamps):
    stamps = np.asarray(stamps, np.float64)
    if stamps.ndim != 1 or stamps.size < 2:
        raise LogError(f"{name}: needs at least 2 time stamps, got {stamps.size}")
    if not np.all(np.isfinite(stamps)):
        index = int(np.flatnonzero(~np.isfinite(stamps))[0])
        raise LogError(f"{name}: time stamp {index} is {stamps[index]!r}, not a finite time")
    step = np.diff(stamps)
    if np.any(step == 0):
        index = int(np.flatnonzero(step == 0)[0]) + 1
        raise LogError(
            f"{name}: duplicate time stamp {stamps[index]:.9g} s (samples {index - 1} and "
            f"{index}); a log needs one sample per stamp"
        )
    if np.any(step < 0):
        index = int(np.flatnonzero(step < 0)[0]) + 1
        raise LogError(
            f"{name}: time goes backwards at sample {index} ({stamps[index - 1]:.9g} s -> "
            f"{stamps[index]:.9g} s); stamps must increase"
        )
    return stamps


def _check_gaps(name, stamps, start, end, max_gap):
    """Intervals (start, end) longer than ``max_gap`` within the grid span raise."""
    step = np.diff(stamps)
    within = (stamps[1:] > start) & (stamps[:-1] < end)
    long = np.flatnonzero((step > max_gap) & within)
    if long.size:
        index = int(long[0])
        raise LogError(
            f"{name}: gap of {step[index]:.4g} s between {stamps[index]:.6g} s and "
            f"{stamps[index + 1]:.6g} s, longer than max_gap = {max_gap:.4g} s; raise max_gap "
            "to bridge it (readings are held across a gap) or cut the log there"
        )


def _check_positions(name, positions, params, names, limit_margin):
    """Positions beyond the robot's limits by more than ``limit_margin`` (rad) raise."""
    finite = np.where(np.isfinite(positions), positions, 0.0)
    limits = joint_limits(params)
    if limits is None:
        lower = np.full(len(names), -DEFAULT_POSITION_LIMIT)
        upper = np.full(len(names), DEFAULT_POSITION_LIMIT)
        what = f"|q| <= {DEFAULT_POSITION_LIMIT:g} rad (the robot declares no limits)"
    else:
        lower, upper = limits[0] - limit_margin, limits[1] + limit_margin
        what = f"its joint limits +- {limit_margin:g} rad"
    bad = (finite < lower[None]) | (finite > upper[None])
    if bad.any():
        sample, joint = (int(v) for v in np.argwhere(bad)[0])
        raise LogError(
            f"{name} of joint {names[joint]!r} is {positions[sample, joint]:.6g} at sample "
            f"{sample}, outside {what}: positions must be in rad (degrees? another robot?)"
        )


def match_joints(log_names, robot_names, where):
    """Column index in the log of each robot joint, and the log's joints the robot lacks.

    Raises:
        LogError: a robot joint missing from the log, or a name given twice.
    """
    log_names = [str(v) for v in log_names]
    duplicates = sorted({v for v in log_names if log_names.count(v) > 1})
    if duplicates:
        raise LogError(f"{where}: joint {duplicates[0]!r} appears more than once")
    missing = [v for v in robot_names if v not in log_names]
    if missing:
        raise LogError(
            f"{where}: the robot's joints {missing} are not in the log, which has "
            f"{log_names}; the joint names must match the robot's {list(robot_names)}"
        )
    extra = [v for v in log_names if v not in robot_names]
    return [log_names.index(v) for v in robot_names], extra


# --------------------------------------------------------------------------
# Resampling
# --------------------------------------------------------------------------


def _interpolate(stamps, values, grid):
    """Linear interpolation of (S, n) ``values`` at ``grid`` (G,): (G, n)."""
    return np.stack([np.interp(grid, stamps, values[:, j]) for j in range(values.shape[1])], -1)


def _reading_index(stamps, grid, dt, rule):
    """Index of the reading each grid point takes, under ``rule``."""
    slack = _ON_GRID * dt
    if rule == "hold":
        index = np.searchsorted(stamps, grid + slack, side="right") - 1
        return np.clip(index, 0, stamps.size - 1)
    after = np.clip(np.searchsorted(stamps, grid, side="left"), 0, stamps.size - 1)
    before = np.clip(after - 1, 0, stamps.size - 1)
    take_before = np.abs(grid - stamps[before]) <= np.abs(stamps[after] - grid) + slack
    return np.where(take_before, before, after)


def assemble(
    params: UncertainRobot,
    *,
    reference_time,
    q_d,
    qd_d,
    qdd_d=None,
    reading_time,
    q,
    qd,
    dt: float = 0.01,
    kp=100.0,
    kd=20.0,
    reading_rule: str = "hold",
    max_gap: float | None = None,
    limit_margin: float = 0.5,
    dtype=None,
    source: dict | None = None,
    names=None,
) -> Log:
    """Put a reference and readings, in the robot's joint order, on the grid (module docstring).

    Args:
        params: the robot (its joint names label the log, its limits check it).
        reference_time: (S_r,) s; q_d, qd_d, qdd_d: (S_r, n) rad, rad/s, rad/s^2
            (``qdd_d`` None: derived by finite differences).
        reading_time: (S_m,) s; q, qd: (S_m, n) measured rad, rad/s.
        dt: the controller's step in s; kp, kd: its gains.
        reading_rule: ``"hold"`` or ``"nearest"``, see :data:`READING_RULES`.
        max_gap: longest tolerated interval (s) between samples; default ``10 dt``.
        limit_margin: rad beyond declared joint limits that still count as plausible.
        dtype: float dtype of the trajectory; default float64 with x64, else float32.
        source: facts about the file for ``Log.source``.
        names: the robot's joint names in its order; default :func:`joint_names`.

    Raises:
        LogError: see the module docstring.
    """
    if reading_rule not in READING_RULES:
        raise ValueError(f"unknown reading_rule {reading_rule!r}; choose one of {READING_RULES}")
    dt = float(dt)
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive step in s, got {dt!r}")
    max_gap = 10 * dt if max_gap is None else float(max_gap)
    if not max_gap > 0:
        raise ValueError(f"max_gap must be a positive time in s, got {max_gap!r}")
    names = tuple(names) if names else joint_names(params)
    if len(names) != params.n_joints:
        raise ValueError(f"{len(names)} joint names for a {params.n_joints}-joint robot")
    n = len(names)
    source = dict(source or {})
    ref_t = _check_stamps("reference", reference_time)
    meas_t = _check_stamps("readings", reading_time)
    series = {"q_d": q_d, "qd_d": qd_d, "q": q, "qd": qd}
    if qdd_d is not None:
        series["qdd_d"] = qdd_d
    for key, value in list(series.items()):
        value = np.asarray(value, np.float64)
        length = (ref_t if key.endswith("_d") else meas_t).size
        if value.shape != (length, n):
            raise LogError(f"{key} must have shape ({length}, {n}), got {value.shape}")
        series[key] = value
    for key in ("q_d", "qd_d", "qdd_d"):
        if key in series and not np.all(np.isfinite(series[key])):
            sample, joint = (int(v) for v in np.argwhere(~np.isfinite(series[key]))[0])
            value = float(series[key][sample, joint])
            raise LogError(
                f"the reference {key} of joint {names[joint]!r} is {value} "
                f"at {ref_t[sample]:.6g} s: the controller's reference must be complete "
                "(a NaN *reading* is kept and alarms; a NaN reference has no meaning)"
            )
    _check_positions("reference q_d", series["q_d"], params, names, limit_margin)
    _check_positions("reading q", series["q"], params, names, limit_margin)

    start, end = max(ref_t[0], meas_t[0]), min(ref_t[-1], meas_t[-1])
    n_steps = int(np.floor((end - start) / dt + _ON_GRID))
    if n_steps < 1:
        raise LogError(
            f"the reference ({ref_t[0]:.6g}..{ref_t[-1]:.6g} s) and the readings "
            f"({meas_t[0]:.6g}..{meas_t[-1]:.6g} s) overlap for less than one step dt = {dt:g} s"
        )
    grid = start + dt * np.arange(n_steps + 1)
    _check_gaps("reference", ref_t, start, grid[-1], max_gap)
    _check_gaps("readings", meas_t, start, grid[-1], max_gap)

    reference = {k: _interpolate(ref_t, series[k], grid) for k in ("q_d", "qd_d")}
    derived = list(source.pop("derived", []))
    if "qdd_d" in series:
        reference["qdd_d"] = _interpolate(ref_t, series["qdd_d"], grid)
    else:
        reference["qdd_d"] = np.gradient(reference["qd_d"], dt, axis=0)
        derived.append("qdd_d: central finite differences of the interpolated qd_d")
    index = _reading_index(meas_t, grid, dt, reading_rule)
    readings = np.stack([series["q"][index], series["qd"][index]], axis=-1)
    nan = np.isnan(readings)
    step = np.diff(meas_t)
    late = np.flatnonzero((step > 1.5 * dt) & (meas_t[1:] > start) & (meas_t[:-1] < grid[-1]))
    gaps = tuple((float(meas_t[i]), float(meas_t[i + 1])) for i in late)

    import jax.numpy as jnp

    if dtype is not None:
        reference = {k: jnp.asarray(v, dtype) for k, v in reference.items()}
    traj = trajectory_from_samples(
        reference["q_d"],
        reference["qd_d"],
        reference["qdd_d"],
        dt=dt,
        kp=kp,
        kd=kd,
        labels=tuple(f"log:{v}" for v in names),
    )
    source.update(
        reading_rule=reading_rule,
        derived=derived,
        trimmed_s={
            "reference": [float(start - ref_t[0]), float(ref_t[-1] - grid[-1])],
            "readings": [float(start - meas_t[0]), float(meas_t[-1] - grid[-1])],
        },
        samples={"reference": int(ref_t.size), "readings": int(meas_t.size)},
        max_gap_s=max_gap,
    )
    source.setdefault("ignored", [])
    return Log(
        traj=traj,
        robot=params,
        readings=readings,
        time=grid,
        joint_names=names,
        gaps=gaps,
        nan=nan,
        source=source,
    )
