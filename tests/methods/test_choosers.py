"""The engine takes its corner search from the model's declared structure.

A user model that declares which parameters enter ``h`` only, affinely
(:class:`rmijax.AffineBias`), gets exactly the bounds of plain enumeration,
tie rule included, while evaluating ``2^(p - a)`` corners instead of ``2^p``.
"""

import collections
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rmijax
from rmijax.methods.choosers import (
    LinearChooser,
    StructuredChooser,
    enumerate_corners,
    pick_corner,
    resolve,
    structured_pick,
)
from rmijax.methods.planar_search import SEARCH
from rmijax.methods.rmi import DEFAULT_MEMORY_BUDGET, _rmi_from_starts
from rmijax.robots.loaders import load_robot
from rmijax.robots.planar import planar_bias, planar_mass_matrix

LENGTHS = (1.5, 1.0)
SMOOTH_VELOCITY = 0.05  # rad/s, the smooth sign's scale in the test model

# th = (b1, m1, b2, c1, m2, c2): viscous b, Coulomb c and masses m, interleaved so the
# sign choice must respect the contract's bit order between affine and enumerated bits.
MASS_INDEX = (1, 4)
AFFINE = (0, 2, 3, 5)


def _planar(th):
    return jnp.stack([th[1], th[4], *(jnp.asarray(x, th.dtype) for x in LENGTHS)])


def _mass(q, th):
    return planar_mass_matrix(q, _planar(th))


def _bias(q, qd, th, counter=None):
    if counter is not None:
        # one value per (state, parameter) pair: under vmap the callback sees the whole batch
        jax.debug.callback(counter, q[0] + th[0], ordered=False)
    viscous = jnp.stack([th[0], th[2]])
    coulomb = jnp.stack([th[3], th[5]])
    friction = viscous * qd + coulomb * jnp.tanh(qd / SMOOTH_VELOCITY)
    return planar_bias(q, qd, _planar(th)) + friction


def _terms(q, qd):
    """The friction arm is affine in every parameter (masses with the lengths fixed)."""
    zero = jnp.zeros(6, q.dtype)
    m_terms = jnp.moveaxis(jax.jacfwd(_mass, argnums=1)(q, zero), -1, 0)
    h_terms = jnp.moveaxis(jax.jacfwd(_bias, argnums=2)(q, qd, zero), -1, 0)
    return _mass(q, zero), m_terms, _bias(q, qd, zero), h_terms


def friction_arm(structure=True, counter=None, linear=False):
    if linear:
        declared = rmijax.LinearDynamics(affine=AFFINE, terms=_terms)
    else:
        declared = rmijax.AffineBias(affine=AFFINE) if structure else None
    model = rmijax.RobotModel(
        n_joints=2,
        n_params=6,
        mass_matrix=_mass,
        bias=lambda q, qd, th: _bias(q, qd, th, counter),
        name="arm2_friction",
        param_names=("b1", "m1", "b2", "c1", "m2", "c2"),
        structure=declared,
    )
    nominal = np.array([0.5, 12.0, 0.4, 0.3, 10.0, 0.2])
    lo = np.array([0.0, 11.0, 0.0, 0.0, 9.0, 0.0])
    hi = np.array([1.0, 13.0, 0.8, 0.6, 11.0, 0.4])
    return rmijax.uncertain_robot(model, nominal, lo, hi)


@pytest.mark.parametrize("linear", [False, True], ids=["affine_bias", "linear_dynamics"])
@pytest.mark.parametrize("mode", ["coupled", "per_joint"])
@pytest.mark.parametrize("paths", [["hold", "sine"], ["slow_sine", "composite"]])
def test_affine_structure_equals_enumeration(mode, paths, linear):
    params = friction_arm(linear=linear)
    traj = rmijax.trajectory(paths, duration=0.6)
    structured = rmijax.rmi(traj, params, mode=mode, window=25)
    enumerated = rmijax.rmi(traj, params, mode=mode, window=25, search="enumerate")
    np.testing.assert_allclose(structured.lower, enumerated.lower, rtol=0, atol=1e-10)
    np.testing.assert_allclose(structured.upper, enumerated.upper, rtol=0, atol=1e-10)
    # the friction box matters: the bands are wider than without it
    frictionless = params.with_box(
        lo=params.lo.at[jnp.array(AFFINE)].set(params.nominal[jnp.array(AFFINE)]),
        hi=params.hi.at[jnp.array(AFFINE)].set(params.nominal[jnp.array(AFFINE)]),
    )
    narrow = rmijax.rmi(traj, frictionless, mode=mode, window=25)
    assert float(jnp.max(structured.width - narrow.width)) > 1e-4


