"""The envelope of constant-corner runs (issue 7): containment by construction, brute force."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rmijax
from rmijax.methods.constant_corners import constant_corner_bounds, corner_of_index

from helpers import random_arm, random_gains
from reference_numpy import PlanarArmNumpy, closed_loop, corners_of, problem_args


def window_envelope_reference(model, traj, params, window, end_steps):
    """Every corner held constant over RMI's window from ``x_n(k0)``, written plainly."""
    q_d, qd_d, qdd_d, kp, kd, dt, nominal = problem_args(traj, params)
    corners = corners_of(np.asarray(params.lo), np.asarray(params.hi))
    u_d, x_n, _ = closed_loop(q_d, qd_d, qdd_d, kp, kd, dt)
    low, high = {}, {}
    for t_f in end_steps:
        k0 = max(0, t_f - window)
        states = np.repeat(x_n[k0][None], len(corners), axis=0)  # (K, n, 2)
        for k in range(k0, t_f):
            for c, th in enumerate(corners):
                q, qd = states[c, :, 0].copy(), states[c, :, 1].copy()
                v = u_d[k] - kd * qd - kp * q
                tau = model.mass_matrix(q, nominal)[0] @ v + model.bias(q, qd, nominal)[0]
                qdd = np.linalg.solve(model.mass_matrix(q, th)[0], tau - model.bias(q, qd, th)[0])
                states[c, :, 0] = q + dt * qd
                states[c, :, 1] = qd + dt * qdd
        low[t_f], high[t_f] = states.min(axis=0), states.max(axis=0)
    return low, high


def run_envelope_reference(model, traj, params):
    """Every corner held constant from ``x(0) = x_d(0)`` over the whole run, written
    plainly (explicit Euler of the true plant under the nominal computed torque, SPEC
    sections 3 and 7): the runs' minimum and maximum per step, (T+1, n, 2) each."""
    q_d, qd_d, qdd_d, kp, kd, dt, nominal = problem_args(traj, params)
    corners = corners_of(np.asarray(params.lo), np.asarray(params.hi))
    u_d = qdd_d + kd * qd_d + kp * q_d
    states = np.repeat(np.stack([q_d[0], qd_d[0]], axis=-1)[None], len(corners), axis=0)
    low, high = [states.min(axis=0)], [states.max(axis=0)]
    for k in range(traj.n_steps):
        for c, th in enumerate(corners):
            q, qd = states[c, :, 0].copy(), states[c, :, 1].copy()
            v = u_d[k] - kd * qd - kp * q
            tau = model.mass_matrix(q, nominal)[0] @ v + model.bias(q, qd, nominal)[0]
            qdd = np.linalg.solve(model.mass_matrix(q, th)[0], tau - model.bias(q, qd, th)[0])
            states[c, :, 0] = q + dt * qd
            states[c, :, 1] = qd + dt * qdd
        low.append(states.min(axis=0))
        high.append(states.max(axis=0))
    return np.stack(low), np.stack(high)


@pytest.fixture(scope="module")
def arm_run():
    params = rmijax.paper_arm2()
    traj = rmijax.trajectory(["hold", "sine"], duration=3.0)
    return params, traj, run_envelope_reference(PlanarArmNumpy(2), traj, params)


@pytest.mark.parametrize("chunk_size, progress", [(None, False), (1, False), (5, True)])
def test_run_horizon_is_the_envelope_of_the_corner_runs(arm_run, chunk_size, progress):
    """The band is the envelope of every constant-corner robot, checked against an
    independent plant (the NumPy reference), not against ``rmijax.simulate``, whose
    step the method shares."""
    params, traj, (low, high) = arm_run
    bounds = constant_corner_bounds(traj, params, chunk_size=chunk_size, progress=progress)
    np.testing.assert_allclose(bounds.lower, low, rtol=0, atol=1e-10)
    np.testing.assert_allclose(bounds.upper, high, rtol=0, atol=1e-10)
    np.testing.assert_array_equal(bounds.nominal, traj.x_n)
    assert not bool(jnp.any(bounds.crossed)) and bounds.dt == traj.dt
    assert float(jnp.min(bounds.width[50:])) > 1e-5  # the box is not degenerate


def test_corner_of_index_is_the_corner_tensor(rng):
    params = random_arm(rng, 3)
    index = jnp.arange(params.n_corners, dtype=jnp.int32)
    corners = jax.vmap(corner_of_index, in_axes=(0, None, None))(index, params.lo, params.hi)
    np.testing.assert_array_equal(corners, params.corners)


