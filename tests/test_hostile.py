"""Hostile input (issue 13): nothing silently accepted, nothing refused late, no cryptic error.

One table per public entry point: each row is a bad input and the error it
must get, with the argument's name in the message. Then the classes of the
issue that need more than a table: jit types, a NaN desired sample in the
monitor, user-model checks, faults, certain parameters, cost and the CLI.
"""

import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rmijax
from rmijax.apps import cli
from rmijax.methods.rmi import estimate_seconds
from rmijax.robots.model import RobotModel

F = rmijax.Fault


@pytest.fixture(scope="module")
def pend():
    return rmijax.paper_pendulum(), rmijax.trajectory("sine", duration=0.2)


@pytest.fixture(scope="module")
def arm():
    return rmijax.paper_arm2(), rmijax.trajectory(["hold", "sine"], duration=0.2)


@pytest.fixture(scope="module")
def pend_bounds(pend):
    params, traj = pend
    return rmijax.rmi(traj, params, window=5)


def _mass(q, th):
    return jnp.array([[th[0], 0.1], [0.1, th[1]]]) + 0.0 * q[0]


def _bias(q, qd, th):
    return 9.81 * jnp.cos(q) * th


def user_robot(mass=_mass, bias=_bias, fd=None):
    model = RobotModel(2, 2, mass, bias, forward_dynamics=fd, name="user")
    return rmijax.uncertain_robot(model, [1.0, 1.0], [0.9, 0.9], [1.1, 1.1])


# --------------------------------------------------------------------------
# Constructors: nothing coerced
# --------------------------------------------------------------------------


def _m1(q, th):
    return jnp.eye(1) * th[0]


def _h1(q, qd, th):
    return jnp.zeros(1)


