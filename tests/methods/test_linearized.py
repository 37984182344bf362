"""The linearized method: first-order parameter sensitivity of the windowed closed loop."""

import dataclasses
import itertools
import re

import jax.numpy as jnp
import numpy as np
import pytest

import rmijax
from rmijax.methods import linearized
from rmijax.methods.linearized import linearized_bounds

# A robot whose perturbation is affine in the parameters and independent of the
# state: constant mass matrix, bias = C th + a state term without th. Then
# gv = M0^-1 C (th_n - th) and every windowed output is affine in th, so the
# linearisation is exact and its band is the envelope of the corner runs.
MASS = np.array([[2.0, 0.3], [0.3, 1.2]])
COUPLING = np.array([[1.5, -0.8, 0.4, 0.0], [0.2, 0.6, -1.1, 0.9]])
NOMINAL = np.array([1.0, 0.5, -0.3, 2.0])
LO = np.array([0.8, 0.45, -0.5, 2.0])  # th[3] certain
HI = np.array([1.3, 0.52, -0.2, 2.0])


def affine_state_term(q, qd, xp):
    return xp.stack([5.0 * xp.cos(q[0]) + 0.5 * qd[1] ** 2, 2.0 * xp.sin(q[0] + q[1])])


def affine_model():
    mass, coupling = jnp.asarray(MASS), jnp.asarray(COUPLING)
    return rmijax.RobotModel(
        n_joints=2,
        n_params=4,
        mass_matrix=lambda q, th: mass + 0.0 * q[0],
        bias=lambda q, qd, th: coupling @ th + affine_state_term(q, qd, jnp),
        name="affine_toy",
    )


def affine_window_numpy(traj, th, t_f, window):
    """The window of end step ``t_f`` run plainly for constant ``th``: x(t_f) (2, 2)."""
    u, x_n = np.asarray(traj.u_d), np.asarray(traj.x_n)
    kp, kd, dt = np.asarray(traj.kp), np.asarray(traj.kd), traj.dt
    k0 = max(0, t_f - window)
    q, qd = x_n[k0, :, 0].copy(), x_n[k0, :, 1].copy()
    for k in range(k0, t_f):
        v = u[k] - kd * qd - kp * q
        tau = MASS @ v + COUPLING @ NOMINAL + affine_state_term(q, qd, np)
        qdd = np.linalg.solve(MASS, tau - COUPLING @ th - affine_state_term(q, qd, np))
        q, qd = q + dt * qd, qd + dt * qdd
    return np.stack([q, qd], axis=-1)


def test_margin_corner_ties_take_lo_whatever_the_rounding():
    """A parameter an output does not depend on has terms equal in exact arithmetic;
    their rounding sign must not choose the remainder margin's corner (it did: on the
    Panda job 476 coordinates changed side with a change of the solve's rounding)."""
    lo, hi = jnp.array([1.0, -2.0, 0.5]), jnp.array([3.0, -1.0, 0.75])
    for tiny in (1e-18, -1e-18, 1e-14, -1e-14):  # rounding-size gaps, either sign
        up = jnp.array([[[0.7, 0.5 * tiny, -0.2]]])
        down = jnp.array([[[-0.7, -0.5 * tiny, 0.1]]])
        corners = np.asarray(linearized.margin_corners(up, down, lo, hi))
        np.testing.assert_array_equal(corners[0, 0, 0], [3.0, -2.0, 0.5])  # max: hi, tie, lo
        np.testing.assert_array_equal(corners[1, 0, 0], [1.0, -2.0, 0.75])  # min: lo, tie, hi
    # a gap just above the tolerance (eps^(2/3) of the linear range 1.7) is no tie
    gap = 2.0 * np.finfo(np.float64).eps ** (2.0 / 3.0) * 1.7
    up = jnp.array([[[0.7, 0.5 * gap, -0.2]]])
    down = jnp.array([[[-0.7, -0.5 * gap, 0.1]]])
    corners = np.asarray(linearized.margin_corners(up, down, lo, hi))
    assert corners[0, 0, 0, 1] == -1.0 and corners[1, 0, 0, 1] == -2.0