@pytest.mark.parametrize("n, window, chunk_size", [(1, 9, None), (2, 12, None), (2, 12, 3)])
def test_window_horizon_equals_brute_force(rng, n, window, chunk_size):
    kp, kd = random_gains(rng, n)
    paths = list(rng.choice(["sine", "composite", "slow_sine"], n))
    traj = rmijax.trajectory(paths, duration=0.3, kp=kp, kd=kd)
    params = random_arm(rng, n)
    bounds = constant_corner_bounds(
        traj, params, horizon="window", window=window, chunk_size=chunk_size
    )
    end_steps = [0, 1, 7, window, window + 3, traj.n_steps]
    low, high = window_envelope_reference(PlanarArmNumpy(n), traj, params, window, end_steps)
    for t_f in end_steps:
        np.testing.assert_allclose(bounds.lower[t_f], low[t_f], rtol=0, atol=1e-10)
        np.testing.assert_allclose(bounds.upper[t_f], high[t_f], rtol=0, atol=1e-10)
    np.testing.assert_array_equal(bounds.lower[0], traj.x_n[0])  # an empty window
    assert float(jnp.max(bounds.width)) > 1e-5


def test_window_horizon_longer_than_the_run_is_the_run(arm_run):
    params, traj, _ = arm_run
    short = rmijax.trajectory(["hold", "sine"], duration=0.5)
    whole = constant_corner_bounds(short, params)
    windowed = constant_corner_bounds(short, params, horizon="window", window=80)
    np.testing.assert_allclose(windowed.lower, whole.lower, rtol=0, atol=1e-13)
    np.testing.assert_allclose(windowed.upper, whole.upper, rtol=0, atol=1e-13)


@pytest.mark.parametrize("horizon", ["run", "window"])
def test_zero_width_box_gives_the_nominal(horizon):
    params = rmijax.paper_arm2()
    params = params.with_box(lo=params.nominal, hi=params.nominal)
    traj = rmijax.trajectory(["slow_sine", "composite"], duration=1.0)
    bounds = constant_corner_bounds(traj, params, horizon=horizon, window=20)
    np.testing.assert_allclose(bounds.lower, traj.x_n, rtol=0, atol=1e-12)
    np.testing.assert_allclose(bounds.upper, traj.x_n, rtol=0, atol=1e-12)


@pytest.mark.parametrize("horizon", ["run", "window"])
def test_noise_shifts_the_bounds(horizon):
    params = rmijax.paper_pendulum()
    traj = rmijax.trajectory(["sine"], duration=0.5)
    noise_lo, noise_hi = np.array([[-1e-3, -0.02]]), np.array([2e-3, 0.01])
    plain = constant_corner_bounds(traj, params, horizon=horizon, window=15)
    noisy = constant_corner_bounds(
        traj, params, horizon=horizon, window=15, noise_lo=noise_lo, noise_hi=noise_hi
    )
    np.testing.assert_array_equal(noisy.upper, plain.upper + noise_hi[None, None, :])
    np.testing.assert_array_equal(noisy.lower, plain.lower + noise_lo[None])
    np.testing.assert_array_equal(noisy.nominal, plain.nominal)


def test_diverging_corner_is_refused():
    """A mass box down to 3% of the nominal makes the loop's effective gains 30x: unstable."""
    params = rmijax.planar_arm([10.0, 1.0], [0.3, 0.99], [11.0, 1.01])
    traj = rmijax.trajectory(["sine"], duration=1.0)
    with pytest.raises(
        rmijax.DivergedError, match=r"constant-corner run diverged .* by step \d+ \(t = "
    ) as err:
        constant_corner_bounds(traj, params)
    said = re.search(r"by step (\d+) .*joint (\d+) (\w+)\)", str(err.value)).groups()
    assert (err.value.step, err.value.joint, err.value.sensor) == (int(said[0]), 0, said[2])


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(horizon="forever"), "unknown horizon 'forever'"),
        (dict(window=0), "window must be an integer number of steps >= 1"),
        (dict(window=2.5), "window must be"),
        (dict(chunk_size=0), "chunk_size must be an integer number of corners >= 1"),
        (dict(noise_lo=[0.0, 0.2], noise_hi=0.1), "noise_lo > noise_hi for joint 0 tachometer"),
        (dict(noise_hi=np.zeros(3)), "noise_hi must be a scalar"),
    ],
)
def test_bad_options(kwargs, match):
    traj = rmijax.trajectory(["sine"], duration=0.1)
    with pytest.raises(ValueError, match=match):
        constant_corner_bounds(traj, rmijax.paper_pendulum(), **kwargs)


def test_bad_robot_or_trajectory():
    traj = rmijax.trajectory(["sine"], duration=0.1)
    with pytest.raises(ValueError, match="traj has 1 joints but params describes a 2-joint"):
        constant_corner_bounds(traj, rmijax.paper_arm2())
    with pytest.raises(TypeError, match="params must be a rmijax.UncertainRobot"):
        constant_corner_bounds(traj, np.ones(4))
    with pytest.raises(TypeError, match="traj must be a rmijax.Trajectory"):
        constant_corner_bounds(np.zeros((11, 1)), rmijax.paper_pendulum())
    with pytest.raises(ValueError, match="2\\^32 corners are out of reach"):
        constant_corner_bounds(
            rmijax.trajectory(["hold"] * 16, duration=0.1), rmijax.preset_arm(16)
        )
