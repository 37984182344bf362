"""Trajectories and the nominal closed loop (SPEC sections 3 and 6)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rmijax

from reference_numpy import closed_loop


def test_grid_and_named_paths():
    traj = rmijax.trajectory(["sine", "ramp", "composite", "slow_sine", "hold"])
    assert traj.n_steps == 1500 and traj.t.shape == (1501,)
    t = np.arange(1501) * 0.01
    np.testing.assert_allclose(traj.t, t, rtol=0, atol=1e-12)
    expected_q = np.stack(
        [np.sin(t), t, np.sin(t) + np.cos(0.5 * t) + 0.1 * (15 - t), np.sin(0.2 * t), 0 * t], -1
    )
    expected_qd = np.stack(
        [
            np.cos(t),
            1 + 0 * t,
            np.cos(t) - 0.5 * np.sin(0.5 * t) - 0.1,
            0.2 * np.cos(0.2 * t),
            0 * t,
        ],
        -1,
    )
    expected_qdd = np.stack(
        [-np.sin(t), 0 * t, -np.sin(t) - 0.25 * np.cos(0.5 * t), -0.04 * np.sin(0.2 * t), 0 * t],
        -1,
    )
    np.testing.assert_allclose(traj.q_d, expected_q, atol=1e-13)
    np.testing.assert_allclose(traj.qd_d, expected_qd, atol=1e-13)
    np.testing.assert_allclose(traj.qdd_d, expected_qdd, atol=1e-13)


def test_nominal_recursion_and_acceleration_identity(rng):
    kp, kd = rng.uniform(50, 150, 2), rng.uniform(10, 30, 2)
    traj = rmijax.trajectory(["slow_sine", "composite"], duration=3.0, dt=0.02, kp=kp, kd=kd)
    u_d, x_n, qdd_n = closed_loop(
        np.asarray(traj.q_d), np.asarray(traj.qd_d), np.asarray(traj.qdd_d), kp, kd, 0.02
    )
    np.testing.assert_allclose(traj.u_d, u_d, atol=1e-12)
    np.testing.assert_allclose(traj.x_n, x_n, atol=1e-12)
    np.testing.assert_allclose(traj.qdd_n, qdd_n, atol=1e-11)
    # qdd_n(k) = (qd_n(k+1) - qd_n(k)) / dt
    finite = (traj.x_n[1:, :, 1] - traj.x_n[:-1, :, 1]) / 0.02
    np.testing.assert_allclose(traj.qdd_n[:-1], finite, atol=1e-9)
    np.testing.assert_array_equal(traj.x_n[0, :, 0], traj.q_d[0])


def test_custom_function_and_samples_agree():
    fn = lambda t: 0.3 * jnp.sin(2.0 * t) + 0.1 * t**2  # noqa: E731
    traj = rmijax.trajectory([fn, "hold"], duration=2.0, kp=[80.0, 120.0], kd=18.0)
    t = np.asarray(traj.t)
    np.testing.assert_allclose(traj.qd_d[:, 0], 0.6 * np.cos(2 * t) + 0.2 * t, atol=1e-13)
    np.testing.assert_allclose(traj.qdd_d[:, 0], -1.2 * np.sin(2 * t) + 0.2, atol=1e-13)
    again = rmijax.trajectory_from_samples(
        traj.q_d, traj.qd_d, traj.qdd_d, dt=0.01, kp=[80.0, 120.0], kd=18.0
    )
    np.testing.assert_array_equal(again.x_n, traj.x_n)
    np.testing.assert_array_equal(again.kd, [18.0, 18.0])


def test_float32_trajectory():
    traj = rmijax.trajectory("sine", dtype=jnp.float32)
    assert traj.x_n.dtype == jnp.float32 and traj.kp.dtype == jnp.float32


def test_unstable_step_names_gains_and_dt():
    with pytest.raises(ValueError, match=r"kp=100, kd=20, dt=0.3 .*spectral radius of 2"):
        rmijax.trajectory("sine", dt=0.3)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(paths=["sine", "wobble"]), "unknown path 'wobble'"),
        (dict(paths=["sine", "sine"], kp=[1.0, 2.0, 3.0]), r"kp has shape \(3,\)"),
        (dict(paths="sine", duration=0.001), "at least one step"),
        (dict(paths="sine", dt=-0.01), "dt must be a positive"),
        (dict(paths=[lambda t: jnp.log(t - 1.0)]), "non-finite"),
        (dict(paths=[lambda t: jnp.stack([t, t])]), "must return a scalar"),
        (dict(paths=[3.0]), "must be a path name"),
    ],
)
def test_bad_paths(kwargs, match):
    with pytest.raises((ValueError, TypeError), match=match):
        rmijax.trajectory(**kwargs)


def test_bad_samples():
    q = np.zeros((11, 2))
    with pytest.raises(ValueError, match=r"qd_d must have shape \(11, 2\)"):
        rmijax.trajectory_from_samples(q, np.zeros((11, 3)), q, dt=0.01)
    bad = q.copy()
    bad[4, 1] = np.nan
    with pytest.raises(ValueError, match=r"qdd_d contains a non-finite value .* index \(4, 1\)"):
        rmijax.trajectory_from_samples(q, q, bad, dt=0.01)
    with pytest.raises(ValueError, match=r"kd must be a scalar or have shape \(2,\)"):
        rmijax.trajectory_from_samples(q, q, q, dt=0.01, kd=[1.0, 2.0, 3.0])


def test_trajectory_is_a_pytree_with_static_step():
    traj = rmijax.trajectory(["sine", "hold"], duration=1.0)
    assert traj.labels == ("sine", "hold")
    leaves, treedef = jax.tree_util.tree_flatten(traj)
    assert len(leaves) == 9  # arrays only; dt and labels live in the treedef
    doubled = jax.jit(lambda tr: dataclasses.replace(tr, kp=tr.kp * 2))(traj)
    assert doubled.dt == 0.01
    np.testing.assert_array_equal(doubled.kp, [200.0, 200.0])


def test_waypoint_trajectory_is_a_rest_to_rest_minimum_jerk_move():
    points = np.array([[0.0, 0.5, -0.3], [0.8, -0.2, 0.1], [0.8, -0.2, 0.1], [-0.4, 0.3, 0.6]])
    times = np.array([0.0, 1.5, 2.0, 3.2])
    traj = rmijax.waypoint_trajectory(points, times=times, dt=0.001)
    assert traj.q_d.shape == (3201, 3)
    for point, t in zip(points, times, strict=True):
        k = int(round(t / 0.001))
        np.testing.assert_allclose(traj.q_d[k], point, atol=1e-12)
        np.testing.assert_allclose(traj.qd_d[k], 0.0, atol=1e-12)
        np.testing.assert_allclose(traj.qdd_d[k], 0.0, atol=1e-9)
    # the dwell between identical waypoints holds still
    dwell = slice(1500, 2001)
    np.testing.assert_allclose(traj.q_d[dwell], points[1][None].repeat(501, 0), atol=1e-12)
    # velocities and accelerations are the derivatives of the positions (central differences,
    # away from the waypoints where the jerk jumps)
    q, qd = np.asarray(traj.q_d), np.asarray(traj.qd_d)
    smooth = np.ones(3199, bool)
    for t in times:
        k = int(round(t / 0.001))
        smooth[max(k - 2, 0) : k + 1] = False
    np.testing.assert_allclose(((q[2:] - q[:-2]) / 0.002)[smooth], qd[1:-1][smooth], atol=2e-5)
    accel = np.asarray(traj.qdd_d)[1:-1]
    np.testing.assert_allclose(((qd[2:] - qd[:-2]) / 0.002)[smooth], accel[smooth], atol=2e-4)
    # the minimum-jerk peak speed is 15/8 of the mean speed
    np.testing.assert_allclose(
        np.max(np.abs(qd[:1501]), 0), 1.875 * np.abs(points[1] - points[0]) / 1.5, rtol=1e-5
    )


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(waypoints=[[0.0, 1.0]]), "shape"),
        (dict(waypoints=[[0.0], [np.nan]]), "NaN"),
        (dict(waypoints=[[0.0], [1.0]], times=[0.0, 1.0, 2.0]), "one arrival time"),
        (dict(waypoints=[[0.0], [1.0]], times=[0.5, 1.0]), "start at 0"),
        (dict(waypoints=[[0.0], [1.0], [2.0]], times=[0.0, 1.0, 1.0]), "increase strictly"),
        (dict(waypoints=[[0.0], [1.0]], segment_time=-1.0), "segment_time"),
        (dict(waypoints=[[0.0], [1.0]], dt=0.0), "dt"),
    ],
)
def test_waypoint_trajectory_refuses_bad_input(kwargs, message):
    with pytest.raises(ValueError, match=message):
        rmijax.waypoint_trajectory(**kwargs)