@pytest.mark.parametrize("window", [7, 60])
def test_exact_for_model_linear_in_parameters(window):
    params = rmijax.uncertain_robot(affine_model(), NOMINAL, LO, HI)
    traj = rmijax.trajectory(["sine", "composite"], duration=0.3, kp=[80.0, 120.0], kd=18.0)
    corners = [np.where(bits, HI, LO) for bits in itertools.product([0, 1], repeat=4)]
    runs = np.array(
        [
            [affine_window_numpy(traj, th, t_f, window) for th in corners]
            for t_f in range(traj.n_steps + 1)
        ]
    )  # (T+1, K, n, 2)
    bounds = linearized_bounds(traj, params, window=window, margin=False)
    np.testing.assert_allclose(bounds.upper, runs.max(axis=1), rtol=0, atol=1e-12)
    np.testing.assert_allclose(bounds.lower, runs.min(axis=1), rtol=0, atol=1e-12)
    np.testing.assert_allclose(bounds.nominal, traj.x_n, rtol=0, atol=0)
    widened = linearized_bounds(traj, params, window=window, margin=True)
    np.testing.assert_allclose(widened.upper, bounds.upper, rtol=0, atol=1e-12)  # margin ~ 0
    np.testing.assert_allclose(widened.lower, bounds.lower, rtol=0, atol=1e-12)
    assert float(jnp.min(bounds.width[1:, :, 1])) > 1e-4  # every tachometer band is open


def simulated_outputs(traj, params, th):
    """True states (R, T+1, n, 2) from ``rmijax.simulate``: the window of every end step
    when the window reaches back to the start of the run."""
    states, _ = rmijax.simulate(traj, params, np.asarray(th))
    return np.asarray(states)


ARMS = {
    "pendulum": (["sine"], rmijax.paper_pendulum),
    "arm2": (["hold", "sine"], rmijax.paper_arm2),
    "arm3": (["slow_sine", "composite", "sine"], lambda: rmijax.preset_arm(3)),
}


@pytest.mark.parametrize("arm", sorted(ARMS))
def test_first_order_band_equals_finite_difference_sensitivity(arm):
    paths, make = ARMS[arm]
    params, traj = make(), rmijax.trajectory(paths, duration=0.8)
    nominal, p = np.asarray(params.nominal), params.n_params
    step = 1e-5 * nominal
    shifted = np.concatenate([nominal + np.diag(step), nominal - np.diag(step)])
    runs = simulated_outputs(traj, params, shifted)
    sens = (runs[:p] - runs[p:]) / (2.0 * step)[:, None, None, None]  # (p, T+1, n, 2)
    up = sens * (np.asarray(params.hi) - nominal)[:, None, None, None]
    down = sens * (np.asarray(params.lo) - nominal)[:, None, None, None]
    y_n = np.asarray(traj.x_n)
    bounds = linearized_bounds(traj, params, window=traj.n_steps, margin=False)
    np.testing.assert_allclose(bounds.upper, y_n + np.maximum(up, down).sum(0), rtol=0, atol=1e-8)
    np.testing.assert_allclose(bounds.lower, y_n + np.minimum(up, down).sum(0), rtol=0, atol=1e-8)


def _scaled_box(params, scale):
    nominal = np.asarray(params.nominal)
    lo = nominal - scale * (nominal - np.asarray(params.lo))
    hi = nominal + scale * (np.asarray(params.hi) - nominal)
    return params.with_box(lo=lo, hi=hi)


