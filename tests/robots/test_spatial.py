"""Spatial serial-chain dynamics against Pinocchio, the planar arm, and their own structure."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rmijax.robots.loaders import SHIPPED, description_path as _resolve, load_chain, load_robot
from rmijax.robots.planar import planar_arm_model
from rmijax.robots.spatial import COULOMB_VELOCITY, Payload, smooth_sign, spatial_dynamics

from arm2_urdf import arm2_urdf

pin = pytest.importorskip("pinocchio")

N_STATES = 100
FRICTION = dict(viscous=(0.0, 2.0), coulomb=(0.0, 1.5))


def _rotation(rng):
    matrix, upper = np.linalg.qr(rng.normal(size=(3, 3)))
    matrix = matrix * np.sign(np.diag(upper))[None, :]
    if np.linalg.det(matrix) < 0:
        matrix[:, 0] *= -1
    return matrix


def _rpy_of(matrix):
    """URDF roll, pitch, yaw of a rotation ``Rz(y) Ry(p) Rx(r)``."""
    pitch = np.arcsin(-matrix[2, 0])
    return np.arctan2(matrix[2, 1], matrix[2, 2]), pitch, np.arctan2(matrix[1, 0], matrix[0, 0])


def _text(values):
    """Space-separated shortest round-trip decimal text of floats."""
    return " ".join(repr(float(v)) for v in np.ravel(values))


def _inertial(rng, mass=None):
    """A random physically consistent inertial element (full tensor, rotated origin)."""
    mass = rng.uniform(0.3, 5.0) if mass is None else mass
    spread = rng.uniform(0.002, 0.05, 3)  # second moments of the mass distribution
    moments = spread.sum() - spread  # (b + c, a + c, a + b): triangle inequality holds
    frame = _rotation(rng)
    tensor = frame @ np.diag(moments) @ frame.T
    xyz, rpy = _text(rng.normal(size=3) * 0.1), _text(rng.uniform(-np.pi, np.pi, 3))
    (ixx, ixy, ixz), (_, iyy, iyz), (_, _, izz) = tensor
    values = dict(ixx=ixx, ixy=ixy, ixz=ixz, iyy=iyy, iyz=iyz, izz=izz)
    inertia = " ".join(f'{k}="{_text([v])}"' for k, v in values.items())
    return (
        f'<inertial><origin xyz="{xyz}" rpy="{rpy}"/><mass value="{_text([mass])}"/>'
        f"<inertia {inertia}/></inertial>"
    )


def random_chain_urdf(rng, n):
    """URDF of a random n-joint chain: revolute/continuous/prismatic joints with random
    axes and origins, full inertia tensors, a massive tool fixed to the tip and a
    massive side link fixed to the first body (both must merge)."""
    links = ['<link name="base">' + _inertial(rng) + "</link>"]
    joints = []
    parent = "base"
    for j in range(n):
        kind = rng.choice(["revolute", "continuous", "prismatic"], p=[0.45, 0.2, 0.35])
        axis = rng.normal(size=3) * rng.uniform(0.5, 2.0)  # not unit: the reader normalises
        xyz = rng.normal(size=3) * 0.3
        rpy = rng.uniform(-np.pi, np.pi, 3)
        links.append(f'<link name="link{j + 1}">{_inertial(rng)}</link>')
        limit = '<limit lower="-1" upper="1" effort="1" velocity="1"/>'
        joints.append(
            f'<joint name="joint{j + 1}" type="{kind}"><parent link="{parent}"/>'
            f'<child link="link{j + 1}"/><origin xyz="{_text(xyz)}" '
            f'rpy="{_text(rpy)}"/><axis xyz="{_text(axis)}"/>'
            f"{limit if kind != 'continuous' else ''}</joint>"
        )
        parent = f"link{j + 1}"
    for name, host in (("tool", parent), ("side", "link1")):
        links.append(f'<link name="{name}">{_inertial(rng)}</link>')
        xyz, rpy = _text(rng.normal(size=3) * 0.2), _text(rng.uniform(-np.pi, np.pi, 3))
        joints.append(
            f'<joint name="{name}_fixed" type="fixed"><parent link="{host}"/>'
            f'<child link="{name}"/><origin xyz="{xyz}" rpy="{rpy}"/></joint>'
        )
    return '<robot name="random">\n' + "\n".join(links + joints) + "\n</robot>\n"


def _batched(model):
    return jax.jit(jax.vmap(lambda q, qd, th: (model.mass_matrix(q, th), model.bias(q, qd, th))))


def _pinocchio_configuration(model, chain_joints, q):
    """Pinocchio's configuration vector: a continuous joint takes (cos q, sin q)."""
    configuration = np.zeros(model.nq)
    for joint, angle in zip(chain_joints, q, strict=True):
        start, size = model.joints[joint].idx_q, model.joints[joint].nq
        configuration[start : start + size] = (
            [angle] if size == 1 else [np.cos(angle), np.sin(angle)]
        )
    return configuration