CONSTRUCTORS = [
    (lambda: rmijax.preset_arm(2.7), ValueError, r"^n must be an integer number of links"),
    (lambda: rmijax.preset_arm("3"), ValueError, r"^n must be an integer"),
    (lambda: rmijax.preset_arm(True), ValueError, r"^n must be an integer"),
    (lambda: rmijax.preset_arm(0), ValueError, r"^n must be an integer number of links >= 1"),
    (lambda: rmijax.preset_arm(2, dtype=jnp.int32), TypeError, r"^dtype must be a float"),
    (lambda: rmijax.planar_arm_model(2.5), ValueError, r"^n_links must be an integer"),
    (lambda: rmijax.paper_pendulum(dtype="int8"), TypeError, r"^dtype must be a float"),
    (lambda: RobotModel(1.5, 1, _m1, _h1), ValueError, r"^n_joints must be an integer"),
    (lambda: RobotModel(1, "2", _m1, _h1), ValueError, r"^n_params must be an integer"),
    (lambda: RobotModel(1, -1, _m1, _h1), ValueError, r"^n_params must be an integer.*>= 0"),
    (lambda: RobotModel(1, 1, None, _h1), TypeError, r"^mass_matrix must be a function"),
    (lambda: RobotModel(1, 1, _m1, 3.0), TypeError, r"^bias must be a function"),
    (
        lambda: RobotModel(1, 1, _m1, _h1, forward_dynamics="fast"),
        TypeError,
        r"^forward_dynamics must be None or a function",
    ),
    (lambda: RobotModel(1, 2, _m1, _h1, param_names="ab"), TypeError, r"^param_names must be"),
    (lambda: RobotModel(1, 2, _m1, _h1, param_names=("a",)), ValueError, r"param_names has 1"),
    (lambda: RobotModel(1, 1, _m1, _h1, trusted=1), ValueError, r"^trusted must be True or"),
    (
        lambda: rmijax.uncertain_robot("arm", [1.0], [1.0], [1.0]),
        TypeError,
        r"^model must be a rmijax.RobotModel",
    ),
    (
        lambda: rmijax.uncertain_robot(RobotModel(1, 1, _m1, _h1), [1.0], [1.1], [0.9]),
        ValueError,
        r"lo > hi for parameter",
    ),
    (
        lambda: rmijax.uncertain_robot(RobotModel(1, 1, _m1, _h1), [2.0], [0.9], [1.1]),
        ValueError,
        r"nominal value .* outside its box",
    ),
    (
        lambda: rmijax.uncertain_robot(RobotModel(1, 1, _m1, _h1), "1", [0.9], [1.1]),
        TypeError,
        r"^nominal must be an array of numbers",
    ),
    (lambda: rmijax.planar_arm(["a", "b"], [1, 1], [1, 1]), TypeError, r"^nominal must be"),
    (lambda: rmijax.planar_arm([1.0, 1.0], [1.0], [1.0, 1.0]), ValueError, r"^lo has shape"),
    (lambda: rmijax.planar_arm([1.0, 1.0], [0.0, 1.0], [1, 1]), ValueError, r"lo of parameter m1"),
    (lambda: rmijax.planar_arm([np.nan, 1.0], [1, 1], [1, 1]), ValueError, r"^nominal contains"),
    (lambda: rmijax.trajectory("sine", duration=np.nan), ValueError, r"^duration must be"),
    (lambda: rmijax.trajectory("sine", duration="15"), ValueError, r"^duration must be"),
    (lambda: rmijax.trajectory("sine", duration=-1.0), ValueError, r"^duration must be a pos"),
    (lambda: rmijax.trajectory("sine", dt="0.01"), ValueError, r"^dt must be a positive"),
    (lambda: rmijax.trajectory("sine", dt=0.0), ValueError, r"^dt must be a positive"),
    (lambda: rmijax.trajectory("sine", dt=0.3), ValueError, r"unstable closed loop .*dt=0.3"),
    (lambda: rmijax.trajectory("sine", kp="100"), TypeError, r"^kp must be a number"),
    (lambda: rmijax.trajectory("sine", kd=[1.0, 2.0]), ValueError, r"^kd has shape"),
    (lambda: rmijax.trajectory("sine", dtype=jnp.int32), TypeError, r"^dtype must be a float"),
    (lambda: rmijax.trajectory([]), ValueError, r"^paths must name at least one"),
    (lambda: rmijax.trajectory("jog"), ValueError, r"^unknown path 'jog'"),
    (lambda: rmijax.trajectory(3.0), TypeError, r"^paths must be a path name"),
    (lambda: rmijax.trajectory([3.0]), TypeError, r"^paths\[0\] must be a path name"),
    (
        lambda: rmijax.trajectory(lambda t: jnp.ones(2) * t, duration=0.1),
        ValueError,
        r"^paths\[0\] must return a scalar",
    ),
    (
        lambda: rmijax.trajectory(lambda t: t * jnp.nan, duration=0.1),
        ValueError,
        r"non-finite q_d",
    ),
    (
        lambda: rmijax.trajectory_from_samples("x", np.zeros((3, 1)), np.zeros((3, 1)), dt=0.01),
        TypeError,
        r"^q_d must be a number or an array",
    ),
    (
        lambda: rmijax.trajectory_from_samples(
            np.r_[0.0, np.nan, 0.0][:, None], np.zeros((3, 1)), np.zeros((3, 1)), dt=0.01
        ),
        ValueError,
        r"^q_d contains a non-finite value",
    ),
    (
        lambda: rmijax.trajectory_from_samples(
            np.zeros((3, 1)), np.zeros((2, 1)), np.zeros((3, 1)), dt=0.01
        ),
        ValueError,
        r"^qd_d must have shape",
    ),
    (
        lambda: rmijax.trajectory_from_samples(
            np.zeros((3, 1)), np.zeros((3, 1)), np.zeros((3, 1)), dt=np.nan
        ),
        ValueError,
        r"^dt must be a positive",
    ),
    (
        lambda: rmijax.trajectory_from_samples(
            np.zeros((3, 1)), np.zeros((3, 1)), np.zeros((3, 1)), dt=0.01, labels=("a", "b")
        ),
        ValueError,
        r"^labels has 2 entries",
    ),
    (lambda: F("jammed", 0, 1.0), ValueError, r"unknown fault kind"),
    (lambda: F("bias", True, 1.0), ValueError, r"^Fault joint must be an integer"),
    (lambda: F("bias", 0.0, 1.0), ValueError, r"^Fault joint must be an integer"),
    (lambda: F("bias", -1, 1.0), ValueError, r"^Fault joint must be an integer >= 0"),
    (lambda: F("bias", 0, "1"), ValueError, r"^Fault onset must be"),
    (lambda: F("bias", 0, np.nan), ValueError, r"^Fault onset must be"),
    (lambda: F("bias", 0, -0.1), ValueError, r"^Fault onset must be a finite number >= 0"),
    (lambda: F("bias", 0, 1.0, value=np.inf), ValueError, r"^Fault value must be"),
    (lambda: F("bias", 0, 1.0, sensor=2), ValueError, r"^Fault sensor must be 0"),
    (lambda: F("bias", 0, 1.0, sensor=True), ValueError, r"^Fault sensor must be 0"),
    (lambda: F("stuck_encoder", 0, 1.0, sensor=1), ValueError, r"sensor means nothing.*stuck_tach"),
    (lambda: F("stuck_sensors", 0, 1.0, sensor=0), ValueError, r"sensor means nothing"),
    (lambda: F("locked", 0, 1.0, value=0.5), ValueError, r"value means nothing for kind 'locked'"),
    (lambda: F("free_swinging", 0, 1.0, sensor=0), ValueError, r"sensor means nothing"),
]


@pytest.mark.parametrize("build, error, match", CONSTRUCTORS)
def test_constructors_refuse(build, error, match):
    with pytest.raises(error, match=match):
        build()


