"""The command line reproduces the paper's fault case and writes its report."""

import json

import matplotlib
import numpy as np
import pytest

import rmijax
from rmijax.apps import cli
from rmijax.apps.plotting import plot_bands, plot_comparison, save_figure

matplotlib.use("Agg")


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli")
    assert (
        cli.main(["--quick", "--draws", "4", "--runs", "3", "--no-progress", "--out", str(out)])
        == 0
    )
    return out, json.loads((out / "report.json").read_text())


def test_cli_writes_report_and_figures(report):
    out, data = report
    for name in data["figures"]:
        assert (out / name).stat().st_size > 10_000
    assert len(data["figures"]) == 7 + 3 + 2
    markdown = (out / "report.md").read_text()
    assert "Every fault kind on both joints" in markdown
    assert len(data["fault_table"]) == 2 * len(rmijax.FAULT_KINDS)
    assert set(data["containment"]) == set(rmijax.experiments.PAPER_RUNS)


def test_cli_reproduces_the_paper_fault_case(report):
    _, data = report
    runs = data["paper_fault_runs"]
    assert runs["fault_free"]["rmi_coupled"]["false_alarms"] == 0
    assert runs["stuck_sensors_joint2"]["rmi_coupled"]["latency_s"] <= 0.05
    joint1 = runs["stuck_sensors_joint1"]["rmi_coupled"]
    assert joint1["false_alarms"] == 0 and joint1["alarm_output"] == "joint 2 encoder"
    assert 1.0 <= joint1["latency_s"] <= 3.0


def test_cli_help_and_bad_onset(capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(["--help"])
    assert info.value.code == 0 and "--persistence" in capsys.readouterr().out
    with pytest.raises(SystemExit) as info:
        cli.main(["--quick", "--onset", "7", "--out", "/tmp/unused-rmijax"])
    assert info.value.code == 2 and "--onset must lie inside" in capsys.readouterr().err


def test_plots_draw_every_panel(tmp_path):
    traj = rmijax.trajectory(["hold", "sine"], duration=1.0)
    bounds = rmijax.rmi(traj, rmijax.paper_arm2(), window=20)
    fig = plot_bands(
        traj.t,
        bounds,
        x_true=bounds.nominal,
        relative=True,
        onset=0.5,
        alarm=0.7,
        zoom=1.0,
        title="test",
    )
    assert len(fig.axes) == 4
    low, high = fig.axes[0].get_ylim()
    width = float(np.max(bounds.width[:, 0, 0]))
    assert high - low == pytest.approx(3 * width, rel=0.05)  # band plus one width each side
    assert save_figure(fig, tmp_path / "bands.png").stat().st_size > 5_000
    fig = plot_comparison(traj.t, bounds, bounds, sensors=(1,), joints=[1])
    assert len(fig.axes) == 1