def _pinocchio_reference(pin_model, joint_names, payload_link, payload_offset, q, qd, th):
    """Pinocchio's M and h with th's mass scales, payload and friction applied by hand."""
    chain_joints = [pin_model.getJointId(name) for name in joint_names]
    base = [pin_model.inertias[j].copy() for j in range(pin_model.njoints)]
    n = len(chain_joints)
    masses, references = [], []
    for qs, qds, ths in zip(q, qd, th, strict=True):
        model = pin_model.copy()
        for b, joint in enumerate(chain_joints):
            inertia = base[joint]
            model.inertias[joint] = pin.Inertia(
                ths[b] * inertia.mass, inertia.lever, ths[b] * inertia.inertia
            )
        offset = n
        if payload_link is not None:
            frame = model.frames[model.getFrameId(payload_link)]
            point = frame.placement.act(np.asarray(payload_offset, float))
            model.inertias[frame.parentJoint] += pin.Inertia(ths[n], point, np.zeros((3, 3)))
            offset += 1
        data = model.createData()
        qs = _pinocchio_configuration(model, chain_joints, qs)
        matrix = pin.crba(model, data, qs)
        masses.append(np.triu(matrix) + np.triu(matrix, 1).T)
        h = pin.nonLinearEffects(model, data, qs, qds).copy()
        if th.shape[1] > offset:
            h += ths[offset : offset + n] * qds
            h += ths[offset + n : offset + 2 * n] * np.tanh(qds / COULOMB_VELOCITY)
        references.append(h)
    return np.array(masses), np.array(references)


def _states(rng, robot, count=N_STATES):
    n = robot.n_joints
    low, high = np.asarray(robot.lo), np.asarray(robot.hi)
    q = rng.uniform(-np.pi, np.pi, (count, n))
    qd = rng.normal(size=(count, n)) * 2.0
    qd[::4, 0] = rng.choice([0.0, 1e-3, -0.02], qd[::4, 0].size)  # the smooth sign's slope
    th = low + (high - low) * rng.uniform(size=(count, low.size))
    return q, qd, th


def _relative(value, reference):
    """Largest per-state error relative to that state's largest entry."""
    axes = tuple(range(1, reference.ndim))
    scale = np.maximum(np.abs(reference).max(axis=axes), 1e-300)
    return float((np.abs(value - reference).max(axis=axes) / scale).max())


def _compare_with_pinocchio(source, robot, pin_model, rng, payload_link, payload_offset):
    q, qd, th = _states(rng, robot)
    mass, bias = _batched(robot.model)(q, qd, th)
    ref_mass, ref_bias = _pinocchio_reference(
        pin_model, load_chain(source).joint_names, payload_link, payload_offset, q, qd, th
    )
    return _relative(np.asarray(mass), ref_mass), _relative(np.asarray(bias), ref_bias)


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_arms_match_pinocchio(name, rng):
    path = str(_resolve(name))
    pin_model = pin.buildModelFromMJCF(path)
    chain = load_chain(name)
    np.testing.assert_array_equal(pin_model.gravity.linear, [0.0, 0.0, -9.81])
    np.testing.assert_allclose(pin_model.armature, chain.armature, rtol=0, atol=0)
    assert chain.armature.max() > 0 or name == "iiwa14"  # Panda, UR5e carry armature 0.1
    link, offset = chain.body_names[-2], [0.05, -0.02, 0.1]
    robot = load_robot(
        name,
        mass=0.3,
        payload=(0.0, 3.0),
        payload_link=link,
        payload_offset=offset,
        friction=FRICTION,
    )
    mass_error, bias_error = _compare_with_pinocchio(name, robot, pin_model, rng, link, offset)
    assert mass_error < 1e-9 and bias_error < 1e-9, (mass_error, bias_error)


@pytest.mark.parametrize("seed,n", [(1, 1), (2, 2), (3, 3), (4, 5), (5, 6), (6, 7), (7, 7)])
def test_random_urdf_chains_match_pinocchio(seed, n, tmp_path):
    rng = np.random.default_rng(seed)
    path = tmp_path / "chain.urdf"
    path.write_text(random_chain_urdf(rng, n))
    pin_model = pin.buildModelFromUrdf(str(path))
    assert pin_model.nv == n
    np.testing.assert_array_equal(pin_model.armature, np.zeros(n))  # a URDF has no armature
    link, offset = rng.choice(["tool", "side", f"link{n}"]), rng.normal(size=3) * 0.1
    robot = load_robot(
        path,
        mass=0.5,
        payload=(0.5, 4.0),
        payload_link=link,
        payload_offset=offset,
        friction=FRICTION,
    )
    assert robot.n_params == 3 * n + 1
    mass_error, bias_error = _compare_with_pinocchio(path, robot, pin_model, rng, link, offset)
    assert mass_error < 1e-9 and bias_error < 1e-9, (mass_error, bias_error)