def test_fault_defaults_still_work():
    assert F("bias", 0, 1.0).value == 0.0 and F("bias", 0, 1.0).sensor == 0
    assert F("drift", 1, 0.5, value=0.1, sensor=1).outputs == ((1, 1),)
    assert F("stuck_sensors", 1, 0.5).outputs == ((1, 0), (1, 1))
    assert F("locked", 0, 0.5).outputs == ()


# --------------------------------------------------------------------------
# Band methods and their options
# --------------------------------------------------------------------------

RMI_ARGS = [
    (dict(traj="t"), TypeError, r"^traj must be a rmijax.Trajectory"),
    (dict(params="p"), TypeError, r"^params must be a rmijax.UncertainRobot"),
    (dict(mode="exact"), ValueError, r"^unknown mode 'exact'"),
    (dict(window=2.0), ValueError, r"^window must be an integer number of steps"),
    (dict(window=0), ValueError, r"^window must be an integer number of steps >= 1"),
    (dict(window=True), ValueError, r"^window must be an integer"),
    (dict(noise_lo="a"), TypeError, r"^noise_lo must be a number"),
    (dict(noise_hi=np.zeros(3)), ValueError, r"^noise_hi must be a scalar, shape \(2,\)"),
    (dict(noise_hi=np.nan), ValueError, r"^noise_hi contains a non-finite"),
    (dict(noise_lo=0.1), ValueError, r"^noise_lo > noise_hi"),
    (dict(memory_budget="4GB"), ValueError, r"^memory_budget must be a positive number of bytes"),
    (dict(memory_budget=-1), ValueError, r"^memory_budget must be a positive number"),
    (dict(memory_budget=np.nan), ValueError, r"^memory_budget must be a positive number"),
    (dict(memory_budget=100), rmijax.ProblemTooLargeError, r"memory_budget is 100 bytes"),
    (dict(chunk_size=2.5), ValueError, r"^chunk_size must be an integer number of end steps"),
    (dict(chunk_size=True), ValueError, r"^chunk_size must be an integer"),
    (dict(chunk_size=0), ValueError, r"^chunk_size must be an integer number of end steps >= 1"),
    (dict(progress="yes"), ValueError, r"^progress must be True or False"),
    (dict(search="fast"), ValueError, r"^unknown search 'fast'"),
]


@pytest.mark.parametrize("kwargs, error, match", RMI_ARGS)
def test_rmi_refuses(pend, kwargs, error, match):
    params, traj = pend
    args = {"traj": traj, "params": params}
    for key in ("traj", "params"):
        if key in kwargs:
            args[key] = kwargs.pop(key)
    with pytest.raises(error, match=match):
        rmijax.rmi(args["traj"], args["params"], **kwargs)


def test_rmi_refuses_mismatched_joints(pend, arm):
    with pytest.raises(ValueError, match=r"traj has 2 joints but params describes a 1-joint"):
        rmijax.rmi(arm[1], pend[0])


BOUNDS_ARGS = [
    (dict(method="magic"), ValueError, r"^unknown method 'magic'"),
    (dict(method="rmi", runs=3), TypeError, r"takes no option 'runs'"),
    (dict(method="empirical", window=5), ValueError, r"has no window"),
    (dict(method="empirical", runs=2.5), ValueError, r"^runs must be an integer number of runs"),
    (dict(method="empirical", runs=0), ValueError, r"^runs must be an integer number of runs"),
    (dict(method="empirical", safety=-1), ValueError, r"^safety must be a positive"),
    (dict(method="empirical", safety=np.nan), ValueError, r"^safety must be a positive"),
    (dict(method="empirical", seed=-1), ValueError, r"^seed must be an integer >= 0"),
    (dict(method="empirical", seed=1.5), ValueError, r"^seed must be an integer"),
    (dict(method="empirical", mode="per_joint"), ValueError, r"mode must be 'coupled'"),
    (dict(method="linearized", margin=-0.1), ValueError, r"^margin must be True or False"),
    (dict(method="linearized", chunk_size=2.5), ValueError, r"^chunk_size must be an integer"),
    (dict(method="linearized", progress=1), ValueError, r"^progress must be True or False"),
    (dict(method="linearized", mode="per_joint"), ValueError, r"mode must be 'coupled'"),
    (dict(method="constant_corners", chunk_size=2.5), ValueError, r"^chunk_size must be an int"),
    (dict(method="constant_corners", horizon="all"), ValueError, r"^unknown horizon 'all'"),
    (dict(method="constant_corners", progress="no"), ValueError, r"^progress must be True"),
    (dict(method="corner_search", max_rounds=1.5), ValueError, r"^max_rounds must be None"),
    (dict(method="corner_search", max_rounds=-1), ValueError, r"^max_rounds must be >= 0"),
    (dict(method="corner_search", memory_budget="1G"), ValueError, r"^memory_budget must be"),
    (dict(method="short_window"), ValueError, r"^readings are required"),
    (dict(method="short_window", readings="r"), TypeError, r"^readings must be an array"),
    (dict(method="short_window", readings=np.zeros((3, 1, 2))), ValueError, r"^readings must"),
    (dict(method="short_window", start="zero"), ValueError, r"^unknown start 'zero'"),
    (dict(method="rmi", readings=np.zeros((21, 1, 2))), ValueError, r"readings are used by"),
]


