"""The method comparison: its pieces on small cases, and one end-to-end pendulum case."""

import dataclasses
import math
import re

import numpy as np
import pytest

import rmijax
from rmijax.apps.experiments import paper_true_parameters
from rmijax.detection.suite import default_fault_suite
from rmijax.evaluation.comparison import (
    Case,
    _Containment,
    _timed_bounds,
    compare,
    prefix,
    summary_rows,
)
from rmijax.methods.base import DivergedError


def test_prefix_bounds_equal_the_start_of_the_whole_run():
    params = rmijax.paper_arm2()
    traj = rmijax.trajectory(["hold", "sine"], duration=1.5)
    short = prefix(traj, 60)
    assert short.n_steps == 60
    whole, part = rmijax.rmi(traj, params), rmijax.rmi(short, params)
    np.testing.assert_array_equal(np.asarray(part.upper), np.asarray(whole.upper)[:61])
    np.testing.assert_array_equal(np.asarray(part.lower), np.asarray(whole.lower)[:61])
    with pytest.raises(ValueError, match="steps must be in"):
        prefix(traj, 0)


def test_containment_counts():
    band = rmijax.Bounds(
        lower=np.zeros((3, 1, 2)),
        upper=np.ones((3, 1, 2)),
        nominal=np.full((3, 1, 2), 0.5),
        crossed=np.zeros((3, 1, 2), bool),
        dt=0.01,
    )
    states = np.full((4, 3, 1, 2), 0.5)
    states[1, 2, 0, 1] = 1.5  # half a band width above
    states[2, 0, 0, 0] = np.nan  # a diverged run is never inside
    count = _Containment()
    count.add(states, band)
    result = count.result()
    assert result["runs"] == 4
    assert result["inside"] == pytest.approx(22 / 24)
    assert result["clean_runs"] == pytest.approx(2 / 4)
    assert result["worst"] == np.inf


def _detections(traj, params, th_true, faults, band_of):
    """Latency of each fault with each method's band, recomputed with the public API."""
    latencies = {}
    for fault in faults:
        x_true, y_meas = rmijax.simulate(traj, params, th_true, faults=[fault])
        for method, band in band_of(y_meas).items():
            found = rmijax.detect(y_meas, band, onset=fault.onset, x_true=x_true)
            latencies.setdefault(method, []).append(found.latency)
    return latencies


def test_pendulum_case_end_to_end():
    """Every score of ``compare`` equals the same quantity recomputed independently from
    the public API (bands, simulate, containment, detect) on the same draws and faults."""
    params = rmijax.paper_pendulum()
    traj = rmijax.trajectory("sine", duration=1.0)
    th_true = paper_true_parameters(params)
    case = Case("pendulum", params, traj, th_true)
    methods = ("rmi", "empirical", "short_window", "constant_corners")
    times = [0.5, 0.9]
    result = compare(
        case,
        methods,
        onsets=(0.4,),
        draws=30,
        times=times,
        short_window_runs=3,
        worst_options=dict(random_starts=2, iterations=10),
        timing_steps=20,
        log=None,
    )
    assert result["n"] == 1 and result["K"] == 4 and result["T"] == 100
    assert result["diverged"] == {}
    faults = default_fault_suite(1, 0.4)
    assert [f["fault"] for f in result["faults"]] == [f.label for f in faults]

    bands = {m: rmijax.bounds(traj, params, method=m) for m in methods if m != "short_window"}
    th = rmijax.monte_carlo_parameters(params, 30, seed=0, corners=True)  # compare's draws
    states = np.asarray(rmijax.simulate(traj, params, th)[0])
    steps = np.rint(np.asarray(times) / traj.dt).astype(int)
    low = np.asarray(result["worst_case"]["low"])
    high = np.asarray(result["worst_case"]["high"])

    def held(y):  # compare builds short_window bands from readings with NaN held
        y = np.array(y)
        for k in range(1, y.shape[0]):
            y[k] = np.where(np.isfinite(y[k]), y[k], y[k - 1])
        return y

    def band_of(y_meas):
        sw = rmijax.bounds(traj, params, method="short_window", readings=held(y_meas))
        return {**bands, "short_window": sw}

    latencies = _detections(traj, params, th_true, faults, band_of)
    for method in methods:
        m = result["methods"][method]
        # containment of the Monte-Carlo runs (short_window: its first 3 runs, own bands)
        if method == "short_window":
            parts = [
                rmijax.containment(
                    run[None], rmijax.bounds(traj, params, method=method, readings=run)
                )
                for run in states[:3]
            ]
            inside = np.mean([p["inside"] for p in parts])
            clean = np.mean([p["clean_runs"] for p in parts])
            worst, runs = max(p["worst"] for p in parts), 3
        else:
            whole = rmijax.containment(states, bands[method])
            inside, clean, worst, runs = (
                whole[k] for k in ("inside", "clean_runs", "worst", "runs")
            )
            # tightness against the worst-case table
            lower = np.asarray(bands[method].lower)[steps]
            upper = np.asarray(bands[method].upper)[steps]
            contained = np.concatenate(
                [(low >= lower - 1e-9).ravel(), (high <= upper + 1e-9).ravel()]
            )
            assert m["worst_points_inside"] == pytest.approx(contained.mean())
            ratio = (upper - lower) / (high - low)
            for s, sensor in enumerate(("encoder", "tachometer")):
                assert m["width_over_worst"][sensor]["median"] == pytest.approx(
                    np.median(ratio[..., s]), rel=1e-12
                )
        assert m["containment"]["runs"] == runs == (3 if method == "short_window" else 34)
        assert m["containment"]["inside"] == pytest.approx(inside, rel=1e-12)
        assert m["containment"]["clean_runs"] == pytest.approx(clean, rel=1e-12)
        assert m["containment"]["worst"] == pytest.approx(worst, rel=1e-9, abs=1e-15)
        # detection over the suite: same latencies, same detected share
        assert [r[method]["latency"] for r in result["faults"]] == pytest.approx(latencies[method])
        found = [v for v in latencies[method] if v is not None]
        assert m["detected"] == pytest.approx(len(found) / len(faults))
        assert m["median_latency"] == (pytest.approx(np.median(found)) if found else None)
    rows = summary_rows([result])
    assert [r["method"] for r in rows] == list(methods)


