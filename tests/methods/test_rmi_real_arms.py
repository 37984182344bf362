"""Exact RMI on arms loaded from robot description files.

The paper's two-joint arm written as a URDF (its plane vertical, point masses at
the link tips) with the mass intervals given as scales gives the planar model's
bounds; the search follows the loaded model's declared structure, so friction
adds no evaluated corner.
"""

import jax.numpy as jnp
import numpy as np
import pytest

import rmijax
from rmijax.methods.choosers import LinearChooser, resolve

from arm2_urdf import arm2_urdf


@pytest.fixture(scope="module")
def urdf_arm2(tmp_path_factory):
    path = tmp_path_factory.mktemp("arm2") / "arm2.urdf"
    path.write_text(arm2_urdf())
    return path


def planar_arm2_lengths_certain():
    nominal = [12.0, 10.0, 1.5, 1.0]
    return rmijax.planar_arm(nominal, [11.0, 9.0, 1.5, 1.0], [13.0, 11.0, 1.5, 1.0])


@pytest.mark.parametrize("mode", ["coupled", "per_joint"])
@pytest.mark.parametrize("paths", [["hold", "sine"], ["slow_sine", "composite"]])
def test_urdf_two_joint_arm_gives_the_planar_bounds(urdf_arm2, mode, paths):
    loaded = rmijax.load_robot(urdf_arm2, mass=(1 / 12, 0.1))
    np.testing.assert_allclose(loaded.lo, [11 / 12, 0.9], rtol=1e-15)
    traj = rmijax.trajectory(paths, duration=2.0)
    want = rmijax.rmi(traj, planar_arm2_lengths_certain(), mode=mode)
    got = rmijax.rmi(traj, loaded, mode=mode)
    np.testing.assert_allclose(got.lower, want.lower, rtol=0, atol=1e-10)
    np.testing.assert_allclose(got.upper, want.upper, rtol=0, atol=1e-10)
    assert float(jnp.max(got.width)) > 1e-3  # the mass box matters


def test_friction_adds_no_evaluated_corner():
    """Mass scales and payload are enumerated (2^8 on the Panda); friction is chosen by sign."""
    plain = rmijax.load_robot("panda", mass=0.1, payload=(0.0, 1.0))
    rough = rmijax.load_robot(
        "panda", mass=0.1, payload=(0.0, 1.0), friction=dict(viscous=(0.0, 0.5), coulomb=(0.0, 0.5))
    )
    assert (plain.n_params, rough.n_params) == (8, 22)
    for params in (plain, rough):
        search = resolve(params.model, "auto")
        assert isinstance(search, LinearChooser)
        assert search.n_evaluated == 2**8
    assert resolve(rough.model, "auto").affine == tuple(range(8, 22))
