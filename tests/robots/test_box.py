"""Parameter box and corners (SPEC section 2)."""

import numpy as np
import pytest

import rmijax


def test_corner_bit_order():
    lo, hi = np.array([1.0, 2.0, 3.0]), np.array([10.0, 20.0, 30.0])
    corners = np.asarray(rmijax.corner_tensor(lo, hi))
    assert corners.shape == (8, 3)
    for c in range(8):
        for b in range(3):
            assert corners[c, b] == (hi[b] if (c >> b) & 1 else lo[b])


@pytest.mark.parametrize("n", [1, 2, 3, 6, 8])
def test_preset_sizes_and_values(n):
    arm = rmijax.preset_arm(n)
    assert (arm.n_joints, arm.n_params, arm.n_corners) == (n, 2 * n, 4**n)
    assert arm.corners.shape == (4**n, 2 * n)
    nominal, lo = np.asarray(arm.nominal), np.asarray(arm.lo)
    np.testing.assert_array_equal(nominal[[0, n]], [12.0, 1.5])
    np.testing.assert_array_equal(lo[[0, n]], [11.0, 1.49])
    if n > 1:
        np.testing.assert_array_equal(arm.nominal[1:n], 10.0)
        np.testing.assert_array_equal(arm.hi[n + 1 :], 1.01)


def test_paper_presets():
    pendulum = rmijax.paper_pendulum()
    np.testing.assert_array_equal(pendulum.nominal, [10.0, 1.0])
    np.testing.assert_array_equal(pendulum.lo, [9.0, 0.99])
    np.testing.assert_array_equal(pendulum.hi, [11.0, 1.01])
    arm = rmijax.paper_arm2()
    np.testing.assert_array_equal(arm.nominal, [12.0, 10.0, 1.5, 1.0])
    np.testing.assert_array_equal(arm.lo, [11.0, 9.0, 1.49, 0.99])
    np.testing.assert_array_equal(arm.hi, [13.0, 11.0, 1.51, 1.01])
    assert arm.corners.shape == (16, 4)


def test_dtype_follows_inputs():
    arm = rmijax.planar_arm(
        np.float32([10.0, 1.0]), np.float32([9.0, 0.99]), np.float32([11.0, 1.01])
    )
    assert arm.nominal.dtype == np.float32 and arm.corners.dtype == np.float32
    assert rmijax.paper_pendulum().nominal.dtype == np.float64  # x64 on in the tests


def test_lo_above_hi_is_rejected():
    with pytest.raises(ValueError, match=r"lo > hi for parameter m1.*Swap"):
        rmijax.planar_arm([10.0, 1.0], [11.0, 0.99], [9.0, 1.01])


def test_nominal_outside_box_is_rejected():
    with pytest.raises(ValueError, match=r"nominal value of parameter l1.*outside its box"):
        rmijax.planar_arm([10.0, 1.2], [9.0, 0.99], [11.0, 1.01])


@pytest.mark.parametrize(
    "args, match",
    [
        (([10.0, 1.0, 2.0], [9.0, 0.99, 1.0], [11.0, 1.01, 3.0]), "even length"),
        (([10.0, 1.0], [9.0, 0.99, 1.0], [11.0, 1.01]), r"lo has shape \(3,\)"),
        (([10.0, 1.0], [9.0, 0.99], [11.0, np.nan]), "non-finite"),
        (([1.0, 1.0], [0.0, 0.99], [2.0, 1.01]), "must be positive"),
    ],
)
def test_bad_boxes(args, match):
    with pytest.raises(ValueError, match=match):
        rmijax.planar_arm(*args)


def test_with_box_and_certain_parameters():
    arm = rmijax.paper_arm2()
    certain = arm.with_box(lo=arm.nominal, hi=arm.nominal)
    assert np.all(np.asarray(certain.corners) == np.asarray(arm.nominal))