@pytest.mark.parametrize("kwargs, error, match", BOUNDS_ARGS)
def test_bounds_refuses(pend, kwargs, error, match):
    params, traj = pend
    if kwargs.get("start") == "zero":
        kwargs = {**kwargs, "readings": traj.x_n}
    with pytest.raises(error, match=match):
        rmijax.bounds(traj, params, **kwargs)


def test_estimate_memory_refuses_unknown_options(pend):
    params, _ = pend
    with pytest.raises(ValueError, match=r"unknown search"):
        rmijax.estimate_memory(params, search="fast")


# --------------------------------------------------------------------------
# rmi_step under jit: types known at trace time are checked, integers never wrap
# --------------------------------------------------------------------------


@pytest.mark.parametrize(
    "t_f, error, match",
    [
        (2.5, TypeError, r"^t_f must be an integer end step"),
        (np.float64(3.0), TypeError, r"^t_f must be an integer end step, got dtype float64"),
        (True, TypeError, r"^t_f must be an integer end step, got the bool"),
        ("3", TypeError, r"^t_f must be an integer end step"),
        (np.array([1, 2]), ValueError, r"^t_f must be a scalar end step"),
        (-1, ValueError, r"^t_f=-1 is outside"),
        (2**40, ValueError, r"is outside the trajectory's end steps"),
    ],
)
def test_rmi_step_refuses_eager(pend, t_f, error, match):
    params, traj = pend
    with pytest.raises(error, match=match):
        rmijax.rmi_step(traj, params, t_f, window=5)


def test_rmi_step_refuses_a_traced_float_and_never_wraps(pend):
    params, traj = pend
    step = jax.jit(lambda t: rmijax.rmi_step(traj, params, t, window=5).upper)
    with pytest.raises(TypeError, match=r"t_f must be an integer end step, got dtype float"):
        step(2.5)
    with pytest.raises(TypeError, match=r"got the bool"):
        step(jnp.asarray(True))
    last = rmijax.rmi_step(traj, params, traj.n_steps, window=5).upper
    wrapped = rmijax.rmi_step(traj, params, 3, window=5).upper
    big = step(np.int64(2**32 + 3))  # int32 would wrap this to step 3
    np.testing.assert_allclose(big, last, rtol=1e-12, atol=0)
    assert not np.allclose(big, wrapped, rtol=1e-12, atol=0)
    np.testing.assert_allclose(step(-5), rmijax.rmi_step(traj, params, 0, window=5).upper)


# --------------------------------------------------------------------------
# The monitor: a NaN desired sample is its own condition, and the monitor recovers
# --------------------------------------------------------------------------


def _run_monitor(params, traj, update, window, bad_tick):
    mon = rmijax.monitor(params, window=window)
    state = mon.init(traj.q_d[0], traj.qd_d[0])
    outs = []
    for k in range(traj.n_steps + 1):
        q_d = traj.q_d[k].at[0].set(jnp.nan) if k == bad_tick else traj.q_d[k]
        state, out = update(mon)(state, (q_d, traj.qd_d[k], traj.qdd_d[k]), traj.x_n[k])
        outs.append(out)
    return outs


def test_monitor_refuses_nan_desired_outside_jit(arm):
    params, traj = arm
    mon = rmijax.monitor(params, window=5)
    state = mon.init(traj.q_d[0], traj.qd_d[0])
    for name in ("q_d", "qd_d", "qdd_d"):
        desired = {"q_d": traj.q_d[0], "qd_d": traj.qd_d[0], "qdd_d": traj.qdd_d[0]}
        desired[name] = desired[name].at[1].set(jnp.inf)
        with pytest.raises(ValueError, match=rf"^desired {name} contains NaN/inf at tick 0"):
            mon.update(state, tuple(desired.values()), traj.x_n[0])


