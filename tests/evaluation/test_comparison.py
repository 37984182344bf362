"""The method comparison: its pieces on small cases, and one end-to-end pendulum case."""

import numpy as np
import pytest

import rmijax
from rmijax.apps.experiments import paper_true_parameters
from rmijax.evaluation.comparison import Case, _Containment, compare, prefix, summary_rows


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


def test_pendulum_case_end_to_end():
    params = rmijax.paper_pendulum()
    traj = rmijax.trajectory("sine", duration=1.0)
    case = Case("pendulum", params, traj, paper_true_parameters(params))
    methods = ("rmi", "empirical", "short_window", "constant_corners")
    result = compare(
        case,
        methods,
        onsets=(0.4,),
        draws=30,
        times=[0.5, 0.9],
        short_window_runs=3,
        worst_options=dict(random_starts=2, iterations=10),
        timing_steps=20,
        log=None,
    )
    assert result["n"] == 1 and result["K"] == 4 and result["T"] == 100
    assert len(result["faults"]) == len(rmijax.FAULT_KINDS)
    # the worst-case search starts from the Monte-Carlo extremes: its range holds every run
    th = rmijax.monte_carlo_parameters(params, 30, seed=0, corners=True)
    states, _ = rmijax.simulate(traj, params, th)
    values = np.asarray(states)[:, [50, 90]]
    low = np.asarray(result["worst_case"]["low"])
    high = np.asarray(result["worst_case"]["high"])
    assert np.all(low <= values.min(axis=0) + 1e-12)
    assert np.all(high >= values.max(axis=0) - 1e-12)
    # constant_corners is the envelope of the corner runs: it holds every corner run
    corners = rmijax.simulate(traj, params, th[:4])[0]
    band = rmijax.bounds(traj, params, method="constant_corners")
    assert np.all(np.asarray(corners) >= np.asarray(band.lower) - 1e-12)
    assert np.all(np.asarray(corners) <= np.asarray(band.upper) + 1e-12)
    for method in methods:
        m = result["methods"][method]
        assert m["seconds_per_step"] > 0
        assert m["containment"]["runs"] == (3 if method == "short_window" else 34)
        assert 0.0 <= m["detected"] <= 1.0
    rows = summary_rows([result])
    assert [r["method"] for r in rows] == list(methods)
