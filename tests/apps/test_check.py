"""``rmijax check``: reports for one log and a folder (resumable); options refused with exit 2."""

import json
import pathlib
import sys

import pytest

sys.path.insert(0, str(pathlib.Path(__file__).parents[1] / "io"))
from log_writers import faulty_run, write_bag, write_table  # noqa: E402

import rmijax  # noqa: E402
from rmijax.apps import cli  # noqa: E402


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("logs")
    run = faulty_run()
    write_table(folder / "stuck.csv", run)
    healthy = faulty_run(duration=0.6, fault=rmijax.Fault("bias", 0, 0.5, 0.0))
    write_table(folder / "healthy.npz", healthy)
    (folder / "broken.csv").write_text("time,q/joint1\n0,1\n")
    pytest.importorskip("rosbags")
    write_bag(folder / "stuck_bag", run, kind="mcap")
    return folder


def test_one_log_report(logs, tmp_path, capsys):
    out = tmp_path / "one"
    assert (
        cli.main(
            [
                "check",
                str(logs / "stuck.csv"),
                "--robot",
                "paper_arm2",
                "--out",
                str(out),
                "--no-progress",
            ]
        )
        == 0
    )
    report = json.loads((out / "report.json").read_text())
    first = report["first_alarm"]
    assert first["time_s"] == 0.5 and first["output"] == "joint2 tachometer"
    assert first["outside_by"] > 0.5 and first["unit"] == "rad/s"
    assert report["alarm_free_stretches_s"] == [[0.0, 0.49]]
    assert report["outputs"]["joint2 encoder"]["alarm_steps"] > 0
    assert "First alarm at 0.50 s" in (out / "report.md").read_text()
    assert (out / "bands.png").stat().st_size > 10_000
    assert "first alarm 0.50 s on joint2 tachometer" in capsys.readouterr().out
    assert "![bands](bands.png)" in (out / "report.md").read_text()


def test_folder_reports_every_log_and_resumes(logs, tmp_path, capsys):
    out = tmp_path / "many"
    args = ["check", str(logs), "--robot", "paper_arm2", "--out", str(out), "--no-progress"]
    args += ["--no-figures"]
    assert cli.main(args) == 0
    summary = {row["log"]: row for row in json.loads((out / "summary.json").read_text())["logs"]}
    assert summary["stuck.csv"]["first_alarm_s"] == 0.5
    assert summary["stuck_bag"]["first_alarm_s"] == 0.5
    assert summary["healthy.npz"]["first_alarm_s"] is None
    assert "not in the log" in summary["broken.csv"]["error"]
    healthy = json.loads((out / "healthy" / "report.json").read_text())
    assert healthy["alarm_free_stretches_s"] == [[0.0, 0.6]] and healthy["samples"] == 61
    assert "3 logs reported (2 with alarms), 1 unreadable" in capsys.readouterr().out
    assert cli.main(args) == 0
    assert "0 logs reported (0 with alarms), 0 unreadable, 4 already reported" in (
        capsys.readouterr().out
    )


@pytest.mark.parametrize(
    "options, message",
    [
        (["--robot", "robonaut"], "unknown robot 'robonaut'"),
        (["--robot", "paper_arm2", "--dt", "0"], "--dt must be a positive number"),
        (["--robot", "paper_arm2", "--dt", "0.3"], "unstable closed loop"),
        (["--robot", "paper_arm2", "--window", "0"], "--window must be >= 1"),
        (["--robot", "paper_arm2", "--method", "nope"], "invalid choice: 'nope'"),
        (["--robot", "paper_arm2", "--joint-state-topic", "/js"], "apply to bags"),
        (["--robot", "ur5e", "--method", "certified"], "default box is not certified"),
        ([], "the following arguments are required: --robot"),
    ],
)
def test_bad_options_exit_2_with_one_line(logs, tmp_path, capsys, options, message):
    assert cli.main(["check", str(logs / "stuck.csv"), "--out", str(tmp_path)] + options) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_diverged_certified_band_exits_1_with_one_line(logs, tmp_path, capsys, monkeypatch):
    """A certified band whose remainder diverges is reported in one line, not a traceback."""
    from rmijax import fleet
    from rmijax.methods.base import DivergedError

    def diverges(*args, **kwargs):
        raise DivergedError.at((3, 1, 0), "certified bounds of run 0 are not finite (step 3)")

    monkeypatch.setattr(fleet, "certified_batch", diverges)
    command = ["check", str(logs / "stuck.csv"), "--robot", "paper_arm2", "--method", "certified"]
    assert cli.main(command + ["--out", str(tmp_path), "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert "not finite (step 3)" in err and err.count("\n") == 1


def test_missing_log_and_empty_folder_exit_2(tmp_path, capsys):
    assert cli.main(["check", str(tmp_path / "none.csv"), "--robot", "preset2"]) == 2
    assert "no such log" in capsys.readouterr().err
    assert cli.main(["check", str(tmp_path), "--robot", "preset2"]) == 2
    assert "holds no logs" in capsys.readouterr().err


@pytest.mark.slow
def test_real_arm_log(tmp_path):
    """A Panda log (the real-arm job's move, stuck sensors on joint 4) checked by name."""
    pytest.importorskip("rmijax.robots.loaders")
    import numpy as np

    from rmijax.apps import real_arm

    params = rmijax.io.resolve_robot("panda")
    traj = real_arm.pick_and_place(real_arm.home_pose("panda"), segment_time=0.05)
    th_true = np.asarray(params.nominal) + 0.6 * (np.asarray(params.hi - params.nominal))
    _, readings = rmijax.simulate(
        traj, params, th_true, faults=[rmijax.Fault("stuck_sensors", 3, 0.2)]
    )
    path = rmijax.io.write_csv(
        tmp_path / "panda.csv",
        time=np.asarray(traj.t),
        joint_names=rmijax.io.robot_joint_names("panda"),
        q_d=traj.q_d,
        qd_d=traj.qd_d,
        qdd_d=traj.qdd_d,
        readings=readings,
    )
    out = tmp_path / "out"
    command = ["check", str(path), "--robot", "panda", "--method", "linearized"]
    assert cli.main(command + ["--window", "20", "--out", str(out), "--no-progress"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["joint_names"][3] == "joint4" and report["alarm"]
    assert report["first_alarm"]["time_s"] >= 0.2


def test_two_processes_share_a_folder(logs, tmp_path):
    """--distributed: 2 local processes (jax.distributed.initialize) take half the logs each."""
    import os
    import socket
    import subprocess

    with socket.socket() as probe:
        probe.bind(("localhost", 0))
        address = f"localhost:{probe.getsockname()[1]}"
    src = pathlib.Path(rmijax.__file__).parents[1]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(src), os.environ.get("PYTHONPATH", "")]))
    out = tmp_path / "hosts"
    command = [sys.executable, "-m", "rmijax.apps.cli", "check", str(logs), "--robot"]
    command += ["paper_arm2", "--out", str(out), "--no-progress", "--no-figures", "--distributed"]
    command += ["--coordinator", address, "--num-processes", "2", "--process-id"]
    procs = [
        subprocess.Popen(
            command + [str(rank)],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for rank in range(2)
    ]
    for proc in procs:
        _, err = proc.communicate(timeout=600)
        assert proc.returncode == 0, err[-3000:]
    shares = [json.loads((out / f"summary.{rank}.json").read_text())["logs"] for rank in (0, 1)]
    logs_seen = sorted(row["log"] for share in shares for row in share)
    assert logs_seen == ["broken.csv", "healthy.npz", "stuck.csv", "stuck_bag"]
    assert [len(share) for share in shares] == [2, 2]
