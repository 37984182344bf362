"""ROS 1 and ROS 2 bags (sqlite3 and MCAP storage), read with ``rosbags`` (no ROS install).

``rosbags`` is an optional dependency: ``pip install "rmijax[ros]"``.

- Readings: ``sensor_msgs/msg/JointState`` (``position`` rad, ``velocity``
  rad/s; ``effort`` is not used), matched to the robot's joints by name in
  every message.
- Reference: ``trajectory_msgs/msg/JointTrajectory`` (a plan: point times are
  the header stamp, or the receive time when the stamp is zero, plus
  ``time_from_start``; a later message replaces the plan from its first point
  on, as a ROS controller does) or ``control_msgs/msg/JointTrajectoryControllerState``
  (the controller's own state at each tick: its ``reference`` field, ``desired``
  in ROS 1 and older ROS 2).
- Topics: given by the user, or the one topic of the right type in the bag
  (several candidates are an error that lists them).
- Time stamps: the messages' header stamps, or the receive (log) times for a
  topic whose header stamps are all zero; ``Log.source["stamps"]`` says which.
"""

from __future__ import annotations

import pathlib

import numpy as np

from rmijax.io.log import Log, LogError, assemble, joint_names

__all__ = [
    "CONTROLLER_STATE",
    "JOINT_STATE",
    "JOINT_TRAJECTORY",
    "control_msgs_types",
    "is_bag",
    "read_bag",
]

JOINT_STATE = "sensor_msgs/msg/JointState"
JOINT_TRAJECTORY = "trajectory_msgs/msg/JointTrajectory"
CONTROLLER_STATE = "control_msgs/msg/JointTrajectoryControllerState"
REFERENCE_TYPES = (CONTROLLER_STATE, JOINT_TRAJECTORY)

_CONTROLLER_STATE_ROS2 = """std_msgs/Header header
string[] joint_names
trajectory_msgs/JointTrajectoryPoint reference
trajectory_msgs/JointTrajectoryPoint feedback
trajectory_msgs/JointTrajectoryPoint error
trajectory_msgs/JointTrajectoryPoint output
"""

_CONTROLLER_STATE_ROS1 = """Header header
string[] joint_names
trajectory_msgs/JointTrajectoryPoint desired
trajectory_msgs/JointTrajectoryPoint actual
trajectory_msgs/JointTrajectoryPoint error
"""


def _rosbags():
    try:
        import rosbags  # noqa: F401
    except ImportError as err:
        raise ImportError(
            'reading ROS bags needs the rosbags library: pip install "rmijax[ros]" '
            "(or pip install rosbags); it is pure Python and needs no ROS install"
        ) from err
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    return AnyReader, Stores, get_types_from_msg, get_typestore


def control_msgs_types(ros: int = 2) -> dict:
    """The ``control_msgs/msg/JointTrajectoryControllerState`` type for ``typestore.register``.

    ``rosbags`` ships no ``control_msgs``; bags written with MCAP, ROS 1 or a
    recent rosbag2 embed the definition and it is taken from there. This one
    (ROS 2 ``control_msgs`` 4.x with ``reference``, or ROS 1 with ``desired``)
    is the fallback, and what the tests write with.
    """
    *_, get_types_from_msg, _ = _rosbags()
    text = _CONTROLLER_STATE_ROS2 if ros == 2 else _CONTROLLER_STATE_ROS1
    return get_types_from_msg(text, CONTROLLER_STATE)


def is_bag(path) -> bool:
    """True for a ROS 1 ``.bag``, a ROS 2 bag folder (``metadata.yaml``), ``.db3`` or ``.mcap``."""
    path = pathlib.Path(path)
    if path.is_dir():
        return (path / "metadata.yaml").exists()
    return path.suffix in (".bag", ".db3", ".mcap")


def _bag_paths(path):
    path = pathlib.Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no such bag: {path}")
    if path.suffix in (".db3", ".mcap") and (path.parent / "metadata.yaml").exists():
        return [path.parent]
    return [path]


def _seconds(stamp):
    return stamp.sec + 1e-9 * stamp.nanosec