def _pendulum_case(params=None, duration=1.0):
    params = params or rmijax.paper_pendulum()
    traj = rmijax.trajectory("sine", duration=duration)
    return Case("pendulum", params, traj, paper_true_parameters(params))


def test_certified_is_scored_on_its_whole_run():
    """``certified`` in the comparison: its cost is its whole run's seconds over ``T``,
    and on the pendulum no Monte-Carlo sample or worst-case point leaves its band, which
    is at least as wide as the worst case found and not much wider."""
    case = _pendulum_case()
    result = compare(
        case,
        ("certified",),
        onsets=(0.4,),
        draws=30,
        times=[0.5, 0.9],
        worst_options=dict(random_starts=2, iterations=10),
        probe_steps=20,
        log=None,
    )
    assert result["diverged"] == {} and result["not_supported"] == {}
    m = result["methods"]["certified"]
    assert m["cost_basis"] == "whole_run"
    assert m["seconds_per_step"] == m["whole_run_s"] / case.traj.n_steps
    assert m["whole_run_s"] > 0 and m["whole_run_first_s"] > 0
    assert m["containment"]["runs"] == 34  # 4 corners + 30 draws
    assert m["containment"]["inside"] == 1.0
    assert m["containment"]["clean_runs"] == 1.0
    assert m["containment"]["worst"] == 0.0
    assert m["worst_points_inside"] == 1.0
    for sensor in ("encoder", "tachometer"):
        ratio = m["width_over_worst"][sensor]
        assert 1.0 <= ratio["min"] <= ratio["median"] <= ratio["max"] < 1.5
    band = rmijax.bounds(case.traj, case.params, method="certified")
    mean_width = np.asarray(band.width).mean(axis=(0, 1))
    np.testing.assert_allclose(m["mean_width"], mean_width, rtol=1e-12)
    (row,) = summary_rows([result])
    assert row["status"] == "scored" and row["cost_basis"] == "whole run / T"
    assert row["ms_per_step"] == m["seconds_per_step"] * 1e3
    assert row["mc_inside"] == 1.0 and row["enc_width_over_worst"] >= 1.0


