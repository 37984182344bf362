"""load_robot: readers (URDF, MJCF subset, MJCF through MuJoCo), the box, and every refusal."""

import dataclasses
import sys

import jax
import numpy as np
import pytest

from rmijax.robots.box import UncertainRobot
from rmijax.robots.loaders import (
    FRICTION_DAMPING_SHARE,
    SHIPPED,
    _friction_bounds,
    default_box,
    load_chain,
    load_robot,
)
from rmijax.robots.spatial import COULOMB_VELOCITY, spatial_dynamics
from rmijax.robots.structure import LinearDynamics

mujoco = pytest.importorskip("mujoco")

CHAIN_FIELDS = ("rotations", "translations", "axes", "armature", "masses", "coms", "inertias")

# A 3-joint arm in the explicit subset, exercising every orientation form the reader knows.
SUBSET_MJCF = """<mujoco model="subset">
  <compiler angle="degree" eulerseq="zyx"/>
  <worldbody>
    <body name="base" pos="0.1 0 0.2" euler="10 20 30">
      <inertial pos="0 0 0" mass="3" diaginertia="0.1 0.1 0.1"/>
      <body name="a" pos="0 0 0.3" axisangle="1 1 0 40">
        <inertial pos="0.01 0.02 0.1" quat="0.9 0.1 0.3 0.2" mass="2"
                  diaginertia="0.03 0.04 0.05"/>
        <joint name="j1" type="hinge" axis="0 1 1" pos="0.02 0 0.01" armature="0.05"/>
        <body name="b" pos="0.2 0 0.1" xyaxes="0 1 0 -1 0 0.2">
          <inertial pos="0 0.05 0.02" mass="1.5" euler="5 -10 15" diaginertia="0.02 0.02 0.01"/>
          <joint name="j2" type="slide" axis="1 0 0"/>
          <body name="c" pos="0 0.1 0.2" zaxis="0.3 -0.2 1">
            <inertial pos="0.03 0 0.04" mass="0.8"
                      fullinertia="0.01 0.012 0.008 0.001 -0.002 0.0005"/>
            <joint name="j3" axis="1 0 0" pos="0 0 -0.05"/>
            <body name="tool" pos="0 0 0.1" quat="0 1 0 0">
              <inertial pos="0.01 0 0" mass="0.4" diaginertia="0.001 0.001 0.001"/>
              <site name="tcp"/>
            </body>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""

# The same kind of arm written with constructs only MuJoCo's compiler reads: default classes,
# childclass, inertia from a primitive geom, and a mesh whose file does not exist.
COMPILED_MJCF = """<mujoco model="compiled">
  <compiler angle="radian"/>
  <asset><mesh name="shell" file="no/such/shell.stl"/></asset>
  <default>
    <default class="arm"><joint axis="0 0 1" armature="0.2"/>
      <default class="heavy"><joint armature="0.3"/></default>
    </default>
  </default>
  <worldbody>
    <body name="l1" pos="0 0 0.3" childclass="arm">
      <inertial pos="0 0 0.1" mass="4" diaginertia="0.05 0.05 0.02"/>
      <joint name="j1"/>
      <geom type="mesh" mesh="shell"/>
      <body name="l2" pos="0 0.1 0.2" euler="1.2 0 0.3">
        <inertial pos="0.1 0 0" mass="3" diaginertia="0.02 0.03 0.03"/>
        <joint name="j2" class="heavy" axis="0 1 0"/>
        <body name="side" pos="0 0.2 0">
          <geom type="box" size="0.05 0.02 0.03" mass="0.5"/>
        </body>
        <body name="l3" pos="0.3 0 0">
          <inertial pos="0.05 0 0" mass="1" diaginertia="0.01 0.01 0.005"/>
          <joint name="j3" axis="1 0 0" pos="0.01 0 0"/>
          <geom type="mesh" mesh="shell"/>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


def _mujoco_dynamics(xml, q, qd):
    """MuJoCo's own M (with armature) and qfrc_bias at each state (gravity 9.81 along -z)."""
    model = mujoco.MjModel.from_xml_string(xml)
    np.testing.assert_array_equal(model.opt.gravity, [0.0, 0.0, -9.81])
    data = mujoco.MjData(model)
    masses, biases = [], []
    for qs, qds in zip(q, qd, strict=True):
        data.qpos[:], data.qvel[:] = qs, qds
        mujoco.mj_forward(model, data)
        matrix = np.zeros((model.nv, model.nv))
        mujoco.mj_fullM(model, data, matrix)
        masses.append(matrix)
        biases.append(data.qfrc_bias.copy())
    return np.array(masses), np.array(biases)