def _pick(connections, wanted, types, role, path):
    """The topic for ``role``: the one asked for, or the only one of the right type."""
    by_topic = {c.topic: c for c in connections}
    if wanted is not None:
        if wanted not in by_topic:
            raise LogError(f"{path}: no topic {wanted!r}; the bag has {sorted(by_topic)}")
        if by_topic[wanted].msgtype not in types:
            raise LogError(
                f"{path}: topic {wanted!r} carries {by_topic[wanted].msgtype}, not "
                f"{' or '.join(types)} ({role})"
            )
        return by_topic[wanted]
    found = [c for c in connections if c.msgtype in types]
    topics = sorted({c.topic for c in found})
    if not topics:
        raise LogError(
            f"{path}: no {' or '.join(types)} topic for the {role}; the bag has "
            f"{sorted((c.topic, c.msgtype) for c in connections)}"
        )
    if len(topics) > 1:
        raise LogError(
            f"{path}: several topics could be the {role}: {topics}; choose one "
            f"({'joint_state_topic' if role == 'readings' else 'reference_topic'}=...)"
        )
    return next(c for c in found if c.topic == topics[0])


def _stamps(header_times, receive_times):
    header_times = np.asarray(header_times, np.float64)
    if header_times.size and np.any(header_times != 0):
        return header_times, "header"
    return np.asarray(receive_times, np.float64), "receive"


class _JointOrder:
    """Columns of the robot's joints in a message's name list (cached per name list)."""

    def __init__(self, robot, where):
        self.robot, self.where, self.cache, self.extra = robot, where, {}, set()

    def __call__(self, names):
        key = tuple(names)
        if key not in self.cache:
            missing = [v for v in self.robot if v not in key]
            if missing:
                raise LogError(
                    f"{self.where}: the robot's joints {missing} are not in the message's "
                    f"joints {list(key)}; the joint names must match the robot's "
                    f"{list(self.robot)}"
                )
            self.extra.update(v for v in key if v not in self.robot)
            self.cache[key] = [key.index(v) for v in self.robot]
        return self.cache[key]


def _field(values, order, what, where, length):
    values = np.asarray(values, np.float64)
    if values.size == 0:
        return None
    if values.size != length:
        raise LogError(f"{where}: {what} has {values.size} entries for {length} joint names")
    return values[order]


def _joint_states(reader, connection, robot, path):
    where = f"{path} {connection.topic}"
    order = _JointOrder(robot, where)
    header_t, receive_t, q, qd = [], [], [], []
    for _, receive, raw in reader.messages(connections=[connection]):
        msg = reader.deserialize(raw, connection.msgtype)
        columns = order(msg.name)
        position = _field(msg.position, columns, "position", where, len(msg.name))
        velocity = _field(msg.velocity, columns, "velocity", where, len(msg.name))
        if position is None or velocity is None:
            missing = "position" if position is None else "velocity"
            raise LogError(
                f"{where}: a JointState at {receive * 1e-9:.6g} s has no {missing}; "
                "RMI compares both encoder and tachometer readings"
            )
        header_t.append(_seconds(msg.header.stamp))
        receive_t.append(receive * 1e-9)
        q.append(position)
        qd.append(velocity)
    if not q:
        raise LogError(f"{where}: the topic has no messages")
    stamps, kind = _stamps(header_t, receive_t)
    return stamps, np.asarray(q), np.asarray(qd), kind, sorted(order.extra)


def _point(point, columns, where, length):
    values = [
        _field(getattr(point, key), columns, key, where, length)
        for key in ("positions", "velocities", "accelerations")
    ]
    if values[0] is None or values[1] is None:
        missing = "positions" if values[0] is None else "velocities"
        raise LogError(f"{where}: a reference point has no {missing}")
    return values


def _controller_states(reader, connection, robot, path):
    where = f"{path} {connection.topic}"
    order = _JointOrder(robot, where)
    header_t, receive_t, points = [], [], []
    for _, receive, raw in reader.messages(connections=[connection]):
        msg = reader.deserialize(raw, connection.msgtype)
        columns = order(msg.joint_names)
        point = getattr(msg, "reference", None)
        if point is None or len(point.positions) == 0:
            point = getattr(msg, "desired", point)
        points.append(_point(point, columns, where, len(msg.joint_names)))
        header_t.append(_seconds(msg.header.stamp))
        receive_t.append(receive * 1e-9)
    if not points:
        raise LogError(f"{where}: the topic has no messages")
    stamps, kind = _stamps(header_t, receive_t)
    return stamps, points, kind, sorted(order.extra), 0


