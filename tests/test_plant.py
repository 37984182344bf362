"""Plant simulation and faults (SPEC section 7) against a plain NumPy simulation."""

import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import rmijax

from reference_numpy import PlanarArmNumpy, problem_args, simulate_faults


@pytest.fixture(scope="module")
def arm():
    return rmijax.paper_arm2(), rmijax.trajectory(["slow_sine", "composite"], duration=2.0)


def paper_truth(params):
    return rmijax.experiments.paper_true_parameters(params)


def test_fault_free_nominal_run_equals_rmi_nominal(arm):
    params, traj = arm
    x_true, y_meas = rmijax.simulate(traj, params, params.nominal)
    bounds = rmijax.rmi(traj, params, window=20)
    np.testing.assert_allclose(x_true, bounds.nominal, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(y_meas, x_true)  # no noise, no fault: readings are exact


CASES = [
    [rmijax.Fault("stuck_encoder", 0, 0.5)],
    [rmijax.Fault("stuck_tach", 1, 0.7)],
    [rmijax.Fault("stuck_sensors", 1, 1.0)],
    [rmijax.Fault("bias", 0, 0.4, value=0.02, sensor=0)],
    [rmijax.Fault("drift", 1, 0.3, value=-0.1, sensor=1)],
    [rmijax.Fault("free_swinging", 1, 1.2)],
    [rmijax.Fault("locked", 0, 0.8)],
    [
        rmijax.Fault("locked", 1, 0.5),
        rmijax.Fault("bias", 0, 0.2, value=0.01, sensor=1),
        rmijax.Fault("stuck_encoder", 1, 1.5),
    ],
]


@pytest.mark.parametrize("faults", CASES, ids=lambda fs: "+".join(f.kind for f in fs))
def test_faults_equal_numpy_simulation(arm, faults):
    params, traj = arm
    th = paper_truth(params)
    x_true, y_meas = rmijax.simulate(
        traj, params, th, faults=faults, noise_lo=[-1e-3, -1e-2], noise_hi=1e-3, seed=3
    )
    steps = [(f.kind, f.joint, int(round(f.onset / traj.dt)), f.value, f.sensor) for f in faults]
    # The same noise, drawn by the simulator with the same seed in a fault-free run.
    clean_x, clean_y = rmijax.simulate(
        traj, params, th, noise_lo=[-1e-3, -1e-2], noise_hi=1e-3, seed=3
    )
    noise = np.asarray(clean_y - clean_x)
    assert noise.shape == x_true.shape and np.abs(noise).max() > 1e-4
    assert np.all(noise[..., 0] >= -1e-3) and np.all(noise[..., 1] <= 1e-3)
    x_ref, y_ref = simulate_faults(
        PlanarArmNumpy(2),
        *problem_args(traj, params),
        th,
        steps,
        noise,
    )
    np.testing.assert_allclose(x_true, x_ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(y_meas, y_ref, rtol=0, atol=1e-9)


def test_fault_semantics(arm):
    params, traj = arm
    th = paper_truth(params)
    k = 100  # onset 1.0 s
    x, y = rmijax.simulate(traj, params, th, faults=[rmijax.Fault("stuck_sensors", 0, 1.0)])
    assert np.all(np.asarray(y[k:, 0, 0]) == float(x[k, 0, 0]))
    assert np.all(np.asarray(y[k:, 0, 1]) == 0.0)
    x, y = rmijax.simulate(traj, params, th, faults=[rmijax.Fault("locked", 1, 1.0)])
    assert np.all(np.asarray(x[k:, 1, 1]) == 0.0)
    assert np.all(np.asarray(x[k:, 1, 0]) == float(x[k, 1, 0]))
    x, y = rmijax.simulate(traj, params, th, faults=[rmijax.Fault("drift", 1, 1.0, 0.5, 0)])
    np.testing.assert_allclose(y[k:, 1, 0] - x[k:, 1, 0], 0.5 * (traj.t[k:] - 1.0), atol=1e-12)


def test_fault_free_batch_equals_numpy(arm):
    params, traj = arm
    th = rmijax.monte_carlo_parameters(params, 2, seed=1)[[0, 7, 16, 17]]
    states, readings = rmijax.simulate(traj, params, th)
    for r in range(th.shape[0]):
        x_ref, _ = simulate_faults(
            PlanarArmNumpy(2), *problem_args(traj, params), th[r], [], np.zeros(states.shape[1:])
        )
        np.testing.assert_allclose(states[r], x_ref, rtol=0, atol=1e-11)
    np.testing.assert_array_equal(readings, states)


def test_batch_equals_single_runs(arm):
    params, traj = arm
    th = rmijax.monte_carlo_parameters(params, 3, seed=1)[[0, 5, 16, 18]]
    xs, ys = rmijax.simulate(traj, params, th)
    assert xs.shape == (4, traj.n_steps + 1, 2, 2)
    for r in range(4):
        x, _ = rmijax.simulate(traj, params, th[r])
        np.testing.assert_allclose(xs[r], x, rtol=0, atol=1e-13)


def test_divergence_is_reported_not_poisoning(arm):
    params, traj = arm
    faults = [rmijax.Fault("stuck_sensors", 1, 0.2), rmijax.Fault("stuck_sensors", 0, 0.2)]
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # numpy NaN warnings would fail here
        with pytest.raises(RuntimeWarning, match=r"plant diverged .* first at t = "):
            rmijax.simulate(traj, params, params.nominal, faults=faults, divergence_limit=50.0)
    with pytest.warns(RuntimeWarning, match="diverged"):
        x, y = rmijax.simulate(traj, params, params.nominal, faults=faults, divergence_limit=50.0)
    finite = np.isfinite(np.asarray(x)).all(axis=(1, 2))
    first_bad = int(np.argmin(finite))
    assert 20 < first_bad < traj.n_steps and not finite[first_bad:].any()
    assert np.abs(np.asarray(x[:first_bad])).max() <= 50.0


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(faults=[rmijax.Fault("bias", 2, 1.0)]), ValueError, r"joint 2.*joints 0..1"),
        (dict(faults=[rmijax.Fault("bias", 0, 2.5)]), ValueError, r"onset 2.5 s, outside"),
        (dict(faults=["stuck"]), TypeError, r"faults\[0\] must be a rmijax.Fault"),
        (dict(th_true=np.ones(3)), ValueError, r"th_true must have shape \(4,\) or \(R, 4\)"),
        (dict(th_true=np.full(4, np.nan)), ValueError, "th_true contains a non-finite"),
        (dict(noise_lo=np.zeros(5)), ValueError, "noise_lo must be a scalar"),
        (dict(noise_lo=0.1, noise_hi=0.0), ValueError, "noise_lo > noise_hi for joint 0"),
    ],
)
def test_bad_simulation_inputs(arm, kwargs, error, match):
    params, traj = arm
    kwargs = {"th_true": params.nominal, **kwargs}
    with pytest.raises(error, match=match):
        rmijax.simulate(traj, params, **kwargs)


def test_unknown_fault_kind_and_outside_box():
    with pytest.raises(ValueError, match="unknown fault kind 'jammed'"):
        rmijax.Fault("jammed", 0, 1.0)
    with pytest.raises(ValueError, match="sensor must be 0"):
        rmijax.Fault("bias", 0, 1.0, sensor=2)
    params, traj = rmijax.paper_pendulum(), rmijax.trajectory("sine", duration=0.2)
    with pytest.warns(UserWarning, match=r"m1 = 12.0 outside its box \[9.0, 11.0\]"):
        rmijax.simulate(traj, params, jnp.array([12.0, 1.0]))
