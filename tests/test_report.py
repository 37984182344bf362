"""The published tables are the results files: documents match benchmarks/report.py."""

import shutil

import pytest

from helpers import ROOT, load_benchmark

report = load_benchmark("report")


def test_documents_match_results():
    """Every generated table of the README, the benchmark notes, the method docs and the
    comparison's conclusions (and the notebook cell that shows them) is what
    ``python benchmarks/report.py`` renders from ``benchmarks/results/*.json``."""
    diffs = report.differences()
    assert not diffs, "run `python benchmarks/report.py`:\n" + "\n".join(diffs)[:6000]


def _copy_documents(tmp_path):
    for document in [*report.BLOCKS, report.NOTEBOOK]:
        target = tmp_path / document
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(ROOT / document, target)


def test_a_doctored_table_is_caught(tmp_path):
    _copy_documents(tmp_path)
    assert report.differences(tmp_path) == []
    readme = tmp_path / "README.md"
    text = readme.read_text()
    start = text.index("<!-- report:scaling ")
    row = text.index("| 2 | 16 |", start)  # the 2-link row of the generated scaling table
    end = text.index("\n", row)
    doctored = text[:row] + text[row:end].replace("1 kHz", "2 kHz") + text[end:]
    assert doctored != text
    readme.write_text(doctored)
    diffs = report.differences(tmp_path)
    assert len(diffs) == 1 and "README.md (committed)" in diffs[0] and "2 kHz" in diffs[0]


def test_a_block_without_markers_is_refused(tmp_path):
    _copy_documents(tmp_path)
    readme = tmp_path / "README.md"
    readme.write_text(readme.read_text().replace("<!-- report:methods ", "<!-- methods "))
    with pytest.raises(ValueError, match="no markers for generated block"):
        report.differences(tmp_path)


@pytest.mark.parametrize(
    "p99_ms, rate",
    [(0.112, "1 kHz"), (0.999, "1 kHz"), (1.0, "500 Hz"), (5.6, "100 Hz"), (33.7, "20 Hz"),
     (339.3, "2 Hz"), (1000.0, "below 1 Hz")],
)  # fmt: skip
def test_real_time_rate_is_the_highest_whose_tick_exceeds_p99(p99_ms, rate):
    assert report.real_time_rate(p99_ms) == rate


def _scored(**cost):
    sensor = {"median": 1.02, "min": 1.0, "max": 1.1}
    return {
        "seconds_per_step": 0.0125,
        **cost,
        "width_over_worst": {"encoder": sensor, "tachometer": sensor},
        "worst_points_inside": 1.0,
        "containment": {"inside": 1.0, "clean_runs": 1.0, "worst": 0.0, "runs": 1016},
        "detected": 0.93,
    }


def test_whole_run_cost_and_refusals_are_labelled():
    """``certified``'s cost cell says it is a whole run over its steps; a diverged or
    unsupported method gets a row saying so instead of disappearing."""
    whole = _scored(cost_basis="whole_run", whole_run_s=12.5, whole_run_first_s=20.0)
    scored = {"T": 1000, "methods": {"rmi": _scored(), "certified": whole}}
    rows = report._case_rows("preset2", scored)
    assert [r[1] for r in rows] == ["`rmi`", "`certified`"]
    assert rows[0][2] == "12.5 ms"
    assert rows[1][2] == "12.5 ms (whole run: 12.5 s / 1000 steps)"
    assert rows[1][3] == "1.02 / 1.02" and rows[1][5] == "100.00%"
    cold = _scored(cost_basis="whole_run_cold", whole_run_first_s=12.5)  # --cold-only
    rows = report._case_rows("preset2", {"T": 1000, "methods": {"certified": cold}})
    assert rows[0][2] == "12.5 ms (one cold whole run: 12.5 s / 1000 steps)"
    message = "certified bounds are not finite (step 16, joint 0 tachometer): diverged [probe]"
    refused = {"T": 1000, "methods": {"rmi": _scored()}, "diverged": {"certified": message}}
    rows = report._case_rows("preset4", refused)
    assert rows[1] == ("preset4", "`certified`", "diverged at step 16", *["-"] * 6)
    unsupported = {"T": 1000, "methods": {}, "not_supported": {"certified": "planar only"}}
    assert report._case_rows("arm", unsupported)[0][2] == "not supported"
    assert report._refusal(scored, "certified") is None


def test_results_files_record_the_host_speed(tmp_path):
    """``write_json`` adds the host's reference speed, measured as the file is written,
    and the provenance table shows it (or says it was not recorded, for older files)."""
    common = load_benchmark("_common")
    path = tmp_path / "run.json"
    common.write_json(str(path), [{"x": 1}], {"command": "python benchmarks/x.py"})
    records, meta = common.read_json(path)
    reference = meta["host_reference"]
    assert records == [{"x": 1}] and meta["command"] == "python benchmarks/x.py"
    assert 0.1 < reference["matmul_gflops"] < 1e4  # any CPU from the last 20 years
    assert 0.1 < reference["dispatch_us"] < 1e5
    shown = report._host_reference(meta)
    assert shown == (f"{reference['matmul_gflops']:.0f} GFLOP/s, {reference['dispatch_us']:.0f} us")
    assert report._host_reference({"command": "old"}) == "not recorded"
