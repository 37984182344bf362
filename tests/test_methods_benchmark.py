"""benchmarks/methods.py: one case's records from several result files are joined."""

import pytest

from helpers import load_benchmark

methods = load_benchmark("methods")

WORST = {"times": [1.0, 2.0], "low": [[[-1.0, -2.0]]] * 2, "high": [[[1.0, 2.0]]] * 2}


def _record(scored, diverged=(), worst=WORST, latency=0.1):
    return {
        "case": "preset2",
        "n": 2,
        "K": 16,
        "T": 1000,
        "dt": 0.01,
        "methods": {m: {"seconds_per_step": 1e-3} for m in scored},
        "diverged": {m: "bounds are not finite (step 9, joint 0 encoder)" for m in diverged},
        "not_supported": {},
        "worst_case": worst if scored else None,
        "faults": [
            {"fault": f"stuck j{j}", **{m: {"latency": latency} for m in scored}} for j in (1, 2)
        ]
        if scored
        else [],
    }


def test_one_case_from_two_files_is_one_record():
    first = [_record(["rmi", "empirical"])]
    refused = {**_record([], ["certified"]), "case": "preset4"}
    second = [_record(["certified"], latency=0.2), refused]
    merged = methods.merge_cases([first, second])
    assert [r["case"] for r in merged] == ["preset2", "preset4"]
    assert list(merged[0]["methods"]) == ["rmi", "empirical", "certified"]
    assert [row["certified"]["latency"] for row in merged[0]["faults"]] == [0.2, 0.2]
    assert [row["rmi"]["latency"] for row in merged[0]["faults"]] == [0.1, 0.1]
    assert merged[0]["worst_case"] == WORST
    assert merged[1]["methods"] == {} and "certified" in merged[1]["diverged"]
    assert set(first[0]["faults"][0]) == {"fault", "rmi", "empirical"}  # inputs left alone


def test_disagreeing_records_are_refused():
    base = [_record(["rmi"])]
    with pytest.raises(ValueError, match="worst-case tables differ"):
        other = {**WORST, "high": [[[1.0, 2.1]]] * 2}
        methods.merge_cases([base, [_record(["certified"], worst=other)]])
    with pytest.raises(ValueError, match="in two files"):
        methods.merge_cases([base, [_record(["rmi"])]])
    with pytest.raises(ValueError, match="T differs"):
        methods.merge_cases([base, [{**_record(["certified"]), "T": 400}]])