def _assert_matches_mujoco(robot, xml, rng):
    q = rng.uniform(-np.pi, np.pi, (30, robot.n_joints))
    qd = rng.normal(size=(30, robot.n_joints))
    th = np.broadcast_to(np.asarray(robot.nominal), (30, robot.n_params))
    mass = jax.vmap(robot.model.mass_matrix)(q, th)
    bias = jax.vmap(robot.model.bias)(q, qd, th)
    ref_mass, ref_bias = _mujoco_dynamics(xml, q, qd)
    np.testing.assert_allclose(np.asarray(mass), ref_mass, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(np.asarray(bias), ref_bias, rtol=1e-10, atol=1e-10)


def _assert_same_chain(first, second):
    assert first.joint_names == second.joint_names
    assert first.body_names == second.body_names
    assert first.joint_types == second.joint_types
    for field in CHAIN_FIELDS:
        np.testing.assert_allclose(
            getattr(first, field), getattr(second, field), rtol=1e-12, atol=1e-14, err_msg=field
        )


@pytest.mark.parametrize("name", SHIPPED)
def test_both_mjcf_readers_give_the_same_chain_on_shipped_arms(name):
    _assert_same_chain(load_chain(name, reader="stdlib"), load_chain(name, reader="mujoco"))
    assert load_chain(name).n_joints == (6 if name == "ur5e" else 7)


def test_subset_mjcf_both_readers_and_mujoco_dynamics(tmp_path, rng):
    path = tmp_path / "subset.xml"
    path.write_text(SUBSET_MJCF)
    stdlib = load_chain(path, reader="stdlib")
    _assert_same_chain(stdlib, load_chain(path, reader="mujoco"))
    assert stdlib.joint_types == ("revolute", "prismatic", "revolute")
    np.testing.assert_allclose(stdlib.masses[-1], 0.8 + 0.4)  # the tool merged into body c
    _assert_matches_mujoco(load_robot(path), SUBSET_MJCF, rng)


def test_subset_mjcf_loads_without_mujoco(tmp_path, monkeypatch):
    path = tmp_path / "subset.xml"
    path.write_text(SUBSET_MJCF)
    monkeypatch.setitem(sys.modules, "mujoco", None)  # import mujoco now fails
    for source in (*SHIPPED, path):
        assert load_robot(source).n_joints >= 3


def test_compiled_mjcf_matches_mujoco_without_its_mesh_files(tmp_path, rng):
    path = tmp_path / "compiled.xml"
    path.write_text(COMPILED_MJCF)
    robot = load_robot(path)
    chain = load_chain(path)
    np.testing.assert_allclose(chain.armature, [0.2, 0.3, 0.2])
    oracle = COMPILED_MJCF.replace('<geom type="mesh" mesh="shell"/>', "").replace(
        '<asset><mesh name="shell" file="no/such/shell.stl"/></asset>', ""
    )
    _assert_matches_mujoco(robot, oracle, rng)


def test_compiled_mjcf_needs_mujoco(tmp_path, monkeypatch):
    path = tmp_path / "compiled.xml"
    path.write_text(COMPILED_MJCF)
    monkeypatch.setitem(sys.modules, "mujoco", None)
    with pytest.raises(ImportError, match=r'pip install "rmijax\[mjcf\]"') as error:
        load_robot(path)
    assert "compiled.xml" in str(error.value) and "default" in str(error.value)


def test_mesh_inertia_is_refused(tmp_path):
    path = tmp_path / "mesh.xml"
    path.write_text(
        COMPILED_MJCF.replace(
            '<inertial pos="0.05 0 0" mass="1" diaginertia="0.01 0.01 0.005"/>', ""
        )
    )
    with pytest.raises(ValueError, match=r"'l3'.*mesh geom.*explicit <inertial>"):
        load_robot(path)


def test_box_layout_and_model(tmp_path):
    robot = load_robot(
        "panda",
        mass=[0.1, 0.2, 0.3, 0.0, 0.1, 0.1, 0.1],
        payload=(0.5, 3.0, 1.0),
        payload_link="link7",
        payload_offset=(0, 0, 0.1),
        friction=dict(viscous=(0.1, 0.5), coulomb=np.tile([0.0, 2.0], (7, 1))),
    )
    assert isinstance(robot, UncertainRobot) and robot.n_params == 7 + 1 + 14
    names = robot.model.param_names
    assert names[0] == "mass_scale[link1]" and names[7] == "payload_mass"
    assert names[8] == "viscous[joint1]" and names[15] == "coulomb[joint1]"
    np.testing.assert_allclose(robot.lo[:8], [0.9, 0.8, 0.7, 1.0, 0.9, 0.9, 0.9, 0.5])
    np.testing.assert_allclose(robot.hi[:8], [1.1, 1.2, 1.3, 1.0, 1.1, 1.1, 1.1, 3.0])
    np.testing.assert_allclose(robot.nominal[:8], [1, 1, 1, 1, 1, 1, 1, 1.0])
    np.testing.assert_allclose(robot.nominal[8:], [0.3] * 7 + [1.0] * 7)
    structure = robot.model.structure
    assert isinstance(structure, LinearDynamics) and structure.affine == tuple(range(8, 22))
    assert robot.model.name == "panda" and robot.dtype == np.float64
    hash(robot.model)  # a static argument of jax.jit
    only_viscous = load_robot("ur5e", friction=dict(viscous=(0.0, 1.0)))
    assert only_viscous.model.param_names[6:] == tuple(
        f"viscous[{j}]" for j in load_chain("ur5e").joint_names
    )
    assert load_robot("iiwa14", dtype=np.float32).nominal.dtype == np.float32


def test_two_loads_of_one_arm_share_the_model_and_its_compilation():
    first = load_robot("ur5e", mass=0.1, payload=(0.0, 1.0))
    second = load_robot("ur5e", mass=0.2, payload=(0.0, 2.0))  # another box, same layout
    assert second.model == first.model and hash(second.model) == hash(first.model)
    assert second.model.structure.layout is first.model.structure.layout
    traces = []

    @jax.jit
    def mass_matrix(robot, q):
        traces.append(robot.model.name)  # runs once per compilation
        return robot.model.mass_matrix(q, robot.nominal)

    q = np.linspace(-1.0, 1.0, 6)
    for robot in (first, second):
        want = robot.model.mass_matrix(q, robot.nominal)
        np.testing.assert_allclose(mass_matrix(robot, q), want, rtol=1e-13, atol=1e-14)
    assert traces == ["ur5e"]
    # another payload point, friction layout or chain is another model
    offset = load_robot("ur5e", payload=(0.0, 1.0), payload_offset=(0, 0, 0.1))
    viscous = load_robot("ur5e", payload=(0.0, 1.0), friction=dict(viscous=(0, 1)))
    assert offset.model != first.model and viscous.model != first.model
    assert load_robot("ur5e", payload=(0.0, 1.0)).model == first.model
    chain = load_chain("ur5e")
    heavier = dataclasses.replace(chain, masses=chain.masses * (1 + 2**-52 * np.arange(6)))
    assert spatial_dynamics(heavier) is not spatial_dynamics(chain)
    assert spatial_dynamics(dataclasses.replace(chain)) is spatial_dynamics(chain)


def test_payload_on_a_fixed_link_is_carried_by_its_body(tmp_path, rng):
    """A payload on the tool (fixed to link c) equals one on c at the tool's point."""
    path = tmp_path / "subset.xml"
    path.write_text(SUBSET_MJCF)
    on_tool = load_robot(path, payload=(1.0, 1.0), payload_link="tool", payload_offset=(0.1, 0, 0))
    # tool frame in c's frame: pos (0, 0, 0.1), quat (0 1 0 0) turns x to x, y to -y, z to -z.
    on_body = load_robot(path, payload=(1.0, 1.0), payload_link="c", payload_offset=(0.1, 0, 0.1))
    q, qd = rng.normal(size=3), rng.normal(size=3)
    np.testing.assert_allclose(
        on_tool.model.mass_matrix(q, on_tool.nominal),
        on_body.model.mass_matrix(q, on_body.nominal),
        rtol=1e-13,
    )
    np.testing.assert_allclose(
        on_tool.model.bias(q, qd, on_tool.nominal),
        on_body.model.bias(q, qd, on_body.nominal),
        rtol=1e-12,
    )


# --------------------------------------------------------------------------
# Refusals: each names the file/element or the argument, and the fix
# --------------------------------------------------------------------------

URDF = """<robot name="bad">
  <link name="base"/>
  <link name="l1"><inertial><mass value="{m1}"/>
    <inertia ixx="{ixx}" iyy="0.1" izz="0.1" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="l2"><inertial><origin xyz="0.1 0 0"/><mass value="1"/>
    <inertia ixx="0.1" iyy="0.1" izz="0.1" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <joint name="j1" type="{kind}"><parent link="base"/><child link="l1"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="{parent2}"/><child link="l2"/>
    <origin xyz="0 0 0.3"/><axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/>
  </joint>
  {extra}
</robot>
"""


def _urdf(tmp_path, m1="2", ixx="0.1", kind="revolute", parent2="l1", extra=""):
    path = tmp_path / "arm.urdf"
    path.write_text(URDF.format(m1=m1, ixx=ixx, kind=kind, parent2=parent2, extra=extra))
    return path


def test_valid_urdf_loads(tmp_path):
    assert load_robot(_urdf(tmp_path)).n_joints == 2


BRANCH = """<link name="l3"><inertial><mass value="1"/>
    <inertia ixx="0.1" iyy="0.1" izz="0.1" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <joint name="j3" type="prismatic"><parent link="l1"/><child link="l3"/><axis xyz="1 0 0"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>"""


@pytest.mark.parametrize(
    "change,message",
    [
        (dict(kind="floating"), r"<joint name='j1' type='floating'>.*floating base.*Remove"),
        (dict(kind="planar"), r"<joint name='j1' type='planar'>.*unsupported joint type"),
        (dict(m1="0"), r"moving <body/link name='l1'> has mass 0.*positive mass"),
        (dict(m1="-1"), r"<link name='l1'> <inertial> has mass -1.0; masses must be >= 0"),
        (dict(ixx="-0.1"), r"<link name='l1'> <inertial>.*not positive \(semi\)definite"),
        (dict(ixx="0.3"), r"<link name='l1'> <inertial>.*triangle inequality"),
        (
            dict(extra=BRANCH),
            r"body 'l1' carries 2 moving chains \(bodies \['l2', 'l3'\]\).*serial",
        ),
    ],
)
def test_bad_urdf_is_refused_naming_file_and_element(tmp_path, change, message):
    path = _urdf(tmp_path, **change)
    with pytest.raises(ValueError, match=message) as error:
        load_robot(path)
    assert str(path) in str(error.value)


def test_fixed_side_branch_merges(tmp_path):
    side = BRANCH.replace('type="prismatic"', 'type="fixed"')
    chain = load_chain(_urdf(tmp_path, extra=side))
    np.testing.assert_allclose(chain.masses, [3.0, 1.0])


MJCF = """<mujoco><worldbody><body name="b1" pos="0 0 0.1">
  <inertial pos="0 0 0" mass="1" diaginertia="0.1 0.1 0.1"/>{joint}
  <body name="b2" pos="0 0 0.2"><inertial pos="0 0 0" mass="1" diaginertia="0.1 0.1 0.1"/>
    <joint name="j2" axis="0 1 0"/></body>
</body></worldbody></mujoco>"""


@pytest.mark.parametrize("reader", ["auto", "mujoco"])
@pytest.mark.parametrize(
    "joint,message",
    [
        ("<freejoint/>", r"<body name='b1'> has a free joint \(a floating base\).*Remove"),
        ('<joint name="j1" type="free"/>', r"<body name='b1'> has a free joint"),
        ('<joint name="j1" type="ball"/>', r"<joint name='j1'> has a ball joint; supported: hinge"),
        (
            '<joint name="j1"/><joint name="k1" axis="1 0 0"/>',
            r"<body name='b1'> has 2 joints.*nested bodies",
        ),
    ],
)
def test_bad_mjcf_is_refused_naming_file_and_element(tmp_path, joint, message, reader):
    path = tmp_path / "arm.xml"
    path.write_text(MJCF.format(joint=joint))
    with pytest.raises(ValueError, match=message) as error:
        load_chain(path, reader=reader)
    assert str(path) in str(error.value)


def test_mujoco_compile_errors_name_the_file(tmp_path):
    path = tmp_path / "arm.xml"  # a triangle-inequality violation MuJoCo itself refuses
    path.write_text(
        MJCF.format(joint='<joint name="j1"/>').replace(
            'diaginertia="0.1 0.1 0.1"', 'diaginertia="0.1 0.1 0.5"', 1
        )
    )
    with pytest.raises(ValueError, match="triangle inequality") as error:
        load_chain(path, reader="stdlib")
    with pytest.raises(ValueError, match="MuJoCo could not compile it") as error:
        load_chain(path, reader="mujoco")
    assert str(path) in str(error.value)


def test_source_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"no_such\.urdf'.*no such file"):
        load_robot(tmp_path / "no_such.urdf")
    with pytest.raises(
        ValueError,
        match=r"unknown shipped robot 'pandas'; shipped: panda, "
        r"iiwa14, ur5e",
    ):
        load_robot("pandas")
    sdf = tmp_path / "arm.sdf"
    sdf.write_text("<sdf version='1.6'><model name='x'/></sdf>")
    with pytest.raises(ValueError, match=r"arm\.sdf'.*neither URDF.*nor MJCF.*<sdf>"):
        load_robot(sdf)
    text = tmp_path / "notes.txt"
    text.write_text("not xml at all")
    with pytest.raises(ValueError, match=r"notes\.txt'.*neither URDF nor MJCF: not XML"):
        load_robot(text)


