"""The online monitor equals offline RMI and detection, tick by tick (issue: online monitor)."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rmijax
from rmijax.detection.monitor import METHODS as MONITOR_METHODS
from rmijax.methods.short_window import short_window_bounds


def run_monitor(mon, traj, readings):
    """The monitor inside one lax.scan over a whole run, jitted."""

    @jax.jit
    def run(desired, readings):
        state = mon.init(desired[0][0], desired[1][0])

        def tick(state, inputs):
            q_d, qd_d, qdd_d, y = inputs
            return mon.update(state, (q_d, qd_d, qdd_d), y)

        return jax.lax.scan(tick, state, (*desired, readings))

    return run((traj.q_d, traj.qd_d, traj.qdd_d), readings)


@pytest.fixture(scope="module")
def arm():
    params = rmijax.paper_arm2()
    traj = rmijax.trajectory(["hold", "sine"], duration=4.0)
    th = rmijax.experiments.paper_true_parameters(params)
    return params, traj, th


@pytest.mark.parametrize("mode", rmijax.MODES)
@pytest.mark.parametrize("fault", [None, rmijax.Fault("stuck_sensors", 1, 1.5)])
def test_monitor_equals_offline_rmi_and_detect(arm, mode, fault):
    params, traj, th = arm
    window, noise = 60, ([-1e-4, -1e-3], [1e-4, 1e-3])
    faults = [] if fault is None else [fault]
    _, y_meas = rmijax.simulate(traj, params, th, faults=faults)
    mon = rmijax.monitor(
        params,
        kp=traj.kp,
        kd=traj.kd,
        dt=traj.dt,
        mode=mode,
        window=window,
        noise_lo=noise[0],
        noise_hi=noise[1],
        persistence=2,
    )
    state, out = run_monitor(mon, traj, y_meas)
    bounds = rmijax.rmi(
        traj, params, mode=mode, window=window, noise_lo=noise[0], noise_hi=noise[1]
    )
    np.testing.assert_allclose(out.lower, bounds.lower, rtol=0, atol=1e-10)
    np.testing.assert_allclose(out.upper, bounds.upper, rtol=0, atol=1e-10)
    np.testing.assert_allclose(out.nominal, bounds.nominal, rtol=0, atol=1e-12)
    report = rmijax.detect(y_meas, bounds, persistence=2)
    np.testing.assert_array_equal(out.alarm, report.alarms)
    expected_first = -1 if report.first_alarm is None else round(report.first_alarm / traj.dt)
    assert int(state.first_alarm) == expected_first
    assert int(state.tick) == traj.n_steps + 1
    if fault is not None and mode == "coupled":
        assert 150 <= expected_first <= 200  # stuck joint-2 sensors: caught within 0.5 s


@pytest.mark.parametrize(
    "mode, window, fault",
    [
        ("coupled", None, None),
        ("coupled", None, rmijax.Fault("stuck_sensors", 1, 1.5)),
        ("per_joint", None, rmijax.Fault("stuck_sensors", 1, 1.5)),
        ("per_joint", 7, None),
        ("coupled", 7, rmijax.Fault("bias", 0, 2.0, value=0.01)),
    ],
)
def test_short_window_monitor_equals_offline(arm, mode, window, fault):
    params, traj, th = arm
    noise = ([-1e-4, -1e-3], [2e-4, 1e-3])
    faults = [] if fault is None else [fault]
    _, y_meas = rmijax.simulate(
        traj, params, th, faults=faults, noise_lo=noise[0], noise_hi=noise[1], seed=11
    )
    options = {} if window is None else dict(window=window)
    mon = rmijax.monitor(
        params,
        kp=traj.kp,
        kd=traj.kd,
        dt=traj.dt,
        method="short_window",
        mode=mode,
        noise_lo=noise[0],
        noise_hi=noise[1],
        persistence=2,
        **options,
    )
    state, out = run_monitor(mon, traj, y_meas)
    bounds = short_window_bounds(
        traj, params, y_meas, mode=mode, noise_lo=noise[0], noise_hi=noise[1], **options
    )
    np.testing.assert_allclose(out.lower, bounds.lower, rtol=0, atol=1e-12)
    np.testing.assert_allclose(out.upper, bounds.upper, rtol=0, atol=1e-12)
    np.testing.assert_allclose(out.nominal, bounds.nominal, rtol=0, atol=1e-12)
    report = rmijax.detect(y_meas, bounds, persistence=2)
    np.testing.assert_array_equal(out.alarm, report.alarms)
    expected_first = -1 if report.first_alarm is None else round(report.first_alarm / traj.dt)
    assert int(state.first_alarm) == expected_first
    assert state.y_buffer.shape == (2 if window is None else window, 2, 2)  # fixed size
    np.testing.assert_array_equal(state.y_first, y_meas[0])
    if mode == "coupled" and fault is None:
        assert expected_first == -1
    elif mode == "coupled":  # per_joint is no safe threshold for n >= 2 (SPEC section 4)
        assert round(fault.onset / traj.dt) <= expected_first <= round(fault.onset / traj.dt) + 5


def test_monitor_vmaps_over_robots(arm):
    params, traj, _ = arm
    traj = rmijax.trajectory(["hold", "sine"], duration=1.0)
    draws = rmijax.monte_carlo_parameters(params, 64, seed=5, corners=False)
    _, readings = rmijax.simulate(traj, params, draws)  # (64, T+1, 2, 2)
    mon = rmijax.monitor(params, window=40)
    desired = (traj.q_d, traj.qd_d, traj.qdd_d)

    def one(y):
        state = mon.init(traj.q_d[0], traj.qd_d[0])

        def tick(state, inputs):
            q_d, qd_d, qdd_d, yk = inputs
            return mon.update(state, (q_d, qd_d, qdd_d), yk)

        return jax.lax.scan(tick, state, (*desired, y))[1]

    batch = jax.jit(jax.vmap(one))(readings)
    single = jax.jit(one)
    for r in (0, 17, 63):
        alone = single(readings[r])
        np.testing.assert_allclose(batch.upper[r], alone.upper, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(batch.alarm[r], alone.alarm)


@pytest.mark.parametrize("method", MONITOR_METHODS)
def test_update_traces_once(arm, method):
    params, traj, _ = arm
    mon = rmijax.monitor(params, method=method, window=20)
    chex.clear_trace_counter()
    update = jax.jit(chex.assert_max_traces(mon.update, n=1))
    state = mon.init(traj.q_d[0], traj.qd_d[0])
    for k in range(5):
        state, out = update(state, (traj.q_d[k], traj.qd_d[k], traj.qdd_d[k]), traj.x_n[k])
    assert int(out.tick) == 4 and not bool(out.alarm.any())


def test_nan_reading_alarms_inside_jit_and_is_refused_outside(arm):
    params, traj, _ = arm
    mon = rmijax.monitor(params, window=20)
    state = mon.init(traj.q_d[0], traj.qd_d[0])
    desired = (traj.q_d[0], traj.qd_d[0], traj.qdd_d[0])
    bad = traj.x_n[0].at[1, 0].set(jnp.nan)
    _, out = jax.jit(mon.update)(state, desired, bad)
    assert bool(out.alarm[1, 0]) and bool(out.nan_reading[1, 0])
    assert int(out.first_alarm) == 0 and int(out.alarm.sum()) == 1
    with pytest.raises(ValueError, match="y_meas contains NaN"):
        mon.update(state, desired, bad)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(kd=250.0), "unstable closed loop"),
        (dict(kp=[1.0, 2.0, 3.0]), r"kp must be a scalar or have shape \(2,\)"),
        (dict(method="magic"), "unknown method 'magic'"),
        (dict(mode="joint"), "unknown mode"),
        (dict(window=0), "window must be"),
        (dict(persistence=0), "persistence must be"),
        (dict(noise_lo=np.zeros(3)), "noise_lo must be a scalar"),
        (dict(noise_lo=[0.0, 0.2], noise_hi=0.1), "noise_lo > noise_hi for joint 0 tachometer"),
    ],
)
def test_bad_monitor_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        rmijax.monitor(rmijax.paper_arm2(), **kwargs)


def test_bad_init_and_update_shapes():
    mon = rmijax.monitor(rmijax.paper_arm2(), window=10)
    with pytest.raises(ValueError, match=r"q_d0 must have shape \(2,\)"):
        mon.init(np.zeros(3), np.zeros(2))
    with pytest.raises(ValueError, match="qd_d0 contains a non-finite"):
        mon.init(np.zeros(2), np.array([0.0, np.inf]))
    state = mon.init(np.zeros(2), np.zeros(2))
    with pytest.raises(ValueError, match=r"y_meas must have shape \(2, 2\)"):
        mon.update(state, (np.zeros(2),) * 3, np.zeros(2))
    with pytest.raises(ValueError, match=r"desired qdd_d must have shape \(2,\)"):
        mon.update(state, (np.zeros(2), np.zeros(2), np.zeros(1)), np.zeros((2, 2)))


def _planned_band(method):
    """A pendulum motion, a band computed before it runs, and readings that leave it.

    ``"certified"``: the certified band and a run with stuck sensors at 0.3 s; ``"plain"``:
    the nominal +- 0.01 and the nominal plus uniform noise in +- 0.012 (no simulation:
    the streaming does not depend on where the band came from).
    """
    params = rmijax.paper_pendulum()
    traj = rmijax.trajectory(["sine"], duration=0.6)
    if method == "certified":
        band = rmijax.bounds(traj, params, method="certified", splits=1)
        th = np.array([10.8, 0.995])  # inside the box
        fault = rmijax.Fault("stuck_sensors", 0, 0.3)
        _, y_meas = rmijax.simulate(traj, params, th, faults=[fault])
        return traj, band, np.array(y_meas)
    nominal = np.asarray(traj.x_n)
    band = rmijax.Bounds(
        lower=nominal - 0.01, upper=nominal + 0.01, nominal=nominal, crossed=None, dt=traj.dt
    )
    noise = np.random.default_rng(0).uniform(-0.012, 0.012, nominal.shape)
    return traj, band, nominal + noise


@pytest.mark.parametrize("method", ["plain", pytest.param("certified", marks=pytest.mark.slow)])
@pytest.mark.parametrize("persistence", [1, 2])
def test_band_monitor_streams_a_precomputed_band_as_detect_sees_it(method, persistence):
    traj, band, y_meas = _planned_band(method)
    y_meas[5, 0, 1] = np.nan  # a NaN reading alarms in both
    mon = rmijax.monitor_from_bounds(band, persistence=persistence)
    state, out = run_monitor(mon, traj, jnp.asarray(y_meas))
    report = rmijax.detect(y_meas, band, persistence=persistence)
    np.testing.assert_array_equal(out.lower, band.lower)
    np.testing.assert_array_equal(out.upper, band.upper)
    np.testing.assert_array_equal(out.alarm, report.alarms)
    assert 0 < report.alarms.sum() < report.alarms.size
    if method == "certified":  # fault-free until 0.3 s: only the NaN reading alarms
        assert not report.alarms[6 + persistence : 30].any() and report.alarms[30:].any()
    assert int(state.first_alarm) == round(report.first_alarm / traj.dt)
    assert int(state.tick) == traj.n_steps + 1


def test_band_monitor_past_the_planned_motion():
    traj, band, y_meas = _planned_band("plain")
    mon = rmijax.monitor_from_bounds(band)
    state = rmijax.BandMonitorState(
        tick=jnp.asarray(traj.n_steps + 1, jnp.int32),
        run_length=jnp.zeros((1, 2), jnp.int32),
        first_alarm=jnp.asarray(-1, jnp.int32),
    )
    with pytest.raises(ValueError, match="past the band's last tick"):
        mon.update(state, None, y_meas[-1])
    _, out = jax.jit(mon.update)(state, None, y_meas[-1])
    assert bool(jnp.all(jnp.isnan(out.upper))) and bool(jnp.all(out.alarm))
    with pytest.raises(ValueError, match=r"y_meas must have shape \(1, 2\)"):
        mon.update(mon.init(), None, np.zeros(2))
    with pytest.raises(TypeError, match="rmijax.Bounds"):
        rmijax.monitor_from_bounds(band.lower)
