"""The worst_case judge: an inner estimate of the true plant's reachable range."""

import itertools

import jax.numpy as jnp
import numpy as np
import pytest

import rmijax
from rmijax.evaluation.worst_case import WorstCase, forget_steps, worst_case, worst_case_table


def simulated(traj, params, th):
    """True states (R, T+1, n, 2) of constant-parameter runs."""
    states, _ = rmijax.simulate(traj, params, np.atleast_2d(np.asarray(th)))
    return np.asarray(states)


def grid(params, points):
    """A dense grid of parameter vectors over the box: (points^p, p)."""
    lo, hi = np.asarray(params.lo), np.asarray(params.hi)
    ticks = np.linspace(0.0, 1.0, points)
    combos = np.array(list(itertools.product(ticks, repeat=lo.size)))
    return lo[None, :] + (hi - lo)[None, :] * combos


@pytest.fixture(scope="module")
def pendulum():
    return rmijax.trajectory(["sine"], duration=3.0), rmijax.paper_pendulum()


@pytest.mark.parametrize("output", [(0, 0), (0, 1)])
def test_pendulum_extremes_dominate_starts_and_match_dense_grid(pendulum, output):
    traj, params = pendulum
    rng = np.random.default_rng(7)
    lo, hi = np.asarray(params.lo), np.asarray(params.hi)
    given = lo + (hi - lo) * rng.uniform(size=(3, 2))
    dense = grid(params, 41)
    dense_runs = simulated(traj, params, dense)
    start_runs = simulated(traj, params, np.concatenate([params.corners, given, [params.nominal]]))
    for t in (0.6, 1.7, 3.0):
        k = round(t / traj.dt)
        found = worst_case(traj, params, output, t, starts=given, random_starts=2)
        assert isinstance(found, WorstCase)
        at_starts = start_runs[:, k, output[0], output[1]]
        assert found.high >= at_starts.max() - 1e-12
        assert found.low <= at_starts.min() + 1e-12
        at_grid = dense_runs[:, k, output[0], output[1]]
        reach = at_grid.max() - at_grid.min()
        assert reach > 1e-4
        # Inside the grid's envelope (it holds the corners, where the pendulum peaks) ...
        slack = 1e-9 * reach
        assert at_grid.min() - slack <= found.low <= found.high <= at_grid.max() + slack
        # ... and reaching it: the search misses no grid point.
        assert found.high >= at_grid.max() - 1e-9 * reach
        assert found.low <= at_grid.min() + 1e-9 * reach


@pytest.mark.parametrize("output, t", [((0, 0), 1.2), ((0, 1), 2.5)])
def test_parameters_lie_in_box_and_reproduce_extremes(pendulum, output, t):
    traj, params = pendulum
    found = worst_case(traj, params, output, t, random_starts=3, iterations=20)
    lo, hi = np.asarray(params.lo), np.asarray(params.hi)
    for th in (found.th_low, found.th_high):
        assert th.shape == (2,)
        assert np.all((np.asarray(th) >= lo) & (np.asarray(th) <= hi))
    runs = simulated(traj, params, np.stack([found.th_low, found.th_high]))
    k = round(t / traj.dt)
    reached = runs[:, k, output[0], output[1]]
    np.testing.assert_allclose(reached, [found.low, found.high], rtol=0, atol=1e-12)


# A robot whose output peaks inside the box: gv = k ((th - c)^2 at th_n minus at th),
# largest at th = c. The corners and the nominal miss it; only the ascent finds it.
PEAK = np.array([0.3, 0.6])


def peaked_model():
    peak = jnp.asarray(PEAK)
    return rmijax.RobotModel(
        n_joints=1,
        n_params=2,
        mass_matrix=lambda q, th: jnp.ones((1, 1)) + 0.0 * q[0],
        bias=lambda q, qd, th: jnp.stack([20.0 * jnp.sum((th - peak) ** 2) + jnp.cos(q[0])]),
        name="peaked",
    )