@pytest.mark.parametrize(
    "kwargs,message",
    [
        (dict(mass=1.0), r"mass=1.0 for body 'link1'.*0 <= r < 1"),
        (dict(mass=-0.1), r"mass=-0.1 for body 'link1'"),
        (dict(mass=[0.1, 0.2]), r"mass must be one ratio or 7"),
        (dict(payload=(2.0, 1.0)), r"payload has lo=2.0 > hi=1.0 kg; swap them"),
        (dict(payload=(-1.0, 1.0)), r"payload=\(-1.0, 1.0\) kg: payload masses must be >= 0"),
        (dict(payload=(0.0, 1.0, 2.0)), r"payload nominal 2.0 kg is outside \[0.0, 1.0\]"),
        (
            dict(payload=(0.0, 1.0), payload_link="hand"),
            r"payload_link='hand' is not a link/body of 'panda'; links: \['link0', 'link1'",
        ),
        (
            dict(payload=(0.0, 1.0), payload_link="link0"),
            r"payload_link='link0' is fixed to the base",
        ),
        (dict(payload_link="link7"), r"payload_link/payload_offset given but payload is None"),
        (
            dict(friction=dict(viscous=(-0.1, 1.0))),
            r"friction\['viscous'\] for joint 'joint1'.*>= 0",
        ),
        (
            dict(friction=dict(coulomb=(2.0, 1.0))),
            r"friction\['coulomb'\] for joint 'joint1' has lo=2.0 > hi=1.0; swap them",
        ),
        (dict(friction=dict(stiction=(0.0, 1.0))), r"friction has unknown keys \['stiction'\]"),
        (
            dict(friction=dict(viscous=np.zeros((6, 2)))),
            r"friction\['viscous'\] must be .*\(7, 2\)",
        ),
    ],
)
def test_bad_box_arguments(kwargs, message):
    with pytest.raises(ValueError, match=message):
        load_robot("panda", **kwargs)