def test_without_payload_or_friction_matches_pinocchio(tmp_path, rng):
    path = tmp_path / "chain.urdf"
    path.write_text(random_chain_urdf(rng, 4))
    robot = load_robot(str(path), mass=0.2)
    assert robot.model.param_names == tuple(f"mass_scale[link{j}]" for j in range(1, 5))
    mass_error, bias_error = _compare_with_pinocchio(
        path, robot, pin.buildModelFromUrdf(str(path)), rng, None, None
    )
    assert mass_error < 1e-9 and bias_error < 1e-9


def _with_every_parameter(name, tmp_path, rng, joints, payload_body, point):
    """A shipped arm (or a random chain of ``joints``) with mass scales, a payload at
    ``point`` of body ``n + payload_body`` and both friction kinds."""
    if name == "random":
        path = tmp_path / "chain.urdf"
        path.write_text(random_chain_urdf(rng, joints))
        name = path
    chain = load_chain(name)
    n = chain.n_joints
    payload = Payload(n + payload_body, np.array(point))
    return chain, spatial_dynamics(chain, payload=payload, friction=("viscous", "coulomb"))


@pytest.mark.parametrize("name", ["panda", "random"])
def test_terms_reassemble_mass_matrix_and_bias(name, tmp_path, rng):
    chain, dynamics = _with_every_parameter(name, tmp_path, rng, 6, -2, [0.1, 0.0, -0.05])
    n = chain.n_joints
    p = len(dynamics.param_names)
    assert p == 3 * n + 1 and dynamics.affine == tuple(range(n + 1, 3 * n + 1))
    count = 20
    q, qd = rng.uniform(-np.pi, np.pi, (count, n)), rng.normal(size=(count, n))
    th = np.concatenate(
        [
            rng.uniform(0.5, 1.5, (count, n)),
            rng.uniform(0, 3, (count, 1)),
            rng.uniform(0, 2, (count, 2 * n)),
        ],
        axis=1,
    )
    mass0, mass_b, bias0, bias_b = jax.jit(jax.vmap(dynamics.terms))(q, qd)
    assert mass_b.shape == (count, p, n, n) and bias_b.shape == (count, p, n)
    np.testing.assert_array_equal(mass_b[:, n + 1 :], 0.0)  # friction enters h only
    np.testing.assert_array_equal(mass0, np.broadcast_to(np.diag(chain.armature), mass0.shape))
    mass = jax.vmap(dynamics.mass_matrix)(q, th)
    bias = jax.vmap(dynamics.bias)(q, qd, th)
    assert (
        _relative(np.asarray(mass0 + jnp.einsum("sb,sbij->sij", th, mass_b)), np.asarray(mass))
        < 1e-12
    )
    assert (
        _relative(np.asarray(bias0 + jnp.einsum("sb,sbi->si", th, bias_b)), np.asarray(bias))
        < 1e-12
    )
    # the declarations the corner search relies on (rmijax.methods.linear_search)
    beyond = np.arange(n)[None, :] > np.asarray(dynamics.reach)[:, None]  # (p, n)
    np.testing.assert_array_equal(np.where(beyond[None, :, :, None], mass_b, 0.0), 0.0)
    np.testing.assert_array_equal(np.where(beyond[None, :, None, :], mass_b, 0.0), 0.0)
    np.testing.assert_array_equal(np.where(beyond[None], bias_b, 0.0), 0.0)
    for b, joint in zip(dynamics.affine, dynamics.affine_joints, strict=True):
        np.testing.assert_array_equal(np.delete(np.asarray(bias_b[:, b]), joint, axis=1), 0.0)


@pytest.mark.parametrize("name", ["panda", "random"])
def test_terms_of_many_tracks_equal_terms_of_each(name, tmp_path, rng):
    """``terms_tracks_last`` (the coupled search's batch form, tracks on the last axis)
    equals ``terms`` state by state, for prismatic joints too."""
    chain, dynamics = _with_every_parameter(name, tmp_path, rng, 7, -1, [0.0, 0.05, 0.1])
    n = chain.n_joints
    tracks = 9
    q, qd = rng.uniform(-np.pi, np.pi, (tracks, n)), rng.normal(size=(tracks, n))
    each = jax.jit(jax.vmap(dynamics.terms))(q, qd)
    many = jax.jit(dynamics.terms_tracks_last)(q.T, qd.T)
    for one, all_ in zip(each, many, strict=True):
        assert all_.shape == one.shape[1:] + (tracks,)
        scale = float(np.max(np.abs(one))) or 1.0
        np.testing.assert_allclose(np.moveaxis(np.asarray(all_), -1, 0), one, atol=1e-14 * scale)