@pytest.mark.parametrize("arm", sorted(ARMS))
def test_planar_arm_near_corner_envelope_with_second_order_remainder(arm):
    """The first-order band misses the corner envelope by a second-order remainder: at
    most 5% of the output's widest band (measured 0.8-2.9%), and 10x smaller when the box
    shrinks 4x (measured 16.6-17.6x; a first-order error would shrink only 4x)."""
    paths, make = ARMS[arm]
    traj = rmijax.trajectory(paths, duration=1.0)
    errors = []
    for scale in (1.0, 0.25):
        params = _scaled_box(make(), scale)
        runs = simulated_outputs(traj, params, params.corners)
        top, bottom = runs.max(axis=0), runs.min(axis=0)
        widest = (top - bottom).max(axis=0)  # (n, 2) per output over the run
        pure = linearized_bounds(traj, params, window=traj.n_steps, margin=False)
        error = np.maximum(np.abs(pure.upper - top), np.abs(pure.lower - bottom))
        assert np.all(error <= 0.05 * widest)
        errors.append(error.max())
        if scale == 1.0:
            widened = linearized_bounds(traj, params, window=traj.n_steps, margin=True)
            up_margin = np.asarray(widened.upper - pure.upper)
            down_margin = np.asarray(pure.lower - widened.lower)
            assert up_margin.min() >= 0.0 and down_margin.min() >= 0.0
            assert up_margin.max() > 1e-6 and down_margin.max() > 1e-6  # the arm is not affine
            assert np.all(up_margin <= 0.05 * widest) and np.all(down_margin <= 0.05 * widest)
            if arm == "pendulum":  # monotone outputs: th* is the extreme corner, band holds it
                assert np.all(np.asarray(widened.upper) >= top - 1e-12)
                assert np.all(np.asarray(widened.lower) <= bottom + 1e-12)
    assert errors[0] >= 10.0 * errors[1]


@pytest.mark.parametrize("margin", [False, True])
@pytest.mark.parametrize("n", [1, 2, 3])
def test_zero_width_box_gives_nominal(n, margin):
    params = rmijax.preset_arm(n)
    params = params.with_box(lo=params.nominal, hi=params.nominal)
    traj = rmijax.trajectory(["slow_sine", "composite", "sine"][:n], duration=1.0)
    bounds = linearized_bounds(traj, params, window=40, margin=margin)
    np.testing.assert_allclose(bounds.lower, traj.x_n, rtol=0, atol=1e-12)
    np.testing.assert_allclose(bounds.upper, traj.x_n, rtol=0, atol=1e-12)
    assert not bool(jnp.any(bounds.crossed))


def test_noise_shifts_the_band():
    params, traj = rmijax.paper_arm2(), rmijax.trajectory(["hold", "sine"], duration=0.5)
    noise_lo = np.array([[-0.01, -0.03], [-0.002, 0.0]])
    noise_hi = np.array([0.02, 0.05])
    clean = linearized_bounds(traj, params, window=20)
    noisy = linearized_bounds(traj, params, window=20, noise_lo=noise_lo, noise_hi=noise_hi)
    np.testing.assert_allclose(noisy.upper, clean.upper + noise_hi[None, None, :], atol=1e-15)
    np.testing.assert_allclose(noisy.lower, clean.lower + noise_lo[None], atol=1e-15)
    np.testing.assert_array_equal(noisy.nominal, clean.nominal)


def test_batching_and_progress_do_not_change_bounds():
    params, traj = rmijax.paper_arm2(), rmijax.trajectory(["hold", "composite"], duration=0.4)
    default = linearized_bounds(traj, params, window=15)
    for options in (dict(chunk_size=7), dict(chunk_size=1000), dict(progress=True)):
        other = linearized_bounds(traj, params, window=15, **options)
        np.testing.assert_allclose(other.upper, default.upper, rtol=0, atol=1e-13)
        np.testing.assert_allclose(other.lower, default.lower, rtol=0, atol=1e-13)


