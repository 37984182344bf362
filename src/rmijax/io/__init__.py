"""Recorded robot logs in: CSV, NPZ and ROS 1 / ROS 2 bags onto the controller's grid.

``rmijax.read_log(path, robot=...)`` reads any of them into a :class:`Log`
(the desired motion as a :class:`~rmijax.Trajectory`, the readings
``(T+1, n, 2)`` for :func:`rmijax.detect`); :mod:`rmijax.io.log` says how the
samples are put on the grid and which logs are refused.
"""

from __future__ import annotations

import pathlib

from rmijax.io.log import (
    READING_RULES as READING_RULES,
    Log as Log,
    LogError as LogError,
    resolve_robot as resolve_robot,
    robot_joint_names as robot_joint_names,
)
from rmijax.io.ros import is_bag as is_bag, read_bag as read_bag
from rmijax.io.tables import (
    read_csv as read_csv,
    read_npz as read_npz,
    write_csv as write_csv,
    write_npz as write_npz,
)
from rmijax.robots.loaders import REAL_ARM_BOX as REAL_ARM_BOX

__all__ = [
    "READING_RULES",
    "REAL_ARM_BOX",
    "Log",
    "LogError",
    "is_log",
    "read_bag",
    "read_csv",
    "read_log",
    "read_npz",
    "resolve_robot",
    "robot_joint_names",
    "write_csv",
    "write_npz",
]


def is_log(path) -> bool:
    """True for a path :func:`read_log` can read (by its suffix, or a ROS 2 bag folder)."""
    path = pathlib.Path(path)
    return path.suffix in (".csv", ".npz") and path.is_file() or is_bag(path)


def read_log(
    path,
    *,
    robot,
    dt: float = 0.01,
    kp=100.0,
    kd=20.0,
    reading_rule: str = "hold",
    max_gap: float | None = None,
    limit_margin: float = 0.5,
    joint_state_topic: str | None = None,
    reference_topic: str | None = None,
    joint_names=None,
    dtype=None,
) -> Log:
    """Read a recorded run onto the controller's grid ``t_k = t_0 + k dt``.

    Args:
        path: ``.csv`` or ``.npz`` (:mod:`rmijax.io.tables` gives the columns),
            a ROS 1 ``.bag``, or a ROS 2 bag folder / ``.db3`` / ``.mcap``
            (:mod:`rmijax.io.ros`; needs ``pip install "rmijax[ros]"``).
        robot: a :class:`~rmijax.UncertainRobot` or a name (``"paper_arm2"``,
            ``"preset<n>"``, a real arm of :func:`rmijax.load_robot`); its joint
            names are matched to the log's.
        dt: the controller's step in s; kp, kd: its gains (scalar or per joint).
        reading_rule: ``"hold"`` (last reading at or before each tick) or
            ``"nearest"``; the reference is interpolated linearly.
        max_gap: longest interval (s) between samples that is bridged; default ``10 dt``.
        limit_margin: rad beyond the robot's joint limits that a position may lie.
        joint_state_topic, reference_topic: bag topics; default found by type.
        joint_names: the robot's joint names in its order, as the log names them;
            default the robot's own (:func:`robot_joint_names`: a real arm's chain,
            ``joint1..jointn`` for the planar arms).
        dtype: float dtype of the trajectory (default float64 with x64, else float32).

    Returns:
        A :class:`Log`: ``log.traj`` for :func:`rmijax.rmi`, ``log.readings``
        (T+1, n, 2) for :func:`rmijax.detect`, the gaps and NaN readings.

    Raises:
        LogError: a log that cannot be a run of this robot (the message says why).
        FileNotFoundError, ImportError (bags without rosbags).
    """
    names = tuple(joint_names) if joint_names is not None else robot_joint_names(robot)
    params = resolve_robot(robot)
    path = pathlib.Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no such log: {path}")
    resample = dict(
        dt=dt,
        kp=kp,
        kd=kd,
        reading_rule=reading_rule,
        max_gap=max_gap,
        limit_margin=limit_margin,
        dtype=dtype,
        names=names,
    )
    if is_bag(path):
        return read_bag(
            path,
            params,
            joint_state_topic=joint_state_topic,
            reference_topic=reference_topic,
            **resample,
        )
    if joint_state_topic is not None or reference_topic is not None:
        raise ValueError(f"{path} is not a bag: joint_state_topic/reference_topic do not apply")
    if path.suffix == ".csv":
        return read_csv(path, params, **resample)
    if path.suffix == ".npz":
        return read_npz(path, params, **resample)
    raise LogError(
        f"{path}: unknown log format {path.suffix!r}; rmijax reads .csv, .npz, ROS 1 .bag and "
        "ROS 2 bags (folder with metadata.yaml, .db3 or .mcap)"
    )
