"""CSV and NPZ logs: round trips give the in-memory run's alarms; bad logs raise LogError."""

import numpy as np
import pytest
from log_writers import DT, ONSET, faulty_run, write_table

import rmijax
from rmijax.io import LogError


@pytest.fixture(scope="module")
def run():
    return faulty_run()


def _alarms(log, run):
    bounds = rmijax.rmi(log.traj, run["params"])
    return rmijax.detect(log.readings, bounds, onset=ONSET)


@pytest.mark.parametrize("suffix", ["csv", "npz"])
def test_round_trip_gives_the_same_alarms(run, tmp_path, suffix):
    path = write_table(tmp_path / f"run.{suffix}", run)
    log = rmijax.read_log(path, robot="paper_arm2")
    assert log.joint_names == ("joint1", "joint2")
    np.testing.assert_array_equal(log.readings, run["readings"])
    np.testing.assert_allclose(log.traj.u_d, run["traj"].u_d, atol=1e-12)
    detection = _alarms(log, run)
    np.testing.assert_array_equal(detection.alarms, run["detection"].alarms)
    assert detection.first_alarm == run["detection"].first_alarm
    assert log.gaps == () and log.nan_samples == 0 and log.source["derived"] == []


def test_missing_accelerations_are_derived_and_said(run, tmp_path):
    log = rmijax.read_log(
        write_table(tmp_path / "a.csv", run, with_accel=False), robot="paper_arm2"
    )
    assert "qdd_d" in log.source["derived"][0]
    interior = slice(1, -1)
    np.testing.assert_allclose(log.traj.qdd_d[interior], run["traj"].qdd_d[interior], atol=2e-4)


def test_faster_readings_are_held_and_offset_grid(run, tmp_path):
    """Readings at twice the rate, half a step late: 'hold' takes the last one at each tick."""
    traj = run["traj"]
    time = np.asarray(traj.t) + 10.0
    fine = 10.0 + DT / 2 * np.arange(2 * traj.n_steps + 1)
    readings = np.repeat(run["readings"], 2, axis=0)[: fine.size]
    path = tmp_path / "fine.npz"
    q = readings[..., 0]
    rmijax.io.write_npz(
        path,
        time=fine,
        joint_names=run["names"],
        q_d=np.interp(fine, time, traj.q_d[:, 0])[:, None].repeat(2, 1),
        qd_d=np.zeros_like(q),
        readings=readings,
    )
    log = rmijax.read_log(path, robot="paper_arm2")
    assert log.time[0] == 10.0 and log.n_steps == traj.n_steps
    np.testing.assert_array_equal(log.readings, run["readings"])
    nearest = rmijax.read_log(path, robot="paper_arm2", reading_rule="nearest")
    np.testing.assert_array_equal(nearest.readings, run["readings"])


def test_nan_readings_are_flagged_and_alarm(run, tmp_path):
    readings = run["readings"].copy()
    readings[20, 0, 1] = np.nan
    log = rmijax.read_log(
        write_table(tmp_path / "n.csv", run, readings=readings), robot="paper_arm2"
    )
    assert log.nan_samples == 1 and log.nan[20, 0, 1]
    detection = rmijax.detect(log.readings, rmijax.rmi(log.traj, run["params"]))
    assert detection.alarms[20, 0, 1] and detection.first_alarm == pytest.approx(20 * DT)


def test_gaps_are_reported_and_long_ones_refused(run, tmp_path):
    keep = np.ones(run["traj"].n_steps + 1, bool)
    keep[30:33] = False  # 0.04 s between samples 29 and 33
    time = np.asarray(run["traj"].t)[keep]
    traj = run["traj"]
    path = rmijax.io.write_csv(
        tmp_path / "g.csv",
        time=time,
        joint_names=run["names"],
        q_d=np.asarray(traj.q_d)[keep],
        qd_d=np.asarray(traj.qd_d)[keep],
        qdd_d=np.asarray(traj.qdd_d)[keep],
        readings=run["readings"][keep],
    )
    log = rmijax.read_log(path, robot="paper_arm2")
    assert log.gaps == (pytest.approx((0.29, 0.33)),)
    np.testing.assert_array_equal(log.readings[30:33], run["readings"][[29, 29, 29]])
    with pytest.raises(LogError, match="gap of 0.04 s"):
        rmijax.read_log(path, robot="paper_arm2", max_gap=0.03)


