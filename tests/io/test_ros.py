"""ROS bags written with rosbags' own writers read back with the in-memory run's alarms."""

import numpy as np
import pytest
from log_writers import ONSET, faulty_run, write_bag

import rmijax
from rmijax.io import LogError

pytest.importorskip("rosbags")


@pytest.fixture(scope="module")
def run():
    return faulty_run()


@pytest.fixture(scope="module")
def bands(run):
    return run["bounds"]


@pytest.mark.parametrize(
    "kind, reference",
    [("sqlite3", "state"), ("mcap", "state"), ("ros1", "state"), ("mcap", "plan")],
)
def test_bag_gives_the_same_alarms(run, tmp_path, kind, reference):
    path = tmp_path / ("run.bag" if kind == "ros1" else "run")
    write_bag(path, run, kind=kind, reference=reference)
    log = rmijax.read_log(path, robot="paper_arm2")
    assert log.source["format"] == ("ros1" if kind == "ros1" else "ros2")
    assert log.source["ignored"][:2] == ["joint gripper (readings)", "joint gripper (reference)"]
    assert log.time[0] == pytest.approx(2.0)
    np.testing.assert_array_equal(log.readings, run["readings"])
    np.testing.assert_allclose(log.traj.x_n, run["traj"].x_n, atol=1e-12)
    bounds = rmijax.rmi(log.traj, run["params"])
    np.testing.assert_allclose(bounds.upper, run["bounds"].upper, atol=1e-12)
    detection = rmijax.detect(log.readings, bounds, onset=ONSET)
    np.testing.assert_array_equal(detection.alarms, run["detection"].alarms)
    assert detection.latency == run["detection"].latency == 0.0


def test_bag_topics_are_checked(run, tmp_path):
    path = write_bag(tmp_path / "run", run, kind="mcap")
    with pytest.raises(LogError, match="no topic '/nope'"):
        rmijax.read_log(path, robot="paper_arm2", joint_state_topic="/nope")
    with pytest.raises(LogError, match="carries sensor_msgs/msg/JointState"):
        rmijax.read_log(path, robot="paper_arm2", reference_topic="/joint_states")
    with pytest.raises(LogError, match=r"joints \['joint3'\] are not in the message"):
        rmijax.read_log(path, robot="preset3")


def test_bag_without_reference_is_refused(run, tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS2_HUMBLE)
    path = tmp_path / "only_states"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        writer.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=typestore)
    with pytest.raises(LogError, match="no control_msgs/msg/JointTrajectoryControllerState or"):
        rmijax.read_log(path, robot="paper_arm2")


def test_joint_states_without_velocity_are_refused(run, tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from rmijax.io import ros

    typestore = get_typestore(Stores.ROS2_HUMBLE)
    typestore.register(ros.control_msgs_types(2))
    types = typestore.types
    path = tmp_path / "no_velocity"
    with Writer(path, version=9, storage_plugin=StoragePlugin.SQLITE3) as writer:
        states = writer.add_connection("/joint_states", ros.JOINT_STATE, typestore=typestore)
        writer.add_connection("/state", ros.CONTROLLER_STATE, typestore=typestore)
        header = types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id=""
        )
        msg = types[ros.JOINT_STATE](
            header=header,
            name=["joint1", "joint2"],
            position=np.zeros(2),
            velocity=np.zeros(0),
            effort=np.zeros(0),
        )
        writer.write(states, 10**9, typestore.serialize_cdr(msg, ros.JOINT_STATE))
    with pytest.raises(LogError, match="has no velocity"):
        rmijax.read_log(path, robot="paper_arm2")