def _trajectories(reader, connection, robot, path):
    where = f"{path} {connection.topic}"
    order = _JointOrder(robot, where)
    plans = []
    for _, receive, raw in reader.messages(connections=[connection]):
        msg = reader.deserialize(raw, connection.msgtype)
        columns = order(msg.joint_names)
        stamp = _seconds(msg.header.stamp)
        base, kind = (stamp, "header") if stamp != 0 else (receive * 1e-9, "receive")
        times = [base + _seconds(p.time_from_start) for p in msg.points]
        values = [_point(p, columns, where, len(msg.joint_names)) for p in msg.points]
        if times:
            plans.append((times, values, kind))
    if not plans:
        raise LogError(f"{where}: no JointTrajectory with points")
    stamps, points, superseded = [], [], 0
    for index, (times, values, _) in enumerate(plans):
        until = plans[index + 1][0][0] if index + 1 < len(plans) else np.inf
        keep = [i for i, t in enumerate(times) if t < until]
        superseded += len(times) - len(keep)
        stamps += [times[i] for i in keep]
        points += [values[i] for i in keep]
    kinds = sorted({kind for *_, kind in plans})
    return np.asarray(stamps), points, "+".join(kinds), sorted(order.extra), superseded


def read_bag(
    path,
    params,
    *,
    joint_state_topic: str | None = None,
    reference_topic: str | None = None,
    **resample,
) -> Log:
    """Read a ROS 1 or ROS 2 bag (module docstring) for robot ``params``.

    Args:
        path: a ROS 1 ``.bag`` file, or a ROS 2 bag folder (or its ``.db3`` /
            ``.mcap`` file).
        params: the robot; its joint names select the JointState entries.
        joint_state_topic, reference_topic: topics to read; default: the one
            topic of the right type.
        **resample: ``dt``, ``kp``, ``kd``, ``reading_rule``, ``max_gap``, ...
            (:func:`rmijax.io.log.assemble`).

    Raises:
        ImportError: rosbags is not installed.
        LogError: a missing or ambiguous topic, joints that do not match,
            messages without positions or velocities, and every check of
            :func:`~rmijax.io.log.assemble`.
    """
    any_reader, stores, _, get_typestore = _rosbags()
    paths = _bag_paths(path)
    robot = resample.pop("names", None) or joint_names(params)
    ros1 = paths[0].is_file() and paths[0].suffix == ".bag"
    typestore = get_typestore(stores.ROS1_NOETIC if ros1 else stores.ROS2_HUMBLE)
    typestore.register(control_msgs_types(1 if ros1 else 2))
    with any_reader(paths, default_typestore=typestore) as reader:
        connections = list(reader.connections)
        readings = _pick(connections, joint_state_topic, (JOINT_STATE,), "readings", path)
        reference = _pick(connections, reference_topic, REFERENCE_TYPES, "reference", path)
        meas_t, q, qd, meas_kind, extra_meas = _joint_states(reader, readings, robot, path)
        if reference.msgtype == JOINT_TRAJECTORY:
            ref = _trajectories(reader, reference, robot, path)
        else:
            ref = _controller_states(reader, reference, robot, path)
    ref_t, points, ref_kind, extra_ref, superseded = ref
    q_d = np.asarray([p[0] for p in points])
    qd_d = np.asarray([p[1] for p in points])
    with_accel = all(p[2] is not None for p in points)
    qdd_d = np.asarray([p[2] for p in points]) if with_accel else None
    ignored = [f"joint {v} (readings)" for v in extra_meas]
    ignored += [f"joint {v} (reference)" for v in extra_ref]
    if superseded:
        ignored.append(f"{superseded} plan points replaced by a later JointTrajectory")
    source = dict(
        path=str(path),
        format="ros1" if ros1 else "ros2",
        topics={
            "readings": f"{readings.topic} ({readings.msgtype})",
            "reference": f"{reference.topic} ({reference.msgtype})",
        },
        stamps={"readings": meas_kind, "reference": ref_kind},
        ignored=ignored,
    )
    return assemble(
        params,
        reference_time=ref_t,
        q_d=q_d,
        qd_d=qd_d,
        qdd_d=qdd_d,
        reading_time=meas_t,
        q=q,
        qd=qd,
        source=source,
        names=robot,
        **resample,
    )