def _count_bias_calls(search):
    calls = collections.Counter()
    params = friction_arm(counter=lambda th: calls.update({"bias": np.size(th)}))
    traj = rmijax.trajectory(["slow_sine", "composite"], duration=0.1)
    rmijax.check_model(params, traj)  # the model check runs (and is cached) before any run
    jax.effects_barrier()
    calls.clear()
    bounds = rmijax.rmi_step(traj, params, 10, window=3, search=search)
    jax.block_until_ready(bounds.upper)
    return calls["bias"], bounds


def test_affine_structure_evaluates_fewer_corners():
    """Count the bias evaluations of one end step (4n = 8 tracks, 3 window steps)."""
    structured_calls, structured = _count_bias_calls("auto")
    enumerated_calls, enumerated = _count_bias_calls("enumerate")
    np.testing.assert_allclose(structured.upper, enumerated.upper, rtol=0, atol=1e-12)
    np.testing.assert_allclose(structured.lower, enumerated.lower, rtol=0, atol=1e-12)
    track_steps = 8 * 3
    # per track step: the nominal torque, every corner, and the chosen corner once more
    assert enumerated_calls == track_steps * (1 + 2**6 + 1)
    # per track step: the nominal torque, 2^2 mass corners (value and slope), the chosen one
    assert structured_calls == track_steps * (1 + 2 * 2**2 + 1)


def test_resolve_follows_the_declaration():
    arm = rmijax.paper_arm2()
    assert resolve(arm.model, "auto") is SEARCH
    assert resolve(arm.model, "enumerate") is enumerate_corners
    assert isinstance(resolve(friction_arm().model, "auto"), StructuredChooser)
    assert isinstance(resolve(friction_arm(linear=True).model, "auto"), LinearChooser)
    assert resolve(friction_arm(structure=False).model, "auto") is enumerate_corners
    bad = rmijax.RobotModel(2, 2, _mass, _bias, structure=rmijax.AffineBias(affine=(5,)))
    with pytest.raises(ValueError, match="affine parameter index 5"):
        resolve(bad, "auto")
    with pytest.raises(ValueError, match="distinct non-negative"):
        rmijax.AffineBias(affine=(1, 1))


def test_structured_pick_equals_pick_corner_on_random_scores(rng):
    """Brute force over every corner of a score affine in the affine bits, ties included."""
    p_enum, p_aff = 3, 3
    enumerated, affine = (0, 2, 5), (1, 3, 4)
    for trial in range(300):
        base = rng.normal(size=2**p_enum)
        span = rng.normal(size=(2**p_enum, p_aff))
        if trial % 3 == 0:  # exact ties: zero coefficients and repeated corners
            span[:, rng.integers(p_aff)] = 0.0
            base[rng.integers(2**p_enum)] = base[0]
        if trial % 5 == 0:  # near-ties inside the tolerance
            span[:, 0] *= 1e-13
        offset = rng.normal()
        scores = np.empty(2 ** (p_enum + p_aff))
        for c in range(scores.size):
            bits = [(c >> b) & 1 for b in range(6)]
            e = sum(bits[b] << k for k, b in enumerate(enumerated))
            scores[c] = base[e] + sum(span[e, j] * bits[b] for j, b in enumerate(affine))
        want = int(pick_corner(jnp.asarray(scores), offset))
        e, a_bits = structured_pick(
            jnp.asarray(base), jnp.asarray(span), offset, enumerated, affine
        )
        bits = [0] * 6
        for k, b in enumerate(enumerated):
            bits[b] = (int(e) >> k) & 1
        for j, b in enumerate(affine):
            bits[b] = int(a_bits[j])
        assert sum(bit << b for b, bit in enumerate(bits)) == want, trial


# A small spatial arm (base yaw, then two pitch joints off a rolled frame, inertias with
# products), the real-arm path at a size where all 2^10 corners can be enumerated.
ARM3_URDF = """<robot name="arm3">
  <link name="base"/>
  <link name="l1"><inertial><origin xyz="0 0.02 0.15"/><mass value="3.0"/>
    <inertia ixx="0.02" iyy="0.025" izz="0.01" ixy="0.001" ixz="0" iyz="0.002"/></inertial></link>
  <link name="l2"><inertial><origin xyz="0.2 0 0.01"/><mass value="2.0"/>
    <inertia ixx="0.004" iyy="0.03" izz="0.03" ixy="0" ixz="0.001" iyz="0"/></inertial></link>
  <link name="l3"><inertial><origin xyz="0.15 0.01 0"/><mass value="1.0"/>
    <inertia ixx="0.002" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>
    <origin xyz="0 0 0.1"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="100" velocity="5"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>
    <origin xyz="0 0 0.3" rpy="0.1 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" effort="100" velocity="5"/></joint>
  <joint name="j3" type="revolute"><parent link="l2"/><child link="l3"/>
    <origin xyz="0.4 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" effort="100" velocity="5"/></joint>
</robot>"""