def test_monitor_flags_nan_desired_inside_jit_and_recovers(arm):
    params, traj = arm
    window, bad = 5, 3
    outs = _run_monitor(params, traj, lambda mon: jax.jit(mon.update), window, bad)
    flagged = [bool(o.desired_invalid) for o in outs]
    assert flagged == [bad <= k <= bad + window for k in range(len(outs))]
    assert not any(bool(o.alarm.any()) for o in outs)  # not a fault
    assert not any(bool(o.nan_reading.any()) for o in outs)
    for k in (bad - 1, bad + window + 1, len(outs) - 1):
        assert np.isfinite(np.asarray(outs[k].upper)).all()
    assert np.isnan(np.asarray(outs[bad + 1].upper)).all()


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(dt=-0.01), ValueError, r"^dt must be a positive"),
        (dict(dt="0.01"), ValueError, r"^dt must be a positive"),
        (dict(persistence=0), ValueError, r"^persistence must be an integer >= 1"),
        (dict(persistence=1.5), ValueError, r"^persistence must be an integer"),
        (dict(tol=-1.0), ValueError, r"^tol must be a finite number >= 0"),
        (dict(kp=np.nan), ValueError, r"^kp contains a non-finite"),
        (dict(kd="20"), TypeError, r"^kd must be a number"),
        (dict(method="linearized"), ValueError, r"^unknown method 'linearized'"),
        (dict(mode="exact"), ValueError, r"^unknown mode"),
        (dict(window=0), ValueError, r"^window must be an integer number of ticks"),
        (dict(noise_lo=1.0), ValueError, r"^noise_lo > noise_hi"),
    ],
)
def test_monitor_refuses(pend, kwargs, error, match):
    with pytest.raises(error, match=match):
        rmijax.monitor(pend[0], **kwargs)


# --------------------------------------------------------------------------
# User models are checked before any work
# --------------------------------------------------------------------------

BAD_MODELS = [
    (dict(mass=lambda q, th: jnp.ones((2, 2)) * th[0] + 0 * q[0]), r"is singular at"),
    (
        dict(mass=lambda q, th: jnp.diag(jnp.array([th[0], -th[1]])) + 0 * q[0]),
        r"is not positive definite at",
    ),
    (
        dict(mass=lambda q, th: jnp.array([[th[0], 0.5], [0.0, th[1]]]) + 0 * q[0]),
        r"is not symmetric at",
    ),
    (
        dict(mass=lambda q, th: jnp.diag(jnp.array([th[0], th[1] * jnp.sin(q[1]) ** 2]))),
        r"is singular at q=\[0\. 0\.\]",
    ),
    (
        dict(mass=lambda q, th: jnp.diag(jnp.array([th[0], 2.0 - 2 * th[1]]))),
        r"is (singular|not positive definite) at .*th\[1\]=1\.1",
    ),
    (dict(mass=lambda q, th: jnp.eye(2) * jnp.nan), r"mass_matrix returns NaN/inf"),
    (dict(bias=lambda q, qd, th: q * jnp.nan), r"bias \(h\) returns NaN/inf"),
    (dict(fd=lambda q, qd, tau, th: tau), r"forward_dynamics disagrees with solve"),
    (dict(mass=lambda q, th: jnp.eye(3) * th[0]), r"mass_matrix returns shape \(3, 3\)"),
    (dict(bias=lambda q, qd, th: jnp.zeros(3)), r"bias returns shape \(3,\)"),
    (dict(bias=lambda q, qd, th: q @ jnp.ones(3)), r"bias\(q, qd, th\) fails"),
]


@pytest.mark.parametrize("parts, match", BAD_MODELS)
def test_bad_user_models_are_refused_before_the_run(arm, parts, match):
    traj = arm[1]
    with pytest.raises(rmijax.ModelCheckError, match=r"^params\.model\..*" + match):
        rmijax.rmi(traj, user_robot(**parts), window=5)


@pytest.mark.parametrize(
    "call",
    [
        lambda traj, params: rmijax.bounds(traj, params, method="linearized", window=5),
        lambda traj, params: rmijax.bounds(traj, params, method="constant_corners"),
        lambda traj, params: rmijax.bounds(traj, params, method="empirical", runs=2),
        lambda traj, params: rmijax.bounds(traj, params, method="corner_search", window=5),
        lambda traj, params: rmijax.bounds(traj, params, method="short_window", readings=traj.x_n),
        lambda traj, params: rmijax.rmi_step(traj, params, 3, window=5),
        lambda traj, params: rmijax.simulate(traj, params, params.nominal),
        lambda traj, params: rmijax.monitor(params),
        lambda traj, params: rmijax.worst_case(traj, params, (0, 0), 0.1),
    ],
)
def test_every_entry_point_checks_the_model(arm, call):
    with pytest.raises(rmijax.ModelCheckError, match=r"forward_dynamics disagrees"):
        call(arm[1], user_robot(fd=lambda q, qd, tau, th: tau))