def test_solved_dynamics_equal_closed_form():
    """Above CLOSED_FORM_MAX_JOINTS the windows solve M qdd = tau - h; same bounds.

    This ran in a subprocess to dodge an XLA compiler crash late in the full suite; the
    crash was the process running out of memory maps (``vm.max_map_count``) after
    thousands of compiled programs, which ``tests/conftest.py`` now prevents by clearing
    JAX's caches after every module (this module compiles about 200 programs and ends
    with about 750 maps, far below the limit of 65530), so the check runs in process.
    """
    params = rmijax.preset_arm(3)
    traj = rmijax.trajectory(["hold", "composite", "sine"], duration=0.4)
    solved_model = linearized.differentiable_model(params.model, closed_form_max_joints=0)
    assert solved_model.forward_dynamics is None
    assert linearized.differentiable_model(params.model, 3) is params.model
    solved = dataclasses.replace(params, model=solved_model)
    closed = linearized_bounds(traj, params, window=15)
    other = linearized_bounds(traj, solved, window=15)
    np.testing.assert_allclose(other.upper, closed.upper, rtol=0, atol=1e-12)
    np.testing.assert_allclose(other.lower, closed.lower, rtol=0, atol=1e-12)
    assert float(jnp.max(closed.width)) > 1e-4


@pytest.mark.slow
def test_sixteen_links_zero_width_and_open_band():
    params = rmijax.preset_arm(16)
    traj = rmijax.trajectory(["slow_sine"] + ["composite"] * 15, duration=0.05)
    bounds = linearized_bounds(traj, params, window=3)
    assert bounds.upper.shape == (6, 16, 2)
    assert float(jnp.min(bounds.width[1:, :, 1])) > 0.0
    certain = params.with_box(lo=params.nominal, hi=params.nominal)
    flat = linearized_bounds(traj, certain, window=3)
    np.testing.assert_allclose(flat.upper, traj.x_n, rtol=0, atol=1e-12)


def test_bad_input_is_refused():
    params, traj = rmijax.paper_arm2(), rmijax.trajectory(["hold", "sine"], duration=0.2)
    with pytest.raises(ValueError, match="mode='coupled'.*per_joint"):
        linearized_bounds(traj, params, mode="per_joint")
    with pytest.raises(ValueError, match="window must be an integer number of steps >= 1"):
        linearized_bounds(traj, params, window=0)
    with pytest.raises(ValueError, match="window"):
        linearized_bounds(traj, params, window=2.5)
    with pytest.raises(ValueError, match="noise_lo > noise_hi"):
        linearized_bounds(traj, params, noise_lo=0.1, noise_hi=0.0)
    with pytest.raises(ValueError, match="noise_hi must be a scalar"):
        linearized_bounds(traj, params, noise_hi=np.zeros(3))
    with pytest.raises(ValueError, match="chunk_size"):
        linearized_bounds(traj, params, chunk_size=0)
    with pytest.raises(ValueError, match="2 joints but params describes a 1-joint"):
        linearized_bounds(traj, rmijax.paper_pendulum())
    with pytest.raises(TypeError, match="params must be a rmijax.UncertainRobot"):
        linearized_bounds(traj, params.nominal)


def test_diverging_window_is_refused():
    """A mass box down to 0.1% of the nominal makes the loop's effective gains 1000x:
    the windows overflow, and the method says so instead of returning NaN."""
    params = rmijax.planar_arm([10.0, 1.0], [0.01, 0.99], [11.0, 1.01])
    traj = rmijax.trajectory(["sine"], duration=1.5)
    with pytest.raises(
        rmijax.DivergedError, match=r"linearized bounds are not finite \(end step \d+, joint 0"
    ) as err:
        linearized_bounds(traj, params)
    said = re.search(r"end step (\d+), joint 0 (\w+)\)", str(err.value)).groups()
    assert (err.value.step, err.value.joint, err.value.sensor) == (int(said[0]), 0, said[1])