@pytest.fixture(scope="module")
def arm3_case(tmp_path_factory):
    """The arm with a box of p = 10 (3 mass scales, payload, 6 friction), a rest-to-rest
    move and its bounds by enumeration of all 2^10 corners."""
    path = tmp_path_factory.mktemp("arm3") / "arm3.urdf"
    path.write_text(ARM3_URDF)
    friction = dict(viscous=(0.0, 0.5), coulomb=(0.0, 0.5))
    params = load_robot(path, mass=0.2, payload=(0.0, 1.0), friction=friction)
    home = np.array([0.1, -0.5, 1.0])
    traj = rmijax.waypoint_trajectory([home, home + 0.4, home], segment_time=0.25, dt=0.01)
    return params, traj, rmijax.rmi(traj, params, window=12, search="enumerate")


def _declaring(params, declared):
    """``params`` whose model declares less than ``load_robot``'s (``"chain"``: all of it)."""
    keep = {
        "chain": {},
        "chain_vmap": dict(terms_tracks_last=None),  # terms of one state, by vmap
        "dense": dict(reach=None),
        "dense_bias": dict(reach=None, affine_joints=None),
    }[declared]
    structure = dataclasses.replace(params.model.structure, **keep)
    model = dataclasses.replace(params.model, structure=structure)
    return rmijax.uncertain_robot(model, params.nominal, params.lo, params.hi)


@pytest.mark.parametrize("declared", ["chain", "chain_vmap", "dense", "dense_bias"])
def test_real_arm_search_equals_enumeration(declared, arm3_case):
    """load_robot's LinearDynamics search equals enumeration in coupled mode, windows
    starting at rest and zero costate weights at the last step included (exact ties),
    also when the model declares less (no batch terms, no ``reach``, no
    ``affine_joints``)."""
    params, traj, enumerated = arm3_case
    structure = params.model.structure
    assert structure.reach == (0, 1, 2, 2, 0, 1, 2, 0, 1, 2)
    params = _declaring(params, declared)
    structured = rmijax.rmi(traj, params, window=12)
    np.testing.assert_allclose(structured.lower, enumerated.lower, rtol=0, atol=1e-10)
    np.testing.assert_allclose(structured.upper, enumerated.upper, rtol=0, atol=1e-10)
    assert float(jnp.min(structured.width)) >= 0 and float(jnp.max(structured.width)) > 1e-4


@pytest.mark.parametrize("declared", ["chain", "dense_bias"])
@pytest.mark.parametrize("start", ["nominal", "measured"])
def test_one_step_windows_equal_enumeration(declared, start, arm3_case):
    """Windows of one step (the monitor's cheapest tick) take the shared start once and
    search the tachometer tracks only; the bounds equal enumeration's, the readings'
    start included (all tracks from one measured state)."""
    params, traj, _ = arm3_case
    params = _declaring(params, declared)
    th = np.asarray(params.nominal) + 0.5 * (np.asarray(params.hi) - np.asarray(params.nominal))
    _, readings = rmijax.simulate(traj, params, th)
    starts = None if start == "nominal" else jnp.asarray(readings)
    no_noise = jnp.zeros((traj.n_joints, 2))
    got, want = (
        _rmi_from_starts(
            traj,
            params,
            starts,
            no_noise,
            no_noise,
            mode="coupled",
            window=1,
            memory_budget=DEFAULT_MEMORY_BUDGET,
            chunk_size=None,
            progress=False,
            search=search,
        )
        for search in ("auto", "enumerate")
    )
    np.testing.assert_allclose(got.lower, want.lower, rtol=0, atol=1e-10)
    np.testing.assert_allclose(got.upper, want.upper, rtol=0, atol=1e-10)
    assert float(jnp.max(got.upper[..., 1] - got.lower[..., 1])) > 1e-4


def test_divide_free_reciprocal_is_within_a_few_ulps(rng):
    """The search's pivots use a Newton reciprocal (no divide, so XLA keeps one loop)."""
    from rmijax._linalg import reciprocal

    x = np.concatenate([np.exp(rng.uniform(-300, 300, 20000)), np.linspace(0.5, 2.0, 1001)])
    x = np.concatenate([x, -x])
    np.testing.assert_allclose(np.asarray(reciprocal(jnp.asarray(x))) * x, 1.0, rtol=0, atol=5e-16)
