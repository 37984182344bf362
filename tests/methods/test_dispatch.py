"""rmijax.bounds: one entry point to every method, each giving rmi-shaped Bounds."""

import numpy as np
import pytest

import rmijax
from rmijax.methods.constant_corners import constant_corner_bounds
from rmijax.methods.corner_search import corner_search_bounds
from rmijax.methods.linearized import linearized_bounds
from rmijax.methods.short_window import short_window_bounds


@pytest.fixture(scope="module")
def arm():
    params = rmijax.paper_arm2()
    traj = rmijax.trajectory(["hold", "sine"], duration=1.2)
    _, readings = rmijax.simulate(traj, params, params.hi)
    return traj, params, np.asarray(readings)


def _same(a, b):
    for field in ("lower", "upper", "nominal", "crossed"):
        np.testing.assert_array_equal(np.asarray(getattr(a, field)), np.asarray(getattr(b, field)))
    assert a.dt == b.dt


def test_every_method_gives_rmi_shaped_finite_bounds(arm):
    traj, params, readings = arm
    for method in rmijax.METHODS:
        extra = {"readings": readings} if method == "short_window" else {}
        band = rmijax.bounds(traj, params, method=method, **extra)
        assert isinstance(band, rmijax.Bounds), method
        for field in ("lower", "upper", "nominal", "crossed"):
            assert np.shape(getattr(band, field)) == (traj.n_steps + 1, 2, 2), (method, field)
        assert np.all(np.isfinite(band.lower)) and np.all(np.isfinite(band.upper)), method
        assert band.dt == traj.dt
        if method == "short_window":
            continue  # its band follows the readings (here the hi corner), not the nominal
        # every other band holds the nominal run except where it reports a crossing
        ok = (np.asarray(band.lower) <= np.asarray(band.nominal) + 1e-12) & (
            np.asarray(band.nominal) <= np.asarray(band.upper) + 1e-12
        )
        assert np.all(ok | np.asarray(band.crossed)), method


def test_default_is_exact_rmi(arm):
    traj, params, _ = arm
    _same(rmijax.bounds(traj, params), rmijax.rmi(traj, params))
    _same(
        rmijax.bounds(traj, params, mode="per_joint", window=30, noise_lo=-0.01, noise_hi=0.02),
        rmijax.rmi(traj, params, mode="per_joint", window=30, noise_lo=-0.01, noise_hi=0.02),
    )


def test_defaults_and_options_reach_each_method(arm):
    traj, params, readings = arm
    _same(
        rmijax.bounds(traj, params, method="short_window", readings=readings),
        short_window_bounds(traj, params, readings, window=rmijax.DEFAULT_WINDOWS["short_window"]),
    )
    _same(
        rmijax.bounds(
            traj, params, method="short_window", readings=readings, window=5, mode="per_joint"
        ),
        short_window_bounds(traj, params, readings, window=5, mode="per_joint"),
    )
    _same(
        rmijax.bounds(traj, params, method="corner_search", max_rounds=0, window=40),
        corner_search_bounds(traj, params, max_rounds=0, window=40),
    )
    _same(
        rmijax.bounds(traj, params, method="constant_corners", horizon="window", window=20),
        constant_corner_bounds(traj, params, horizon="window", window=20),
    )
    _same(
        rmijax.bounds(traj, params, method="linearized", margin=False),
        linearized_bounds(traj, params, window=rmijax.DEFAULT_WINDOWS["linearized"], margin=False),
    )
    loose = rmijax.bounds(traj, params, method="empirical", safety=2.0, runs=4)
    tight = rmijax.bounds(traj, params, method="empirical", safety=1.0, runs=4)
    np.testing.assert_allclose(
        np.asarray(loose.upper - loose.nominal), 2.0 * np.asarray(tight.upper - tight.nominal)
    )


def test_short_window_at_full_window_from_nominal_is_rmi(arm):
    traj, params, _ = arm
    exact = rmijax.rmi(traj, params, window=100)
    band = rmijax.bounds(traj, params, method="short_window", window=100, start="nominal")
    np.testing.assert_allclose(np.asarray(band.lower), np.asarray(exact.lower), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(band.upper), np.asarray(exact.upper), rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(method="exact"), "unknown method 'exact'"),
        (dict(method="rmi", readings=np.zeros((121, 2, 2))), "readings are used by"),
        (dict(method="empirical", window=10), "has no window"),
        (dict(method="linearized", mode="per_joint"), "mode must be 'coupled'"),
        (dict(method="constant_corners", mode="per_joint"), "mode must be 'coupled'"),
        (dict(method="empirical", mode="per_joint"), "mode must be 'coupled'"),
        (dict(method="short_window"), "readings"),
        (dict(method="corner_search", max_rounds=-1), "max_rounds"),
        (dict(method="rmi", horizon="run"), "takes no option .horizon.; its options are"),
    ],
)
def test_bad_calls_name_the_problem(arm, kwargs, message):
    traj, params, _ = arm
    with pytest.raises((ValueError, TypeError), match=message):
        rmijax.bounds(traj, params, **kwargs)