@pytest.mark.parametrize("name", SHIPPED)
def test_mass_matrix_spd_and_passivity(name, rng):
    """M = M' > 0, and Mdot - 2C is skew with C = (1/2) dh/dqd (Christoffel form)."""
    robot = load_robot(name, mass=0.3, payload=(0.0, 2.0))
    model, nominal = robot.model, robot.nominal
    for _ in range(5):
        q, qd = rng.uniform(-np.pi, np.pi, robot.n_joints), rng.normal(size=robot.n_joints)
        mass = np.asarray(model.mass_matrix(q, nominal))
        np.testing.assert_array_equal(mass, mass.T)
        assert np.linalg.eigvalsh(mass).min() > 0
        _, mass_dot = jax.jvp(lambda x: model.mass_matrix(x, nominal), (q,), (qd,))
        coriolis = 0.5 * jax.jacfwd(lambda v, q=q: model.bias(q, v, nominal))(qd)
        residual = np.asarray(mass_dot - 2 * coriolis)
        scale = np.abs(np.asarray(mass_dot)).max()
        assert scale > 1e-3  # the check is not vacuous
        np.testing.assert_allclose(residual, -residual.T, atol=1e-12 * scale)


@pytest.mark.parametrize("inertia", [0.0, 1e-3])
def test_planar_two_joint_urdf_equals_planar_model(inertia, tmp_path, rng):
    path = tmp_path / "arm2.urdf"
    path.write_text(arm2_urdf(inertia=inertia))
    robot = load_robot(path)
    planar = planar_arm_model(2)
    th_planar = np.array([12.0, 10.0, 1.5, 1.0])
    pin_model = pin.buildModelFromUrdf(str(path))
    pin_data = pin_model.createData()
    for _ in range(20):
        q, qd = rng.uniform(-np.pi, np.pi, 2), rng.normal(size=2) * 2
        mass = np.asarray(robot.model.mass_matrix(q, robot.nominal))
        bias = np.asarray(robot.model.bias(q, qd, robot.nominal))
        # Rotational inertia about the joint axes adds I (both links) and I (link 2 only).
        extra = inertia * np.array([[2.0, 1.0], [1.0, 1.0]])
        np.testing.assert_allclose(
            mass, np.asarray(planar.mass_matrix(q, th_planar)) + extra, rtol=1e-12, atol=1e-12
        )
        np.testing.assert_allclose(
            bias, np.asarray(planar.bias(q, qd, th_planar)), rtol=1e-12, atol=1e-10
        )
        reference = pin.crba(pin_model, pin_data, q)
        np.testing.assert_allclose(mass, np.triu(reference) + np.triu(reference, 1).T, rtol=1e-12)
        np.testing.assert_allclose(
            bias, pin.nonLinearEffects(pin_model, pin_data, q, qd), rtol=1e-12, atol=1e-10
        )


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_jit_vmap_over_4096_pairs(dtype, rng):
    robot = load_robot("panda", mass=0.2, payload=(0.0, 3.0), friction=FRICTION)
    q, qd, th = _states(rng, robot, 4096)
    mass, bias = _batched(robot.model)(*(jnp.asarray(x, dtype) for x in (q, qd, th)))
    assert mass.dtype == dtype and bias.dtype == dtype
    assert mass.shape == (4096, 7, 7) and bias.shape == (4096, 7)
    ref_mass, ref_bias = _batched(robot.model)(q, qd, th)
    tolerance = 1e-5 if dtype == jnp.float32 else 1e-14
    assert _relative(np.asarray(mass, np.float64), np.asarray(ref_mass)) < tolerance
    assert _relative(np.asarray(bias, np.float64), np.asarray(ref_bias)) < 10 * tolerance
    fd = jax.jit(jax.vmap(robot.model.forward_dynamics))
    qdd = fd(q, qd, np.asarray(ref_bias), th)  # tau = h: zero acceleration
    np.testing.assert_allclose(np.asarray(qdd), 0.0, atol=1e-9)


def test_smooth_sign():
    speed = 10 * COULOMB_VELOCITY
    values = np.asarray(smooth_sign(jnp.array([-speed, -COULOMB_VELOCITY, 0.0, 0.5 * speed])))
    np.testing.assert_allclose(values, [-np.tanh(10.0), -np.tanh(1.0), 0.0, np.tanh(5.0)])
    assert COULOMB_VELOCITY == 0.1  # rad/s: the documented physical choice (Gaz et al. 2019)
