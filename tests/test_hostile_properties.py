"""Property-based hostile input (issue 13): over boxes, gains, shapes and dtypes, every
builder and ``rmi`` either returns a sane answer or refuses with the argument's name.

Small ``max_examples`` and no deadline keep the default run fast; the heavier
``rmi`` properties are marked slow.
"""

import re

import jax.numpy as jnp
import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import (  # noqa: E402
    example,
    given,
    settings,
    strategies as st,  # noqa: E402
)

import rmijax  # noqa: E402

# derandomize: the same examples on every run, so CI cannot pass or fail by chance
FAST = settings(max_examples=40, deadline=None, derandomize=True)
SLOW = settings(max_examples=12, deadline=None, derandomize=True)

hostile_floats = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.sampled_from([0.0, -0.0, 1e-300, -1.0, 1e300, np.nan, np.inf]),
)
sane_floats = st.floats(min_value=0.05, max_value=50.0)
dtypes = st.sampled_from([np.float16, np.float32, np.float64, np.int32, np.int64, bool])


def _refusal_names(err, *names):
    """The error is one of ours: ValueError/TypeError naming one of ``names``."""
    assert isinstance(err, (ValueError, TypeError)), repr(err)
    message = str(err)
    assert any(re.search(rf"\b{re.escape(n)}\b", message) for n in names), message


@FAST
@given(
    n=st.integers(1, 3),
    values=st.lists(hostile_floats, min_size=18, max_size=18),
    dtype=dtypes,
)
def test_planar_arm_returns_a_valid_box_or_names_the_argument(n, values, dtype):
    nominal, lo, hi = (np.asarray(values[k * 6 : k * 6 + 2 * n]) for k in range(3))
    with np.errstate(over="ignore", invalid="ignore"):
        nominal, lo, hi = (
            a.astype(dtype) if dtype is not bool else a > 0 for a in (nominal, lo, hi)
        )
    try:
        params = rmijax.planar_arm(nominal, lo, hi)
    except (ValueError, TypeError) as err:
        _refusal_names(err, "nominal", "lo", "hi", "parameter", "dtype")
        return
    low, mid, high = (np.asarray(a, np.float64) for a in (params.lo, params.nominal, params.hi))
    assert np.isfinite([low, mid, high]).all()
    assert (low > 0).all() and (low <= mid).all() and (mid <= high).all()
    assert jnp.issubdtype(params.dtype, jnp.floating)


@FAST
@given(
    shape=st.sampled_from([(), (1,), (2,), (3,), (1, 2), (2, 2), (0,), (2, 1)]),
    fill=hostile_floats,
)
def test_uncertain_robot_shapes(shape, fill):
    model = rmijax.planar_arm_model(1)
    value = np.full(shape, fill)
    try:
        params = rmijax.uncertain_robot(model, value, [1.0, 0.5], [20.0, 2.0])
    except (ValueError, TypeError) as err:
        _refusal_names(err, "nominal")
        return
    assert params.nominal.shape == (2,)
    assert np.isfinite(np.asarray(params.nominal)).all()


gain = st.one_of(
    hostile_floats,
    st.floats(min_value=-10.0, max_value=1e4),
    st.lists(st.floats(min_value=-10.0, max_value=1e4), min_size=1, max_size=3),
)


@FAST
@given(kp=gain, kd=gain, dt=st.one_of(hostile_floats, st.floats(1e-4, 0.5)))
@example(kp=0.0, kd=179769314.0, dt=1e300)  # kd dt overflows: refused, not a LinAlgError
def test_gains_and_step_give_a_stable_loop_or_are_refused(kp, kd, dt):
    n = 2
    samples = np.zeros((4, n))
    try:
        traj = rmijax.trajectory_from_samples(samples, samples, samples, dt=dt, kp=kp, kd=kd)
    except (ValueError, TypeError) as err:
        _refusal_names(err, "kp", "kd", "dt")
        return
    radius = rmijax._checks.closed_loop_radius(traj.kp, traj.kd, traj.dt)
    assert (radius < 1.0).all() and traj.kp.shape == (n,) and traj.dt > 0


