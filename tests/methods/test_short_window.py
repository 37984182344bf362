"""Short-window RMI from the measured state (issue 7, the paper's section 4 proposal)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rmijax
from rmijax.methods.short_window import short_window_bounds, start_error_bounds, transition_powers

from helpers import random_arm, random_gains
from reference_numpy import PlanarArmNumpy, closed_loop, corners_of, pick, problem_args


def short_window_reference(
    model, traj, params, readings, *, mode, window, v_lo, v_hi, end_steps, start="measured"
):
    """Short-window RMI written plainly: loops over end steps, outputs and window steps.

    SPEC section 5 with the tracks started from ``readings[k0]`` (own joint
    only in per_joint mode), widened by the reading noise pushed through
    ``A_i^(t_f - k0)`` in interval arithmetic, plus the output noise.
    """
    q_d, qd_d, qdd_d, kp, kd, dt, nominal = problem_args(traj, params)
    n = q_d.shape[1]
    corners = corners_of(np.asarray(params.lo), np.asarray(params.hi))
    u_d, x_n, qdd_n = closed_loop(q_d, qd_d, qdd_d, kp, kd, dt)
    starts = x_n if start == "nominal" else np.asarray(readings)
    a_joint = [np.array([[1.0, dt], [-kp[i] * dt, 1.0 - kd[i] * dt]]) for i in range(n)]

    def gv_all(q, qd, u):  # (K, n) perturbation of every joint
        v = u - kd * qd - kp * q
        tau = model.mass_matrix(q, nominal)[0] @ v + model.bias(q, qd, nominal)[0]
        mh, hh = model.mass_matrix(q, corners), model.bias(q, qd, corners)
        return np.linalg.solve(mh, (tau[None, :] - hh)[..., None])[..., 0] - v[None, :], v

    def gv_own(i, xi, k):  # per_joint: others on the nominal trajectory
        q, qd = x_n[k, :, 0].copy(), x_n[k, :, 1].copy()
        q[i], qd[i] = xi
        v = u_d[k] - kd * qd - kp * q
        tau = model.mass_matrix(q, nominal)[0] @ v + model.bias(q, qd, nominal)[0]
        mh, hh = model.mass_matrix(q, corners), model.bias(q, qd, corners)
        others = sum(mh[:, i, j] * qdd_n[k, j] for j in range(n) if j != i)
        return (tau[i] - others - hh[:, i]) / mh[:, i, i] - v[i], v[i]

    lower, upper = {}, {}
    for t_f in end_steps:
        k0 = max(0, t_f - window)
        for i in range(n):
            power = np.linalg.matrix_power(a_joint[i], t_f - k0)
            for s in range(2):
                weights = {t_f: np.eye(2)[s]}
                for k in range(t_f - 1, k0, -1):
                    weights[k] = a_joint[i].T @ weights[k + 1]
                ends = []
                for largest in (True, False):
                    x = starts[k0].copy() if mode == "coupled" else starts[k0, i].copy()
                    for k in range(k0, t_f):
                        w = weights[k + 1][1]
                        if mode == "coupled":
                            gv, v = gv_all(x[:, 0], x[:, 1], u_d[k])
                            chosen = gv[pick(w * gv[:, i], w * v[i], largest)]
                            for j in range(n):
                                x[j] = a_joint[j] @ x[j] + np.array([0.0, dt]) * (
                                    u_d[k, j] + chosen[j]
                                )
                        else:
                            gv, v_i = gv_own(i, x, k)
                            chosen = gv[pick(w * gv, w * v_i, largest)]
                            x = a_joint[i] @ x + np.array([0.0, dt]) * (u_d[k, i] + chosen)
                    ends.append(x[i, s] if mode == "coupled" else x[s])
                widen_hi = widen_lo = 0.0
                if start == "measured":  # true start = reading - noise
                    for j in range(2):
                        products = (power[s, j] * -v_hi[i, j], power[s, j] * -v_lo[i, j])
                        widen_hi += max(products)
                        widen_lo += min(products)
                upper[t_f, i, s] = ends[0] + widen_hi + v_hi[i, s]
                lower[t_f, i, s] = ends[1] + widen_lo + v_lo[i, s]
    return lower, upper


@pytest.fixture(scope="module")
def arm():
    params = rmijax.paper_arm2()
    th = rmijax.experiments.paper_true_parameters(params)
    return params, th


def random_problem(rng, n, duration):
    kp, kd = random_gains(rng, n)
    paths = list(rng.choice(["sine", "composite", "slow_sine", "hold"], n))
    traj = rmijax.trajectory(paths, duration=duration, kp=kp, kd=kd)
    params = random_arm(rng, n)
    th = rng.uniform(np.asarray(params.lo), np.asarray(params.hi))
    noise_lo = -rng.uniform(0.0, 2e-3, (n, 2))
    noise_hi = rng.uniform(0.0, 2e-3, (n, 2))
    _, readings = rmijax.simulate(traj, params, th, noise_lo=noise_lo, noise_hi=noise_hi, seed=3)
    return traj, params, readings, noise_lo, noise_hi


@pytest.mark.parametrize("mode", rmijax.MODES)
@pytest.mark.parametrize("n, window", [(1, 2), (2, 2), (2, 5), (3, 3)])
def test_equals_plain_reference(rng, n, window, mode):
    traj, params, readings, noise_lo, noise_hi = random_problem(rng, n, duration=0.3)
    bounds = short_window_bounds(
        traj, params, readings, mode=mode, window=window, noise_lo=noise_lo, noise_hi=noise_hi
    )
    end_steps = [0, 1, window - 1, window, window + 1, 17, traj.n_steps]
    lower, upper = short_window_reference(
        PlanarArmNumpy(n),
        traj,
        params,
        readings,
        mode=mode,
        window=window,
        v_lo=noise_lo,
        v_hi=noise_hi,
        end_steps=end_steps,
    )
    for (t_f, i, s), value in upper.items():
        assert float(bounds.upper[t_f, i, s]) == pytest.approx(value, abs=1e-10)
        assert float(bounds.lower[t_f, i, s]) == pytest.approx(lower[t_f, i, s], abs=1e-10)
    np.testing.assert_array_equal(bounds.nominal, traj.x_n)
    assert float(jnp.max(bounds.width[1:] - (noise_hi - noise_lo)[None])) > 1e-6


@pytest.mark.parametrize("mode", rmijax.MODES)
def test_nominal_start_with_window_100_is_rmi(arm, mode):
    params, _ = arm
    traj = rmijax.trajectory(["hold", "sine"], duration=1.5)
    noise = dict(noise_lo=[-1e-4, -2e-3], noise_hi=[3e-4, 1e-3])
    exact = rmijax.rmi(traj, params, mode=mode, **noise)
    short = short_window_bounds(traj, params, None, mode=mode, window=100, start="nominal", **noise)
    for key in ("lower", "upper", "nominal", "crossed"):
        np.testing.assert_array_equal(getattr(short, key), getattr(exact, key))
    assert short.dt == exact.dt


@pytest.mark.parametrize("mode", rmijax.MODES)
@pytest.mark.parametrize("window", [1, 2, 9])
def test_noise_free_nominal_readings_equal_nominal_start(arm, mode, window):
    params, _ = arm
    traj = rmijax.trajectory(["slow_sine", "composite"], duration=0.5)
    measured = short_window_bounds(traj, params, traj.x_n, mode=mode, window=window)
    nominal = short_window_bounds(traj, params, None, mode=mode, window=window, start="nominal")
    np.testing.assert_array_equal(measured.lower, nominal.lower)
    np.testing.assert_array_equal(measured.upper, nominal.upper)


@pytest.mark.parametrize("window", [1, 2, 6])
def test_zero_width_box_is_the_linear_loop_widened_by_the_noise(rng, window):
    """No parameter error: each band is ``A^m y(k0) + inputs`` plus the noise intervals."""
    params = rmijax.paper_arm2()
    params = params.with_box(lo=params.nominal, hi=params.nominal)
    traj = rmijax.trajectory(["hold", "sine"], duration=0.3)
    n_samples = traj.n_steps + 1
    readings = np.asarray(traj.x_n) + rng.uniform(-0.01, 0.01, (n_samples, 2, 2))
    noise_lo, noise_hi = np.array([-1e-3, -4e-3]), np.array([2e-3, 1e-3])
    bounds = short_window_bounds(
        traj, params, readings, window=window, noise_lo=noise_lo, noise_hi=noise_hi
    )
    kp, kd, dt, u_d = np.asarray(traj.kp), np.asarray(traj.kd), traj.dt, np.asarray(traj.u_d)
    for t_f in range(n_samples):
        k0 = max(0, t_f - window)
        for i in range(2):
            a = np.array([[1.0, dt], [-kp[i] * dt, 1.0 - kd[i] * dt]])
            x = readings[k0, i].copy()
            for k in range(k0, t_f):
                x = a @ x + np.array([0.0, dt]) * u_d[k, i]
            power = np.linalg.matrix_power(a, t_f - k0)
            spread = np.abs(power) @ (noise_hi - noise_lo)  # width of A^m [-hi, -lo]
            centre = x - power @ (noise_hi + noise_lo) / 2.0
            np.testing.assert_allclose(
                bounds.upper[t_f, i], centre + spread / 2 + noise_hi, rtol=0, atol=1e-12
            )
            np.testing.assert_allclose(
                bounds.lower[t_f, i], centre - spread / 2 + noise_lo, rtol=0, atol=1e-12
            )


def test_start_error_bounds_by_enumerating_the_noise_box(rng):
    kp, kd = (jnp.asarray(g) for g in random_gains(rng, 3))
    powers = transition_powers(kp, kd, 0.01, 7)
    noise_lo = jnp.asarray(-rng.uniform(0.0, 0.1, (3, 2)))
    noise_hi = jnp.asarray(rng.uniform(-0.05, 0.1, (3, 2)))
    noise_hi = jnp.maximum(noise_hi, noise_lo)
    low, high = start_error_bounds(powers, noise_lo, noise_hi)
    assert low.shape == high.shape == (8, 3, 2)
    for m in (0, 1, 7):
        for i in range(3):
            a = np.array([[1.0, 0.01], [-float(kp[i]) * 0.01, 1.0 - float(kd[i]) * 0.01]])
            np.testing.assert_allclose(powers[m, i], np.linalg.matrix_power(a, m), atol=1e-14)
            errors = [  # the four corners of [-hi, -lo]: a linear map's extremes
                -np.array([float(position), float(velocity)])
                for position in (noise_lo[i, 0], noise_hi[i, 0])
                for velocity in (noise_lo[i, 1], noise_hi[i, 1])
            ]
            images = np.array([np.linalg.matrix_power(a, m) @ e for e in errors])
            np.testing.assert_allclose(high[m, i], images.max(axis=0), rtol=0, atol=1e-15)
            np.testing.assert_allclose(low[m, i], images.min(axis=0), rtol=0, atol=1e-15)


def test_paper_fault_case_alarms_after_onset(arm):
    """Two-joint arm, hold/sine, stuck_sensors on joint 2 at 3 s (SPEC section 10)."""
    params, th = arm
    traj = rmijax.trajectory(["hold", "sine"], duration=5.0)
    _, clean = rmijax.simulate(traj, params, th)
    quiet = rmijax.detect(clean, short_window_bounds(traj, params, clean))
    assert quiet.first_alarm is None and quiet.false_alarms == 0
    fault = rmijax.Fault("stuck_sensors", 1, 3.0)
    x_true, readings = rmijax.simulate(traj, params, th, faults=[fault])
    report = rmijax.detect(
        readings, short_window_bounds(traj, params, readings), onset=fault.onset, x_true=x_true
    )
    assert report.false_alarms == 0
    assert report.latency is not None and np.isfinite(report.latency)
    assert report.latency <= 0.05  # measured: 0.00 s, on joint 2's tachometer
    assert report.alarm_output[0] == 1


def test_under_jit_equals_eager(arm):
    params, th = arm
    traj = rmijax.trajectory(["hold", "sine"], duration=0.5)
    _, readings = rmijax.simulate(traj, params, th, noise_lo=-1e-3, noise_hi=1e-3)
    eager = short_window_bounds(traj, params, readings, noise_lo=-1e-3, noise_hi=1e-3)
    jitted = jax.jit(lambda y: short_window_bounds(traj, params, y, noise_lo=-1e-3, noise_hi=1e-3))(
        readings
    )
    np.testing.assert_allclose(jitted.upper, eager.upper, rtol=0, atol=1e-14)
    np.testing.assert_allclose(jitted.lower, eager.lower, rtol=0, atol=1e-14)


def test_progress_and_chunks_give_the_same_bounds(arm):
    params, th = arm
    traj = rmijax.trajectory(["hold", "sine"], duration=0.4)
    _, readings = rmijax.simulate(traj, params, th)
    plain = short_window_bounds(traj, params, readings, window=3)
    chunked = short_window_bounds(traj, params, readings, window=3, chunk_size=7, progress=True)
    np.testing.assert_allclose(chunked.upper, plain.upper, rtol=0, atol=1e-14)
    np.testing.assert_allclose(chunked.lower, plain.lower, rtol=0, atol=1e-14)


def test_bad_readings(arm):
    params, th = arm
    traj = rmijax.trajectory(["hold", "sine"], duration=0.2)
    _, readings = rmijax.simulate(traj, params, th)
    bad = np.array(readings)
    bad[7, 1, 0] = np.nan
    with pytest.raises(ValueError, match=r"readings are not finite from step 7 on \(joint 1 enc"):
        short_window_bounds(traj, params, bad)
    with pytest.raises(ValueError, match="diverged run"):
        short_window_bounds(traj, params, bad)
    with pytest.raises(ValueError, match=r"readings must have shape \(T\+1, n, 2\) = \(21, 2, 2\)"):
        short_window_bounds(traj, params, readings[:-1])
    with pytest.raises(ValueError, match=r"got shape \(21, 2\)"):
        short_window_bounds(traj, params, readings[..., 0])
    with pytest.raises(ValueError, match="readings are required with start='measured'"):
        short_window_bounds(traj, params, None)
    with pytest.raises(ValueError, match="readings must have shape"):
        short_window_bounds(traj, params, readings[:3], start="nominal")


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(start="reading"), "unknown start 'reading'"),
        (dict(window=0), "window must be an integer number of steps >= 1"),
        (dict(mode="joint"), "unknown mode 'joint'"),
        (dict(noise_lo=[0.0, 0.2], noise_hi=0.1), "noise_lo > noise_hi for joint 0 tachometer"),
        (dict(noise_hi=np.zeros(3)), "noise_hi must be a scalar"),
    ],
)
def test_bad_options(arm, kwargs, match):
    params, th = arm
    traj = rmijax.trajectory(["hold", "sine"], duration=0.1)
    _, readings = rmijax.simulate(traj, params, th)
    with pytest.raises(ValueError, match=match):
        short_window_bounds(traj, params, readings, **kwargs)