def test_ascent_finds_an_interior_maximum():
    params = rmijax.uncertain_robot(peaked_model(), [0.9, 0.05], [0.0, 0.0], [1.0, 1.0])
    traj = rmijax.trajectory(["sine"], duration=1.0)
    t = 0.8
    k = round(t / traj.dt)
    found = worst_case(traj, params, (0, 0), t, random_starts=0, iterations=60)
    np.testing.assert_allclose(found.th_high, PEAK, atol=5e-3)
    dense = simulated(traj, params, grid(params, 51))[:, k, 0, 0]  # holds PEAK exactly
    starts = simulated(traj, params, np.concatenate([params.corners, [params.nominal]]))[:, k, 0, 0]
    assert found.high > starts.max() + 0.1 * (dense.max() - dense.min())  # better than any start
    np.testing.assert_allclose(found.high, dense.max(), rtol=0, atol=1e-6 * np.ptp(dense))
    assert found.high <= dense.max() + 1e-12  # PEAK is the true maximum and a grid point
    assert found.low == pytest.approx(dense.min(), abs=1e-12)  # the far corner (1, 0)


def test_table_agrees_with_single_search(pendulum):
    traj, params = pendulum
    times = [0.4, 1.7, 2.6]
    table = worst_case_table(traj, params, times, random_starts=2, iterations=15, seed=3)
    assert table["low"].shape == table["high"].shape == (3, 1, 2)
    assert table["th_high"].shape == (3, 1, 2, 2)
    np.testing.assert_array_equal(table["steps"], [40, 170, 260])
    assert np.all(table["low"] < table["high"])
    for index, output in ((1, (0, 1)), (2, (0, 0))):
        single = worst_case(
            traj, params, output, times[index], random_starts=2, iterations=15, seed=3
        )
        joint, sensor = output
        assert table["high"][index, joint, sensor] == pytest.approx(single.high, abs=1e-12)
        assert table["low"][index, joint, sensor] == pytest.approx(single.low, abs=1e-12)
        np.testing.assert_allclose(table["th_high"][index, joint, sensor], single.th_high)


def test_forget_steps_is_the_first_forgotten_step():
    traj = rmijax.trajectory(["sine"], duration=15.0)
    rho = float(np.max(rmijax._checks.closed_loop_radius(traj.kp, traj.kd, traj.dt)))
    for tolerance in (1e-4, 1e-7, 1e-9):
        h = forget_steps(traj.kp, traj.kd, traj.dt, traj.n_steps, tolerance)
        assert (h + 1) * rho**h <= tolerance < h * rho ** (h - 1)
    assert forget_steps(traj.kp, traj.kd, traj.dt, 50, 1e-9) == 50  # capped at the run


def test_bad_input_is_refused(pendulum):
    traj, params = pendulum
    with pytest.raises(ValueError, match="output=.*out of range"):
        worst_case(traj, params, (1, 0), 1.0)
    with pytest.raises(ValueError, match="output=.*out of range"):
        worst_case(traj, params, (0, 2), 1.0)
    with pytest.raises(ValueError, match="output must be a"):
        worst_case(traj, params, 0, 1.0)
    with pytest.raises(ValueError, match=r"t=4\.0 s is outside the run \[0, 3\] s"):
        worst_case(traj, params, (0, 0), 4.0)
    for bad_time in (float("nan"), "soon", [1.0, 2.0]):
        with pytest.raises(ValueError, match="t must be a finite time"):
            worst_case(traj, params, (0, 0), bad_time)
    with pytest.raises(ValueError, match=r"starts must have shape \(S, 2\)"):
        worst_case(traj, params, (0, 0), 1.0, starts=np.ones((3, 5)))
    with pytest.raises(ValueError, match=r"starts\[0, 0\] = 20.0 lies outside the box"):
        worst_case(traj, params, (0, 0), 1.0, starts=[[20.0, 1.0]])
    with pytest.raises(ValueError, match="random_starts"):
        worst_case(traj, params, (0, 0), 1.0, random_starts=-1)
    with pytest.raises(ValueError, match="iterations"):
        worst_case(traj, params, (0, 0), 1.0, iterations=0)
    with pytest.raises(ValueError, match=r"times\[1\]=-1.0 s is outside the run"):
        worst_case_table(traj, params, [1.0, -1.0])
    with pytest.raises(ValueError, match="times must be a non-empty 1-D"):
        worst_case_table(traj, params, [])
    with pytest.raises(ValueError, match="2 joints but params describes a 1-joint"):
        worst_case(rmijax.trajectory(["hold", "sine"], duration=1.0), params, (0, 0), 0.5)