def test_a_good_user_model_passes_and_the_check_is_cached(arm, monkeypatch):
    from rmijax.robots import check

    traj = arm[1]
    good = user_robot(
        fd=lambda q, qd, tau, th: jnp.linalg.solve(_mass(q, th), tau - _bias(q, qd, th))
    )
    calls = []
    evaluate = check._evaluate
    monkeypatch.setattr(check, "_evaluate", lambda *args: calls.append(1) or evaluate(*args))
    rmijax.check_model(good, traj)
    rmijax.check_model(good, traj)  # the same model, box and states: a cache hit
    assert len(calls) == 1


# --------------------------------------------------------------------------
# Faults are never silently dropped
# --------------------------------------------------------------------------


@pytest.mark.parametrize(
    "faults, match",
    [
        ([F("bias", 0, 0.1, value=0.1), F("drift", 0, 0.1, value=1.0)], r"joint 0 encoder"),
        ([F("stuck_encoder", 1, 0.1), F("stuck_encoder", 1, 0.15)], r"joint 1 encoder"),
        ([F("stuck_tach", 1, 0.1), F("stuck_sensors", 1, 0.1)], r"joint 1 tachometer"),
        ([F("bias", 0, 0.1, sensor=1), F("stuck_tach", 0, 0.1)], r"joint 0 tachometer"),
        ([F("locked", 0, 0.1), F("free_swinging", 0, 0.1)], r"the motor of joint 0"),
    ],
)
def test_two_faults_on_one_output_are_refused(arm, faults, match):
    params, traj = arm
    with pytest.raises(ValueError, match=r"^faults\[0\] .* and faults\[1\] .*" + match):
        rmijax.simulate(traj, params, params.nominal, faults=faults)


def test_faults_on_different_outputs_combine(arm):
    params, traj = arm
    faults = [F("bias", 0, 0.1, value=0.1), F("bias", 0, 0.1, value=0.1, sensor=1)]
    faults += [F("stuck_encoder", 1, 0.1), F("locked", 1, 0.1)]
    _, y = rmijax.simulate(traj, params, params.nominal, faults=faults)
    assert np.isfinite(np.asarray(y)).all()


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(th_true="x"), TypeError, r"^th_true must be a number"),
        (dict(th_true=np.ones(3)), ValueError, r"^th_true must have shape"),
        (dict(faults="stuck"), TypeError, r"^faults must be a Fault or a list"),
        (dict(seed=1.5), ValueError, r"^seed must be an integer"),
        (dict(seed=-1), ValueError, r"^seed must be an integer >= 0"),
        (dict(divergence_limit=np.nan), ValueError, r"^divergence_limit must be a positive"),
        (dict(divergence_limit=-1.0), ValueError, r"^divergence_limit must be a positive"),
        (dict(noise_hi="a"), TypeError, r"^noise_hi must be a number"),
        (dict(th_true=np.ones((2 * 10**6, 4))), rmijax.ProblemTooLargeError, r"th_true in batches"),
    ],
)
def test_simulate_refuses(arm, kwargs, error, match):
    params, traj = arm
    kwargs = {"th_true": params.nominal, **kwargs}
    with pytest.raises(error, match=match):
        rmijax.simulate(traj, params, **kwargs)