def test_a_method_that_diverges_is_reported_and_the_others_scored():
    """On a box 3x around the nominal ``certified``'s remainder diverges: the prefix probe
    says so at the step where the whole run diverges, its row says diverged, and
    ``empirical`` is still scored on the case."""
    params = rmijax.paper_pendulum()
    nominal = np.asarray(params.nominal)
    wide = rmijax.uncertain_robot(params.model, nominal, nominal / 3, nominal * 3)
    case = _pendulum_case(wide)
    result = compare(
        case,
        ("empirical", "certified"),
        onsets=(0.4,),
        draws=10,
        times=[0.5],
        worst_options=dict(random_starts=0, iterations=5),
        probe_steps=20,
        log=None,
    )
    message = result["diverged"]["certified"]
    assert "found on the first 20 of 100 steps" in message
    assert list(result["methods"]) == ["empirical"] and result["not_supported"] == {}
    scored_in_faults = {"fault", "kind", "joint", "onset", "empirical"}
    assert result["faults"] and all(set(row) == scored_in_faults for row in result["faults"])
    step = re.search(r"\(step \d+,", message).group()
    with pytest.raises(DivergedError) as whole:
        rmijax.bounds(case.traj, wide, method="certified")
    assert step in str(whole.value)  # the probe's verdict is the whole run's
    with pytest.raises(DivergedError) as probed:  # the probe's error keeps where it happened
        _timed_bounds(case, "certified", None, {}, 5, 20)
    where = (probed.value.step, probed.value.joint, probed.value.sensor)
    assert where == (whole.value.step, whole.value.joint, whole.value.sensor)
    assert probed.value.step is not None and probed.value.step < 20
    rows = summary_rows([result])
    assert [(r["method"], r["status"], r["cost_basis"]) for r in rows] == [
        ("empirical", "scored", "end step"),
        ("certified", "diverged", "-"),
    ]
    assert rows[0]["ms_per_step"] > 0 and 0.0 <= rows[0]["mc_inside"] <= 1.0  # scored
    assert math.isnan(rows[1]["ms_per_step"]) and math.isnan(rows[1]["mc_inside"])


def test_an_unsupported_method_is_reported_not_dropped():
    """A model without the planar structure: ``certified`` refuses it before computing
    anything, and the result says so; with nothing left to score nothing is simulated."""
    params = rmijax.paper_pendulum()
    model = dataclasses.replace(params.model, structure=None)  # declares nothing
    other = rmijax.uncertain_robot(model, params.nominal, params.lo, params.hi)
    result = compare(_pendulum_case(other, duration=0.3), ("certified",), log=None)
    assert "planar" in result["not_supported"]["certified"]
    assert result["methods"] == {} and result["diverged"] == {}
    assert result["worst_case"] is None and result["faults"] == []
    (row,) = summary_rows([result])
    assert (row["method"], row["status"]) == ("certified", "not supported")
    assert math.isnan(row["enc_width_over_worst"]) and math.isnan(row["detected"])


@pytest.mark.parametrize("warm", [True, False])
def test_whole_run_methods_are_called_twice_warm_and_once_cold(monkeypatch, warm):
    """``warm=False`` (``benchmarks/methods.py --cold-only``) calls a whole-run method
    once, and its cost is that call over ``T``, labelled so; warm, the second of two
    calls. The band is the same either way."""
    import rmijax.evaluation.comparison as comparison

    calls = []

    def counted(traj, params, **kwargs):
        calls.append(traj.n_steps)
        return rmijax.bounds(traj, params, **kwargs)

    monkeypatch.setattr(comparison, "bounds", counted)
    case = _pendulum_case(duration=0.3)
    band, cost = _timed_bounds(case, "certified", None, {}, 5, 0, warm=warm)
    assert calls == [case.traj.n_steps] * (2 if warm else 1)
    expected = rmijax.bounds(case.traj, case.params, method="certified")
    np.testing.assert_array_equal(np.asarray(band.upper), np.asarray(expected.upper))
    seconds = cost["whole_run_s"] if warm else cost["whole_run_first_s"]
    assert cost["seconds_per_step"] == seconds / case.traj.n_steps
    assert cost["cost_basis"] == ("whole_run" if warm else "whole_run_cold")
    assert ("whole_run_s" in cost) == warm and cost["whole_run_first_s"] > 0
    scored = {
        "seconds_per_step": cost["seconds_per_step"],
        "cost_basis": cost["cost_basis"],
        "width_over_worst": {s: {"median": 1.0} for s in ("encoder", "tachometer")},
        "worst_points_inside": 1.0,
        "containment": {"inside": 1.0, "clean_runs": 1.0, "worst": 0.0},
        "detected": 1.0,
        "median_latency": None,
        "false_alarms_fault_free": 0,
        "false_alarms_fault_runs": 0,
    }
    (row,) = summary_rows([{"case": "p", "n": 1, "methods": {"certified": scored}}])
    assert row["cost_basis"] == ("whole run / T" if warm else "cold whole run / T")