@FAST
@given(
    count=st.one_of(
        st.integers(-3, 4),
        st.floats(allow_nan=True),
        st.sampled_from(["3", True, None, 2.0, np.int64(2), np.float64(2.0)]),
    )
)
def test_counts_are_never_coerced(count):
    try:
        params = rmijax.preset_arm(count)
    except (ValueError, TypeError) as err:
        _refusal_names(err, "n")
        is_int = isinstance(count, (int, np.integer)) and not isinstance(count, bool)
        assert not (is_int and count >= 1)
        return
    assert isinstance(count, (int, np.integer)) and not isinstance(count, bool)
    assert params.n_joints == count >= 1


@FAST
@given(
    name=st.sampled_from(["window", "chunk_size", "memory_budget", "progress"]),
    value=st.one_of(
        hostile_floats,
        st.integers(-5, 0),
        st.sampled_from(["4GB", "1", None, 2.5, True, [1]]),
    ),
)
def test_rmi_options_refuse_before_any_work(name, value):
    params = rmijax.paper_pendulum()
    traj = rmijax.trajectory("sine", duration=0.05)
    if value is None and name == "chunk_size":
        return  # None is its default
    try:
        rmijax.rmi(traj, params, **{name: value})
    except rmijax.ProblemTooLargeError as err:  # a real budget, too small for one end step
        assert name == "memory_budget" and "memory_budget" in str(err)
        return
    except (ValueError, TypeError) as err:
        _refusal_names(err, name)
        return
    # Accepted only when it is a real value of the right kind.
    if name == "progress":
        assert isinstance(value, bool)
    elif name == "memory_budget":
        assert np.isfinite(value) and value >= 1 and not isinstance(value, bool)
    else:
        assert isinstance(value, int) and not isinstance(value, bool) and value >= 1


noise_shapes = st.sampled_from([(), (2,), (1, 2), (3,), (2, 2), (1,), (1, 1, 2)])


@pytest.mark.slow
@SLOW
@given(
    lo_shape=noise_shapes,
    hi_shape=noise_shapes,
    lo=st.floats(-0.1, 0.1),
    hi=st.floats(-0.1, 0.1),
    dtype=st.sampled_from([np.float32, np.float64]),
)
def test_rmi_noise_shapes_and_dtypes(lo_shape, hi_shape, lo, hi, dtype):
    params = rmijax.paper_pendulum(dtype=dtype)
    traj = rmijax.trajectory("sine", duration=0.05, dtype=dtype)
    try:
        bounds = rmijax.rmi(
            traj, params, window=3, noise_lo=np.full(lo_shape, lo), noise_hi=np.full(hi_shape, hi)
        )
    except (ValueError, TypeError) as err:
        _refusal_names(err, "noise_lo", "noise_hi")
        return
    assert bounds.upper.shape == (traj.n_steps + 1, 1, 2)
    assert bounds.upper.dtype == dtype
    assert np.isfinite(np.asarray(bounds.upper)).all()


@pytest.mark.slow
@SLOW
@given(
    masses=st.lists(sane_floats, min_size=2, max_size=2),
    spread=st.lists(st.sampled_from([0.0, 0.01, 0.05, 0.1]), min_size=4, max_size=4),
    kp=st.floats(20.0, 200.0),
)
def test_rmi_over_random_boxes_contains_the_nominal(masses, spread, kp):
    nominal = np.array(masses + [1.0, 0.8])
    lo, hi = nominal * (1 - np.array(spread)), nominal * (1 + np.array(spread))
    params = rmijax.planar_arm(nominal, lo, hi)
    traj = rmijax.trajectory(["hold", "sine"], duration=0.1, kp=kp, kd=2 * np.sqrt(kp))
    bounds = rmijax.rmi(traj, params, window=5)
    lower, upper, nom = (np.asarray(a) for a in (bounds.lower, bounds.upper, bounds.nominal))
    assert np.isfinite([lower, upper]).all()
    assert (lower <= nom + 1e-9).all() and (nom <= upper + 1e-9).all()
    if not any(spread):
        np.testing.assert_allclose(lower, nom, atol=1e-12)
        np.testing.assert_allclose(upper, nom, atol=1e-12)