# --------------------------------------------------------------------------
# Detection
# --------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(dt=-0.01), ValueError, r"^dt must be a positive"),
        (dict(dt=0.02), ValueError, r"^dt=0.02 s disagrees with the step of the bounds"),
        (dict(onset=np.nan), ValueError, r"^onset must be a finite number >= 0"),
        (dict(onset="1"), ValueError, r"^onset must be a finite"),
        (dict(onset=5.0), ValueError, r"^onset 5.0 s is outside the run"),
        (dict(persistence=2.5), ValueError, r"^persistence must be an integer"),
        (dict(persistence=0), ValueError, r"^persistence must be an integer >= 1"),
        (dict(tol=-1), ValueError, r"^tol must be a finite number >= 0"),
        (dict(tol=np.nan), ValueError, r"^tol must be a finite number >= 0"),
        (dict(x_true=np.zeros((2, 1, 2))), ValueError, r"^x_true must have shape"),
        (dict(y_meas="y"), TypeError, r"^y_meas must be a number or an array"),
        (dict(y_meas=np.zeros((2, 1, 2))), ValueError, r"^y_meas must have the bounds' shape"),
        (dict(bounds="b"), TypeError, r"^bounds must be a rmijax.Bounds"),
    ],
)
def test_detect_refuses(pend_bounds, kwargs, error, match):
    args = dict(y_meas=np.asarray(pend_bounds.nominal), bounds=pend_bounds)
    for key in ("y_meas", "bounds"):
        if key in kwargs:
            args[key] = kwargs.pop(key)
    with pytest.raises(error, match=match):
        rmijax.detect(args["y_meas"], args["bounds"], **kwargs)


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(tol=np.nan), ValueError, r"^tol must be a finite number >= 0"),
        (dict(states=np.zeros((3, 3))), ValueError, r"^states must have shape"),
        (dict(bounds=object()), TypeError, r"^bounds must be a rmijax.Bounds"),
    ],
)
def test_containment_refuses(pend_bounds, kwargs, error, match):
    args = dict(states=np.asarray(pend_bounds.nominal), bounds=pend_bounds)
    for key in ("states", "bounds"):
        if key in kwargs:
            args[key] = kwargs.pop(key)
    with pytest.raises(error, match=match):
        rmijax.containment(args["states"], args["bounds"], **kwargs)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(draws=-3), r"^draws must be an integer >= 0"),
        (dict(draws=2.5), r"^draws must be an integer"),
        (dict(seed=-1), r"^seed must be an integer >= 0"),
        (dict(corners="yes"), r"^corners must be True or False"),
    ],
)
def test_monte_carlo_parameters_refuses(pend, kwargs, match):
    kwargs = {"draws": 2, **kwargs}
    with pytest.raises(ValueError, match=match):
        rmijax.monte_carlo_parameters(pend[0], **kwargs)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(output=(0, 2)), r"^output=\(0, 2\) is out of range"),
        (dict(output=(0.0, 0)), r"^output must be a \(joint, sensor\) pair"),
        (dict(t=np.nan), r"^t must be a finite time"),
        (dict(t=9.0), r"^t=9.0 s is outside the run"),
        (dict(iterations=0), r"^iterations must be an integer >= 1"),
        (dict(random_starts=-1), r"^random_starts must be an integer >= 0"),
        (dict(seed=-2), r"^seed must be an integer >= 0"),
        (dict(starts=np.ones((1, 3))), r"^starts must have shape \(S, 2\)"),
    ],
)
def test_worst_case_refuses(pend, kwargs, match):
    params, traj = pend
    kwargs = {"output": (0, 0), "t": 0.1, **kwargs}
    with pytest.raises(ValueError, match=match):
        rmijax.worst_case(traj, params, **kwargs)


# --------------------------------------------------------------------------
# Cost: certain parameters add no corners, hopeless problems are refused at once
# --------------------------------------------------------------------------


def test_certain_parameters_add_no_corners_and_keep_the_bounds(arm):
    _, traj = arm
    nominal = [12.0, 10.0, 1.5, 1.0]
    partly = rmijax.planar_arm(nominal, [11.0, 10.0, 1.5, 0.99], [13.0, 10.0, 1.5, 1.01])
    assert rmijax.uncertain_indices(partly) == (0, 3)
    full = rmijax.estimate_memory(rmijax.paper_arm2(), search="enumerate")
    fewer = rmijax.estimate_memory(partly, search="enumerate")
    assert fewer < full
    reduced = rmijax.rmi(traj, partly, window=10, search="enumerate")
    # Under jit the box is traced: every one of the 2^4 corners is enumerated.
    every = jax.jit(lambda p: rmijax.rmi(traj, p, window=10, search="enumerate"))(partly)
    for field in ("lower", "upper"):
        np.testing.assert_allclose(
            getattr(reduced, field), getattr(every, field), rtol=0, atol=1e-12
        )
    corners = rmijax.corner_tensor(partly.lo, partly.hi, (0, 3))
    assert corners.shape == (4, 4)
    every_corner = np.asarray(rmijax.corner_tensor(partly.lo, partly.hi))
    np.testing.assert_array_equal(corners, every_corner[[0, 1, 8, 9]])


def test_constant_corners_with_certain_parameters_equal_the_full_envelope(arm):
    _, traj = arm
    partly = rmijax.planar_arm(
        [12.0, 10.0, 1.5, 1.0], [11.0, 10.0, 1.5, 0.99], [13.0, 10.0, 1.5, 1.01]
    )
    reduced = rmijax.bounds(traj, partly, method="constant_corners")
    every = jax.jit(lambda p: rmijax.bounds(traj, p, method="constant_corners"))(partly)
    np.testing.assert_allclose(reduced.upper, every.upper, rtol=0, atol=1e-12)
    np.testing.assert_allclose(reduced.lower, every.lower, rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(method="rmi"),
        dict(method="short_window", readings="x_n", noise_lo=-1e-3, noise_hi=1e-3),
        dict(method="linearized"),
        dict(method="constant_corners", horizon="window"),
        dict(method="corner_search"),
    ],
)
def test_a_window_longer_than_the_run_gives_the_same_bounds(pend, kwargs):
    params, traj = pend
    if kwargs.get("readings") == "x_n":
        kwargs = {**kwargs, "readings": traj.x_n}
    long = rmijax.bounds(traj, params, window=10**6, **kwargs)
    short = rmijax.bounds(traj, params, window=traj.n_steps, **kwargs)
    np.testing.assert_array_equal(long.upper, short.upper)
    np.testing.assert_array_equal(long.lower, short.lower)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(method="rmi"), r"one end step of this problem needs about .* GiB"),
        (dict(method="rmi", search="enumerate"), r"needs about 1056.00 GiB"),
        (dict(method="corner_search", memory_budget=10**5), r"memory_budget"),
        (dict(method="constant_corners"), r"constant_corners over 16777216 corners .* days"),
        (dict(method="empirical", runs=10**5), r"simulating 100000 runs .* GiB"),
        (
            dict(method="short_window", readings="x_n", memory_budget=10**5),
            r"memory_budget",
        ),
        (dict(method="linearized", chunk_size=0), r"^chunk_size must be"),
    ],
)
def test_too_large_problems_are_refused_at_once(kwargs, match):
    params = rmijax.preset_arm(12)
    traj = rmijax.trajectory(["hold"] * 12, duration=15.0)
    if kwargs.get("readings") == "x_n":
        kwargs = {**kwargs, "readings": traj.x_n}
    if kwargs["method"] == "rmi" and "search" not in kwargs:
        kwargs = {**kwargs, "memory_budget": 10**5}
    started = time.perf_counter()
    with pytest.raises((rmijax.ProblemTooLargeError, ValueError), match=match):
        rmijax.bounds(traj, params, **kwargs)
    assert time.perf_counter() - started < 1.0


