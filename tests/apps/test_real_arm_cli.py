"""rmijax --robot NAME: the real-arm job refuses bad options at once and writes its report."""

import json

import numpy as np
import pytest

import rmijax
from rmijax.apps import cli, real_arm


def exit_code(argv):
    """The CLI's exit code, whether it returns it or argparse exits with it."""
    try:
        return cli.main(argv)
    except SystemExit as stop:
        return stop.code


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--robot", "atlas"], "--robot"),
        (["--robot", "ur5e", "--methods", "rmi,magic"], "--methods"),
        (["--robot", "ur5e", "--methods", ","], "--methods"),
        (["--robot", "ur5e", "--segment-time", "0"], "--segment-time"),
        (["--robot", "ur5e", "--persistence", "0"], "--persistence"),
    ],
)
def test_bad_options_are_one_line_and_exit_2(argv, message, tmp_path, capsys):
    assert exit_code([*argv, "--out", str(tmp_path / "out"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err
    assert len(err.splitlines()) == 1
    assert not (tmp_path / "out" / "report.json").exists()


@pytest.mark.slow
def test_real_arm_job_on_the_ur5e(tmp_path):
    out = tmp_path / "ur5e"
    argv = ["--robot", "ur5e", "--methods", "linearized,empirical", "--segment-time", "0.4"]
    assert cli.main([*argv, "--out", str(out), "--no-progress"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["robot"] == "ur5e"
    assert len(report["settings"]["param_names"]) == 6 + 1 + 12
    assert len(report["fault_table"]) == 6 * 7  # every kind on every joint
    assert set(report["methods"]) == {"linearized", "empirical"}
    for name in report["figures"]:
        assert (out / name).stat().st_size > 10_000
    # the true robot differs from the nominal one, so some fault is caught by each method
    for method in ("linearized", "empirical"):
        latencies = [row["results"][method]["latency_s"] for row in report["fault_table"]]
        assert any(x is not None for x in latencies)
    rows = real_arm.summary_by_kind(report)
    assert {row["kind"] for row in rows} == set(rmijax.FAULT_KINDS)
    assert "| fault | method |" in (out / "report.md").read_text()
    assert np.isfinite(report["methods"]["linearized"]["median_width"]["encoder_rad"])