@pytest.mark.slow
@pytest.mark.parametrize("name", SHIPPED)
def test_default_box_keeps_the_friction_error_within_a_quarter_of_the_damping(name):
    """Per joint, half the viscous range plus half the Coulomb range over the smooth sign's
    scale, divided by the joint's inertia, stays below a quarter of kd = 20 /s; heavy
    joints are capped at 0.5 N m, light ones get less. The inertia here is the smallest
    over states drawn apart from the rule's own, so a sampled minimum: 3 % slack."""
    box = default_box(name)  # the shipped table; the rule recomputed from the file:
    np.testing.assert_allclose(
        box["friction"]["coulomb"][:, 1], _friction_bounds(name, 20.0, 0.25), rtol=1e-12
    )
    params = load_robot(name, **box)
    viscous, coulomb = (np.asarray(box["friction"][k]) for k in ("viscous", "coulomb"))
    assert np.all(viscous[:, 0] == 0) and np.all(coulomb[:, 0] == 0)
    lightest = np.asarray(params.lo)
    q = np.random.default_rng(7).uniform(-np.pi, np.pi, (1024, params.n_joints))
    inertia = jax.vmap(lambda q: jax.numpy.diag(params.model.mass_matrix(q, lightest)))(q)
    smallest = np.asarray(inertia).min(axis=0)
    rate = (viscous[:, 1] / 2 + coulomb[:, 1] / 2 / COULOMB_VELOCITY) / smallest
    assert np.all(rate <= FRICTION_DAMPING_SHARE * 20.0 * 1.03)
    assert np.all(rate >= 0.5 * FRICTION_DAMPING_SHARE * 20.0 * (coulomb[:, 1] < 0.5))
    assert np.all(coulomb[:, 1] <= 0.5)
    assert box["mass"] == 0.1 and tuple(box["payload"]) == (0.0, 1.0)