def test_the_time_refusal_names_a_fix_that_works():
    params = rmijax.preset_arm(6)
    traj = rmijax.trajectory(["hold"] * 6, duration=15.0)
    assert estimate_seconds(params, traj.n_steps, search="enumerate") > 600
    with pytest.raises(rmijax.ProblemTooLargeError, match=r"make parameters certain|Make param"):
        rmijax.rmi(traj, params, search="enumerate")
    # The fix: certain lengths and all but two masses leave 4 corners, estimated in seconds.
    nominal = np.asarray(params.nominal)
    lo, hi = nominal.copy(), nominal.copy()
    lo[:2], hi[:2] = np.asarray(params.lo)[:2], np.asarray(params.hi)[:2]
    certain = rmijax.planar_arm(nominal, lo, hi)
    assert estimate_seconds(certain, traj.n_steps, search="enumerate") < 600


# --------------------------------------------------------------------------
# The CLI: every failure is one line on stderr and exit code 2, before any work
# --------------------------------------------------------------------------


@pytest.mark.parametrize(
    "argv, match",
    [
        (["--persistence", "0"], r"--persistence must be an integer >= 1"),
        (["--draws", "-1"], r"--draws must be an integer >= 0"),
        (["--runs", "0"], r"--runs must be an integer >= 1"),
        (["--safety", "nan"], r"--safety must be a positive finite"),
        (["--safety", "-2"], r"--safety must be a positive finite"),
        (["--onset", "99"], r"--onset must lie inside the 6 s run"),
        (["--onset", "inf"], r"--onset must lie inside"),
        (["--runs", "two"], r"argument --runs: invalid int value"),
        (["--bogus"], r"unrecognized arguments: --bogus"),
        (["--out", "FILE"], r"--out .* is an existing file"),
        (["--out", "FILE/sub"], r"--out .* cannot be created"),
    ],
)
def test_cli_refuses_in_one_line_before_work(tmp_path, capsys, argv, match):
    afile = tmp_path / "afile"
    afile.write_text("")
    argv = [a.replace("FILE", str(afile)) for a in argv]
    if "--out" not in argv:
        argv += ["--out", str(tmp_path / "out")]
    started = time.perf_counter()
    with pytest.raises(SystemExit) as info:
        cli.main(["--quick", "--no-progress", *argv])
    assert time.perf_counter() - started < 2.0  # refused before any computation
    err = capsys.readouterr().err
    assert info.value.code == 2
    assert err.count("\n") == 1 and err.startswith("rmijax: error: ")
    assert "Traceback" not in err
    assert __import__("re").search(match, err)


def test_cli_in_a_subprocess_prints_no_traceback(tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("")
    run = subprocess.run(
        [sys.executable, "-m", "rmijax.apps.cli", "--quick", "--out", str(afile)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 2
    assert run.stderr.count("\n") == 1 and "is an existing file" in run.stderr


def test_numpy_and_jax_scalars_are_numbers_not_refused(pend):
    params, traj = pend
    assert rmijax.preset_arm(np.int64(2)).n_joints == 2
    assert rmijax.trajectory("sine", duration=jnp.float32(0.2), dt=np.float64(0.01)).n_steps == 20
    bounds = rmijax.rmi(traj, params, window=np.int32(5), chunk_size=jnp.int32(4))
    found = rmijax.detect(np.asarray(bounds.nominal), bounds, onset=np.float32(0.1))
    assert found.false_alarms == 0
    with pytest.raises(ValueError, match=r"^window must be an integer"):
        rmijax.rmi(traj, params, window=np.array(True))
