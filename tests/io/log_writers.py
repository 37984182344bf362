"""Write simulated runs as logs (CSV, NPZ, ROS 1 and ROS 2 bags) for the reader tests."""

from __future__ import annotations

import numpy as np

import rmijax
from rmijax.io import ros

DT = 0.01
ONSET = 0.5


def faulty_run(duration=1.0, fault=None):
    """A two-joint run with stuck sensors on joint 2 at 0.5 s; its bands and detection."""
    params = rmijax.paper_arm2()
    traj = rmijax.trajectory(["hold", "sine"], duration=duration, dt=DT)
    th_true = np.asarray(params.nominal) * np.r_[1.08, 1.08, 1.0, 1.0] - np.r_[0, 0, 0.005, 0.005]
    fault = fault or rmijax.Fault("stuck_sensors", 1, ONSET)
    _, readings = rmijax.simulate(traj, params, th_true, faults=[fault])
    bounds = rmijax.rmi(traj, params)
    detection = rmijax.detect(readings, bounds, onset=ONSET)
    return dict(
        params=params,
        traj=traj,
        readings=np.asarray(readings),
        bounds=bounds,
        detection=detection,
        names=["joint1", "joint2"],
    )


def _stamp(types, nanoseconds, ros1=False):
    time = types["builtin_interfaces/msg/Time"]
    stamp = time(sec=int(nanoseconds // 10**9), nanosec=int(nanoseconds % 10**9))
    header = types["std_msgs/msg/Header"]
    if ros1:
        return header(seq=0, stamp=stamp, frame_id="")
    return header(stamp=stamp, frame_id="")


def _point(types, q, qd, qdd, offset_ns=0):
    duration = types["builtin_interfaces/msg/Duration"]
    return types["trajectory_msgs/msg/JointTrajectoryPoint"](
        positions=np.asarray(q, np.float64),
        velocities=np.asarray(qd, np.float64),
        accelerations=np.asarray(qdd, np.float64),
        effort=np.zeros(0),
        time_from_start=duration(sec=int(offset_ns // 10**9), nanosec=int(offset_ns % 10**9)),
    )


def write_bag(path, run, *, kind="sqlite3", reference="state", start_ns=2 * 10**9, extra=True):
    """Write ``run`` as a bag: JointState readings and the reference on its own topic.

    Args:
        kind: ``"sqlite3"``, ``"mcap"`` (ROS 2) or ``"ros1"``.
        reference: ``"state"`` (a JointTrajectoryControllerState per tick) or
            ``"plan"`` (one JointTrajectory holding every point).
        start_ns: log time of the first sample.
        extra: add a gripper joint the robot does not have (it must be ignored).
    """
    from rosbags.typesys import Stores, get_typestore

    ros1 = kind == "ros1"
    typestore = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    typestore.register(ros.control_msgs_types(1 if ros1 else 2))
    types = typestore.types
    serialize = typestore.serialize_ros1 if ros1 else typestore.serialize_cdr
    traj, readings = run["traj"], run["readings"]
    names = list(run["names"]) + (["gripper"] if extra else [])
    pad = [0.0] if extra else []
    q_d, qd_d, qdd_d = (np.asarray(a) for a in (traj.q_d, traj.qd_d, traj.qdd_d))
    times = start_ns + np.arange(traj.n_steps + 1) * int(round(DT * 1e9))
    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        writer = Writer(path, version=9, storage_plugin=plugin)
    joint_state = types[ros.JOINT_STATE]
    with writer:
        measured = writer.add_connection("/joint_states", ros.JOINT_STATE, typestore=typestore)
        if reference == "state":
            ref = writer.add_connection(
                "/arm_controller/controller_state", ros.CONTROLLER_STATE, typestore=typestore
            )
        else:
            ref = writer.add_connection(
                "/arm_controller/joint_trajectory", ros.JOINT_TRAJECTORY, typestore=typestore
            )
            plan = types[ros.JOINT_TRAJECTORY](
                header=_stamp(types, times[0], ros1),
                joint_names=names,
                points=[
                    _point(
                        types, [*q_d[k], *pad], [*qd_d[k], *pad], [*qdd_d[k], *pad], t - times[0]
                    )
                    for k, t in enumerate(times)
                ],
            )
            writer.write(ref, int(times[0]), serialize(plan, ros.JOINT_TRAJECTORY))
        for k, t in enumerate(times):
            msg = joint_state(
                header=_stamp(types, t, ros1),
                name=list(reversed(names)),  # any order: matched by name
                position=np.asarray([*pad, *readings[k, ::-1, 0]]),
                velocity=np.asarray([*pad, *readings[k, ::-1, 1]]),
                effort=np.zeros(0),
            )
            writer.write(measured, int(t), serialize(msg, ros.JOINT_STATE))
            if reference == "state":
                point = _point(types, [*q_d[k], *pad], [*qd_d[k], *pad], [*qdd_d[k], *pad])
                fields = dict(header=_stamp(types, t, ros1), joint_names=names)
                if ros1:
                    fields.update(desired=point, actual=point, error=point)
                else:
                    fields.update(reference=point, feedback=point, error=point, output=point)
                state = types[ros.CONTROLLER_STATE](**fields)
                writer.write(ref, int(t), serialize(state, ros.CONTROLLER_STATE))
    return path


def write_table(path, run, *, time=None, readings=None, q_d=None, with_accel=True):
    """Write ``run`` as CSV or NPZ (by suffix), with optional replaced columns."""
    traj = run["traj"]
    writer = rmijax.io.write_csv if str(path).endswith(".csv") else rmijax.io.write_npz
    return writer(
        path,
        time=np.asarray(traj.t) if time is None else time,
        joint_names=run["names"],
        q_d=np.asarray(traj.q_d) if q_d is None else q_d,
        qd_d=np.asarray(traj.qd_d),
        qdd_d=np.asarray(traj.qdd_d) if with_accel else None,
        readings=run["readings"] if readings is None else readings,
    )