def _csv(tmp_path, header, rows):
    path = tmp_path / "bad.csv"
    path.write_text(",".join(header) + "\n" + "\n".join(",".join(map(str, r)) for r in rows))
    return path


def _columns(joints=("joint1", "joint2"), quantities=("q_d", "qd_d", "q", "qd")):
    return ["time"] + [f"{q}/{j}" for j in joints for q in quantities]


@pytest.mark.parametrize(
    "case, match",
    [
        ("missing column", r"missing columns \['qd/joint2'\]"),
        ("no time", "no 'time' column"),
        ("wrong joints", r"joints \['joint2'\] are not in the log"),
        ("duplicate stamp", "duplicate time stamp 0.01"),
        ("backwards", "time goes backwards at sample 2"),
        ("nan reference", "reference q_d of joint 'joint1' is nan at 0.01 s"),
        ("degrees", "outside |q| <= 100 rad"),
        ("too short", "overlap for less than one step"),
    ],
)
def test_bad_csv_logs_raise(tmp_path, case, match):
    header = _columns()
    times = [0.0, 0.01, 0.02, 0.03]
    rows = [[t] + [0.1] * 8 for t in times]
    if case == "missing column":
        header = header[:-1]
        rows = [r[:-1] for r in rows]
    elif case == "no time":
        header[0] = "t"
    elif case == "wrong joints":
        header = _columns(("joint1", "elbow"))
    elif case == "duplicate stamp":
        rows[2][0] = 0.01
    elif case == "backwards":
        rows[2][0] = 0.005
    elif case == "nan reference":
        rows[1][1] = "nan"
    elif case == "degrees":
        rows[3][3] = 170.0  # q/joint1 in degrees
    elif case == "too short":
        rows = [[0.0] + [0.1] * 8, [0.005] + [0.1] * 8]
    with pytest.raises(LogError, match=match):
        rmijax.read_log(_csv(tmp_path, header, rows), robot="paper_arm2")


def test_bad_npz_and_unknown_inputs_raise(tmp_path):
    np.savez(tmp_path / "x.npz", time=np.arange(3.0), joint_names=np.asarray(["joint1"]))
    with pytest.raises(LogError, match="missing arrays"):
        rmijax.read_log(tmp_path / "x.npz", robot="paper_pendulum")
    (tmp_path / "x.txt").write_text("")
    with pytest.raises(LogError, match="unknown log format"):
        rmijax.read_log(tmp_path / "x.txt", robot="paper_pendulum")
    with pytest.raises(FileNotFoundError):
        rmijax.read_log(tmp_path / "none.csv", robot="paper_pendulum")
    with pytest.raises(ValueError, match="unknown robot 'robonaut'"):
        rmijax.read_log(tmp_path / "x.npz", robot="robonaut")


def test_robot_names_resolve():
    assert rmijax.io.resolve_robot("preset3").n_joints == 3
    assert rmijax.io.resolve_robot("paper_pendulum").n_joints == 1
    arm = rmijax.paper_arm2()
    assert rmijax.io.resolve_robot(arm) is arm
    assert rmijax.io.robot_joint_names(arm) == ("joint1", "joint2")


def test_real_arm_log_matches_the_chain_joints(tmp_path):
    """A Panda log (the real-arm job's move, nominal readings) reads by the chain's joint names."""
    from rmijax.apps import real_arm

    traj = real_arm.pick_and_place(real_arm.home_pose("panda"), segment_time=0.05)
    names = rmijax.io.robot_joint_names("panda")
    assert len(names) == 7 and names[0] == "joint1"
    path = rmijax.io.write_csv(
        tmp_path / "panda.csv",
        time=np.asarray(traj.t),
        joint_names=list(reversed(names)),  # columns in any order
        q_d=np.asarray(traj.q_d)[:, ::-1],
        qd_d=np.asarray(traj.qd_d)[:, ::-1],
        qdd_d=np.asarray(traj.qdd_d)[:, ::-1],
        readings=np.asarray(traj.x_n)[:, ::-1],
    )
    log = rmijax.read_log(path, robot="panda")
    assert log.joint_names == names and log.robot.n_joints == 7
    np.testing.assert_array_equal(log.readings, np.asarray(traj.x_n))
    np.testing.assert_allclose(log.traj.x_n, traj.x_n, atol=1e-9)
    renamed = ["shoulder", "upper_arm"] + list(names[2:])
    with pytest.raises(LogError, match=r"joints \['shoulder', 'upper_arm'\] are not in the log"):
        rmijax.read_log(path, robot="panda", joint_names=renamed)
