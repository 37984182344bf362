"""Load a real arm from a URDF or MJCF file (or a shipped description) as an uncertain robot.

:func:`load_robot` reads the kinematic and inertial tree, merges bodies attached
by fixed joints into their parent, checks that the moving joints form one serial
chain from a fixed base, and returns an
:class:`~rmijax.robots.box.UncertainRobot` whose model is
:func:`rmijax.robots.spatial.spatial_dynamics` of that chain.

Readers:

- URDF: the standard library (``xml.etree.ElementTree``); visuals, collisions
  and meshes are never read.
- MJCF in the explicit subset (no ``<default>``, ``<include>``, ``class``,
  ``childclass``, ``<frame>``, ...; every body with mass has an ``<inertial>``):
  the standard library too. The shipped descriptions are in this subset.
- Any other MJCF: compiled by MuJoCo (optional, ``pip install "rmijax[mjcf]"``)
  after mesh/height-field geoms and their assets are removed, so that missing
  mesh files do not matter.

Gravity is always 9.81 m/s^2 along ``-z`` of the base (``<option gravity>`` is
not read), joint damping, stiffness and friction loss in the files are not read
(friction is an uncertain parameter given here), and MJCF armature is added to
the mass matrix (a URDF has none).
"""

from __future__ import annotations

import dataclasses
import functools
import importlib.resources
import os
import pathlib
import xml.etree.ElementTree as ET

import numpy as np

from rmijax import _checks
from rmijax.robots.box import UncertainRobot, uncertain_robot
from rmijax.robots.model import RobotModel
from rmijax.robots.spatial import Chain, Payload, spatial_dynamics
from rmijax.robots.structure import LinearDynamics

__all__ = [
    "FRICTION_DAMPING_SHARE",
    "REAL_ARM_BOX",
    "SHIPPED",
    "default_box",
    "description_path",
    "load_chain",
    "load_robot",
]

SHIPPED = ("panda", "iiwa14", "ur5e")
"""Names of the descriptions shipped in ``rmijax/robots/descriptions/`` (MJCF, mesh-free)."""

REAL_ARM_BOX = dict(
    mass=0.1,
    payload=(0.0, 1.0),
    friction=dict(viscous=(0.0, 0.5), coulomb=(0.0, 0.5)),
)
"""A generic box for a heavy-jointed arm: link masses +-10 %, a 0-1 kg payload at the last
link, viscous 0-0.5 N m s/rad and Coulomb 0-0.5 N m friction per joint (nominal at
midpoints). Too much friction uncertainty for light wrists (the iiwa14 file has no
armature: its RMI diverges); the real-arm job uses :func:`default_box` instead."""

FRICTION_DAMPING_SHARE = 0.25
"""Share of the servo's damping ``Kd`` that the friction uncertainty may take (see
:func:`default_box`)."""

_BOX_SAMPLES = 4096  # configurations over which each joint's smallest inertia is taken

_SHIPPED_FRICTION = {
    "panda": (0.17, 0.48, 0.14, 0.5, 0.1, 0.11, 0.094),
    "iiwa14": (0.061, 0.5, 0.025, 0.5, 0.0087, 0.014, 0.00081),
    "ur5e": (0.28, 0.5, 0.44, 0.1, 0.093, 0.091),
}
"""``f_j`` of :func:`default_box`'s rule for the shipped files at ``kd = 20``, share 1/4
(N m s/rad and N m, base to tip), so that loading a shipped arm computes nothing; the
tests recompute them from the rule."""


def default_box(source, *, kd=20.0, share=FRICTION_DAMPING_SHARE) -> dict:
    """The default uncertain box of an arm, friction scaled to each joint's inertia.

    Masses +-10 % and a 0-1 kg payload at the last link, as :data:`REAL_ARM_BOX`; per
    joint ``j`` viscous ``(0, f_j)`` N m s/rad and Coulomb ``(0, f_j)`` N m with

        f_j = min(0.5, 2 share kd M_jj,min v_s / (1 + v_s)),

    ``M_jj,min`` the joint's smallest inertia (kg m^2: the diagonal of ``M`` at the
    lightest mass corner, no payload, the least of 4096 configurations drawn in ``[-pi, pi]``)
    and ``v_s`` the smooth sign's scale
    (:data:`~rmijax.robots.spatial.COULOMB_VELOCITY`). Why: the computed-torque servo
    cancels the nominal friction, so the friction error ``(b - b_n) qd + (c - c_n)
    tanh(qd / v_s)`` acts on the joint like a damper of up to ``(db + dc / v_s) / M_jj``
    per second near rest (``db``, ``dc`` the half-widths). This rule keeps it within
    ``share`` (a quarter) of the servo's damping ``kd``: the loop stays damped at every
    corner and explicit Euler resolves it. A wider friction error makes the true
    plant hunt around rest or diverge (the iiwa14's wrist, 0.0009 kg m^2 without
    armature, under :data:`REAL_ARM_BOX`) and leaves the bands of the step-wise corner
    search (Panda, 3 s move, ``tests/test_real_arm_workflow.py``: worst violation 3 % of
    the band width with this box, 5.7 % with a share of a half, 34 % with
    :data:`REAL_ARM_BOX`, at 0.1 rad/s; SPEC section 10 allows under 5 %). The
    0.5 N m cap is within the Panda's identified Coulomb friction, 0.15-0.64 N m per
    joint (Gaz et al., IEEE RA-L 2019), so the heavy joints keep a realistic range.

    For the shipped arms at the defaults the ``f_j`` are tabulated (recomputed by the
    tests), base to tip: Panda 0.17, 0.48, 0.14, 0.5, 0.1, 0.11, 0.094; iiwa14 0.061,
    0.5, 0.025, 0.5, 0.0087, 0.014, 0.00081; UR5e 0.28, 0.5, 0.44, 0.1, 0.093, 0.091.
    Another file or setting is computed (a few seconds, once per process).

    Args:
        source: a shipped name or a URDF/MJCF path, as :func:`load_robot`.
        kd: the servo's velocity gain (1/s), default the job's critically damped 20.
        share: the share of ``kd`` the friction error may take.

    Returns:
        Keyword arguments for :func:`load_robot`: ``mass``, ``payload``, ``friction``
        (``viscous`` and ``coulomb`` each an (n, 2) array of ``(lo, hi)``).
    """
    if isinstance(source, str) and source in _SHIPPED_FRICTION and (kd, share) == (20.0, 0.25):
        bounds = np.array(_SHIPPED_FRICTION[source])
    else:
        bounds = _friction_bounds(str(source), float(kd), float(share))
    pairs = np.stack([np.zeros_like(bounds), bounds], axis=1)
    return dict(
        mass=REAL_ARM_BOX["mass"],
        payload=REAL_ARM_BOX["payload"],
        friction=dict(viscous=pairs.copy(), coulomb=pairs.copy()),
    )


@functools.lru_cache(maxsize=16)
def _friction_bounds(source, kd, share):
    import jax

    from rmijax.robots.spatial import COULOMB_VELOCITY

    robot = load_robot(source, mass=REAL_ARM_BOX["mass"])
    lightest = robot.lo
    configurations = np.random.default_rng(0).uniform(-np.pi, np.pi, (_BOX_SAMPLES, robot.n_joints))
    diagonal = jax.jit(jax.vmap(lambda q: jax.numpy.diag(robot.model.mass_matrix(q, lightest))))
    smallest = np.asarray(diagonal(configurations.astype(lightest.dtype)), np.float64).min(axis=0)
    bound = 2 * share * kd * smallest * COULOMB_VELOCITY / (1 + COULOMB_VELOCITY)
    bound = np.minimum(REAL_ARM_BOX["friction"]["coulomb"][1], bound)
    # two significant digits, rounded down (the rule is an upper limit)
    scale = 10.0 ** (np.floor(np.log10(bound)) - 1)
    return np.round(np.floor(bound / scale) * scale, 12)


@dataclasses.dataclass
class _Joint:
    name: str
    kind: str  # "revolute" or "prismatic"
    axis: np.ndarray  # (3,) unit, in the body frame
    position: np.ndarray  # (3,) point on the axis, body frame (MJCF joint pos)
    armature: float


@dataclasses.dataclass
class _Body:
    name: str
    parent: int  # index into the body list, -1 for the world
    rotation: np.ndarray  # (3, 3) body frame in the parent frame at q = 0
    position: np.ndarray  # (3,)
    joint: _Joint | None
    mass: float = 0.0
    com: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    inertia: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((3, 3)))
    tree: tuple | None = None  # set for moving bodies: joint frame in the parent carrier's frame


@dataclasses.dataclass
class _Description:
    chain: Chain
    frames: dict  # link name -> (chain body index or -1 for the base, rotation, position)


class _NeedsCompiler(Exception):
    """The MJCF uses something the standard-library reader does not read."""


# --------------------------------------------------------------------------
# Rotations
# --------------------------------------------------------------------------


def _axis_angle(axis, angle):
    axis = np.asarray(axis, dtype=float)
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def _rpy(roll, pitch, yaw):
    """URDF fixed-axis roll, pitch, yaw: ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    return (
        _axis_angle([0, 0, 1], yaw) @ _axis_angle([0, 1, 0], pitch) @ _axis_angle([1, 0, 0], roll)
    )


def _quat(wxyz):
    w, x, y, z = np.asarray(wxyz, dtype=float) / np.linalg.norm(wxyz)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


# --------------------------------------------------------------------------
# Checks
# --------------------------------------------------------------------------


def _check_inertial(mass, inertia, label, where):
    """Mass >= 0 and a physically consistent inertia (PSD, triangle inequality)."""
    if not np.isfinite(mass) or mass < 0:
        raise ValueError(f"{label}: {where} has mass {mass!r}; masses must be >= 0 kg")
    if not np.all(np.isfinite(inertia)):
        raise ValueError(f"{label}: {where} has a non-finite inertia tensor")
    moments = np.linalg.eigvalsh(0.5 * (inertia + inertia.T))
    tol = 1e-9 * max(np.abs(moments).max(), 1e-12)
    if moments.min() < -tol:
        raise ValueError(
            f"{label}: {where} has an inertia tensor that is not positive (semi)definite "
            f"(principal moments {moments.tolist()}). Fix the ixx..izz values of this inertial."
        )
    a, b, c = moments
    if a + b < c - tol:
        raise ValueError(
            f"{label}: {where} has principal moments {moments.tolist()} that violate the "
            "triangle inequality I1 + I2 >= I3 (no rigid body has them). Fix the inertia."
        )


# --------------------------------------------------------------------------
# URDF
# --------------------------------------------------------------------------


def _floats(element, attribute, default, label, where, size=3):
    text = element.get(attribute) if element is not None else None
    if text is None:
        return np.array(default, dtype=float)
    try:
        values = np.array([float(v) for v in text.split()])
    except ValueError:
        raise ValueError(
            f"{label}: {where} {attribute}={text!r} is not a list of numbers"
        ) from None
    if values.size != size:
        raise ValueError(f"{label}: {where} {attribute}={text!r} needs {size} numbers")
    return values


def _read_urdf(root, label):
    links = {}
    for link in root.findall("link"):
        name = link.get("name")
        if name in links:
            raise ValueError(f"{label}: two <link name={name!r}> elements; link names must differ")
        links[name] = link
    joints = {}  # child link -> joint element
    children = {name: [] for name in links}
    for joint in root.findall("joint"):
        jname, kind = joint.get("name"), joint.get("type")
        where = f"<joint name={jname!r} type={kind!r}>"
        if kind == "floating":
            raise ValueError(
                f"{label}: {where} makes a floating base; only fixed-base arms are supported. "
                "Remove the floating joint (the arm's root link is then fixed to the world)."
            )
        if kind not in ("revolute", "continuous", "prismatic", "fixed"):
            raise ValueError(
                f"{label}: {where} has an unsupported joint type; supported: revolute, "
                "continuous, prismatic, fixed. Model it as a chain of those joints."
            )
        if joint.find("mimic") is not None:
            raise ValueError(f"{label}: {where} has a <mimic>; mimic joints are not supported")
        parent, child = (joint.find(t).get("link") for t in ("parent", "child"))
        for role, link in (("parent", parent), ("child", child)):
            if link not in links:
                raise ValueError(f"{label}: {where} names {role} link {link!r}, not a <link>")
        if child in joints:
            raise ValueError(f"{label}: link {child!r} is the child of two joints (a loop)")
        joints[child] = joint
        children[parent].append(child)
    roots = [name for name in links if name not in joints]
    if len(roots) != 1:
        raise ValueError(f"{label}: the links must form one tree; root links found: {roots}")
    bodies, index, order = [], {}, [roots[0]]
    for name in order:  # breadth first: parents before children
        order.extend(children[name])
        joint = joints.get(name)
        rotation, position, moving = np.eye(3), np.zeros(3), None
        if joint is not None:
            where = f"<joint name={joint.get('name')!r}>"
            origin = joint.find("origin")
            position = _floats(origin, "xyz", [0, 0, 0], label, where + " <origin>")
            rotation = _rpy(*_floats(origin, "rpy", [0, 0, 0], label, where + " <origin>"))
            if joint.get("type") != "fixed":
                axis = _floats(joint.find("axis"), "xyz", [1, 0, 0], label, where + " <axis>")
                if np.linalg.norm(axis) == 0:
                    raise ValueError(f"{label}: {where} <axis xyz='0 0 0'>: give a nonzero axis")
                kind = "prismatic" if joint.get("type") == "prismatic" else "revolute"
                moving = _Joint(
                    joint.get("name"), kind, axis / np.linalg.norm(axis), np.zeros(3), 0.0
                )
        body = _Body(
            name,
            index[joint.find("parent").get("link")] if joint is not None else -1,
            rotation,
            position,
            moving,
        )
        inertial = links[name].find("inertial")
        if inertial is not None:
            where = f"<link name={name!r}> <inertial>"
            origin = inertial.find("origin")
            mass_element = inertial.find("mass")
            body.mass = float(mass_element.get("value")) if mass_element is not None else 0.0
            body.com = _floats(origin, "xyz", [0, 0, 0], label, where + " <origin>")
            frame = _rpy(*_floats(origin, "rpy", [0, 0, 0], label, where + " <origin>"))
            element = inertial.find("inertia")
            moments = {
                key: float(element.get(key, 0.0)) if element is not None else 0.0
                for key in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
            }
            tensor = np.array(
                [
                    [moments["ixx"], moments["ixy"], moments["ixz"]],
                    [moments["ixy"], moments["iyy"], moments["iyz"]],
                    [moments["ixz"], moments["iyz"], moments["izz"]],
                ]
            )
            _check_inertial(body.mass, tensor, label, where)
            body.inertia = frame @ tensor @ frame.T
        index[name] = len(bodies)
        bodies.append(body)
    return root.get("name", "robot"), bodies


# --------------------------------------------------------------------------
# MJCF, explicit subset (standard library)
# --------------------------------------------------------------------------

_MJCF_TOP = {
    "compiler",
    "option",
    "size",
    "visual",
    "statistic",
    "asset",
    "worldbody",
    "actuator",
    "sensor",
    "contact",
    "keyframe",
    "tendon",
    "equality",
    "custom",
}
_MJCF_COMPILER = {
    "angle",
    "eulerseq",
    "autolimits",
    "meshdir",
    "texturedir",
    "assetdir",
    "inertiafromgeom",
    "discardvisual",
    "strippath",
}
_MJCF_BODY = {"body", "inertial", "joint", "freejoint", "geom", "site", "camera", "light"}
_ORIENTATIONS = ("quat", "axisangle", "euler", "xyaxes", "zaxis")


class _MjcfAngles:
    def __init__(self, compiler):
        angle = compiler.get("angle", "degree") if compiler is not None else "degree"
        self.scale = np.pi / 180 if angle == "degree" else 1.0
        self.sequence = compiler.get("eulerseq", "xyz") if compiler is not None else "xyz"

    def rotation(self, element, label, where):
        given = [k for k in _ORIENTATIONS if element.get(k) is not None]
        if len(given) > 1:
            raise ValueError(f"{label}: {where} gives {given}; give one orientation")
        if not given:
            return np.eye(3)
        kind = given[0]
        values = _floats(
            element,
            kind,
            None,
            label,
            where,
            size={"quat": 4, "axisangle": 4, "euler": 3, "xyaxes": 6, "zaxis": 3}[kind],
        )
        if kind == "quat":
            return _quat(values)
        if kind == "axisangle":
            return _axis_angle(values[:3], values[3] * self.scale)
        if kind == "euler":
            rotation = np.eye(3)
            for letter, angle in zip(self.sequence, values, strict=True):
                turn = _axis_angle(np.eye(3)["xyz".index(letter.lower())], angle * self.scale)
                rotation = rotation @ turn if letter.islower() else turn @ rotation
            return rotation
        if kind == "xyaxes":
            x = values[:3] / np.linalg.norm(values[:3])
            y = values[3:] - (values[3:] @ x) * x
            y = y / np.linalg.norm(y)
            return np.stack([x, y, np.cross(x, y)], axis=1)
        z = values / np.linalg.norm(values)  # zaxis: the shortest turn taking +z to it
        cross = np.cross([0.0, 0.0, 1.0], z)
        if np.linalg.norm(cross) < 1e-12:
            return np.eye(3) if z[2] > 0 else _axis_angle([1, 0, 0], np.pi)
        return _axis_angle(cross, np.arctan2(np.linalg.norm(cross), z[2]))


def _read_mjcf_simple(root, label):
    """Bodies of an MJCF in the explicit subset; raises _NeedsCompiler otherwise."""
    for element in root.iter():
        for attribute in ("class", "childclass"):
            if element.get(attribute) is not None:
                raise _NeedsCompiler(f"<{element.tag} {attribute}=...>")
    for child in root:
        if child.tag not in _MJCF_TOP:
            raise _NeedsCompiler(f"<{child.tag}>")
    compiler = root.find("compiler")
    if compiler is not None:
        unknown = set(compiler.attrib) - _MJCF_COMPILER
        if unknown or compiler.get("inertiafromgeom", "auto") == "true":
            raise _NeedsCompiler(f"<compiler {' '.join(sorted(unknown)) or 'inertiafromgeom'}>")
    geoms_weigh = compiler is None or compiler.get("inertiafromgeom", "auto") != "false"
    angles = _MjcfAngles(compiler)
    worldbody = root.find("worldbody")
    if worldbody is None:
        raise ValueError(f"{label}: no <worldbody>; the MJCF has no bodies")
    bodies = []

    def visit(element, parent):
        for child in element:
            if child.tag not in _MJCF_BODY:
                raise _NeedsCompiler(f"<{child.tag}>")
            if child.tag != "body":
                continue
            index = len(bodies)
            name = child.get("name") or f"body #{index + 1}"
            where = f"<body name={name!r}>"
            if child.get("mocap") == "true":
                raise _NeedsCompiler("mocap body")
            if child.find("freejoint") is not None:
                raise _floating(label, where)
            joints = child.findall("joint")
            if len(joints) > 1:
                raise _multiple_joints(label, where, len(joints))
            joint = None
            for element_joint in joints:
                joint = _mjcf_joint(element_joint, name, index, label, where)
            body = _Body(
                name,
                parent,
                angles.rotation(child, label, where),
                _floats(child, "pos", [0, 0, 0], label, where),
                joint,
            )
            inertial = child.find("inertial")
            if inertial is None and geoms_weigh and child.find("geom") is not None:
                raise _NeedsCompiler(f"{where} without <inertial> (inertia from geoms)")
            if inertial is not None:
                iwhere = where + " <inertial>"
                body.mass = float(inertial.get("mass"))
                body.com = _floats(inertial, "pos", None, label, iwhere)
                if inertial.get("fullinertia") is not None:
                    i = _floats(inertial, "fullinertia", None, label, iwhere, size=6)
                    tensor = np.array([[i[0], i[3], i[4]], [i[3], i[1], i[5]], [i[4], i[5], i[2]]])
                    frame = np.eye(3)
                else:
                    tensor = np.diag(_floats(inertial, "diaginertia", None, label, iwhere))
                    frame = angles.rotation(inertial, label, iwhere)
                _check_inertial(body.mass, tensor, label, iwhere)
                body.inertia = frame @ tensor @ frame.T
            bodies.append(body)
            visit(child, index)

    visit(worldbody, -1)
    return root.get("model", "robot"), bodies


def _floating(label, where):
    return ValueError(
        f"{label}: {where} has a free joint (a floating base); only fixed-base arms are "
        "supported. Remove the <freejoint>/free joint to weld the base to the world."
    )


def _multiple_joints(label, where, count):
    return ValueError(
        f"{label}: {where} has {count} joints; one joint per body is supported. Split it "
        "into nested bodies, one joint each."
    )


def _unsupported(label, where, kind):
    return ValueError(
        f"{label}: {where} has a {kind} joint; supported: hinge (revolute) and slide "
        "(prismatic). Model it as a chain of hinges."
    )


def _mjcf_joint(element, body_name, index, label, where):
    kind = element.get("type", "hinge")
    name = element.get("name") or f"{body_name} joint"
    jwhere = f"{where} <joint name={name!r}>"
    if kind == "free":
        raise _floating(label, where)
    if kind not in ("hinge", "slide"):
        raise _unsupported(label, jwhere, kind)
    if float(element.get("ref", 0.0)) != 0.0:
        raise ValueError(f"{label}: {jwhere} has ref != 0, which is not supported; remove it")
    axis = _floats(element, "axis", [0, 0, 1], label, jwhere)
    if np.linalg.norm(axis) == 0:
        raise ValueError(f"{label}: {jwhere} axis='0 0 0': give a nonzero axis")
    return _Joint(
        name,
        "revolute" if kind == "hinge" else "prismatic",
        axis / np.linalg.norm(axis),
        _floats(element, "pos", [0, 0, 0], label, jwhere),
        float(element.get("armature", 0.0)),
    )


# --------------------------------------------------------------------------
# MJCF, any (MuJoCo compiler)
# --------------------------------------------------------------------------


def _read_mjcf_compiled(path, label, reason):
    try:
        import mujoco
    except ImportError as error:
        raise ImportError(
            f"{label} uses MJCF features the built-in reader does not read ({reason}); "
            'compiling it needs MuJoCo: pip install "rmijax[mjcf]"'
        ) from error
    try:
        spec = mujoco.MjSpec.from_file(str(path))
    except Exception as error:
        raise ValueError(f"{label}: MuJoCo could not parse it: {error}") from None
    shapes = (mujoco.mjtGeom.mjGEOM_MESH, mujoco.mjtGeom.mjGEOM_HFIELD, mujoco.mjtGeom.mjGEOM_SDF)
    from_geoms = spec.compiler.inertiafromgeom
    for geom in list(spec.geoms):
        if geom.type in shapes or geom.meshname:
            body = geom.parent
            if from_geoms == mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_TRUE or (
                from_geoms == mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_AUTO
                and not body.explicitinertial
            ):
                raise ValueError(
                    f"{label}: <body name={body.name!r}> takes its inertia from a mesh geom; "
                    "meshes are not read. Give the body an explicit <inertial>."
                )
            spec.delete(geom)
    for group in (spec.meshes, spec.hfields, spec.skins, spec.textures):
        for element in list(group):
            spec.delete(element)
    for material in spec.materials:
        material.textures = [""] * len(material.textures)
    try:
        model = spec.compile()
    except Exception as error:
        raise ValueError(f"{label}: MuJoCo could not compile it: {error}") from None
    name_of = mujoco.mj_id2name
    kinds = {
        mujoco.mjtJoint.mjJNT_HINGE: ("revolute", "hinge"),
        mujoco.mjtJoint.mjJNT_SLIDE: ("prismatic", "slide"),
        mujoco.mjtJoint.mjJNT_BALL: (None, "ball"),
        mujoco.mjtJoint.mjJNT_FREE: (None, "free"),
    }
    bodies = []
    for b in range(1, model.nbody):
        name = name_of(model, mujoco.mjtObj.mjOBJ_BODY, b) or f"body #{b}"
        where = f"<body name={name!r}>"
        joint = None
        if model.body_jntnum[b] > 1:
            raise _multiple_joints(label, where, int(model.body_jntnum[b]))
        if model.body_jntnum[b] == 1:
            j = int(model.body_jntadr[b])
            kind, mj_kind = kinds[mujoco.mjtJoint(model.jnt_type[j])]
            jname = name_of(model, mujoco.mjtObj.mjOBJ_JOINT, j) or f"{name} joint"
            if mj_kind == "free":
                raise _floating(label, where)
            if kind is None:
                raise _unsupported(label, f"{where} <joint name={jname!r}>", mj_kind)
            if model.qpos0[model.jnt_qposadr[j]] != 0:
                raise ValueError(
                    f"{label}: {where} <joint name={jname!r}> has ref != 0, "
                    "which is not supported; remove it"
                )
            joint = _Joint(
                jname,
                kind,
                np.array(model.jnt_axis[j]),
                np.array(model.jnt_pos[j]),
                float(model.dof_armature[model.jnt_dofadr[j]]),
            )
        frame = _quat(model.body_iquat[b])
        body = _Body(
            name,
            int(model.body_parentid[b]) - 1,
            _quat(model.body_quat[b]),
            np.array(model.body_pos[b]),
            joint,
            float(model.body_mass[b]),
            np.array(model.body_ipos[b]),
            frame @ np.diag(model.body_inertia[b]) @ frame.T,
        )
        bodies.append(body)
    return spec.modelname or "robot", bodies


# --------------------------------------------------------------------------
# Tree -> serial chain
# --------------------------------------------------------------------------


def _compose(outer, inner):
    return outer[0] @ inner[0], outer[1] + outer[0] @ inner[1]


def _merge(parts):
    """Combine (mass, com, inertia about com) triples given in one frame."""
    mass = sum(m for m, _, _ in parts)
    com = sum(m * c for m, c, _ in parts) / mass if mass > 0 else np.zeros(3)
    inertia = np.zeros((3, 3))
    for m, c, i in parts:
        d = c - com
        inertia = inertia + i + m * ((d @ d) * np.eye(3) - np.outer(d, d))
    return mass, com, inertia


def _build_chain(name, bodies, label):
    """Merge fixed bodies into their carrier and order the moving ones base to tip."""
    identity = (np.eye(3), np.zeros(3))
    shift = [b.joint.position if b.joint is not None else np.zeros(3) for b in bodies]
    carrier, pose = [], []  # carrier body (-1 base) and pose of the body's joint frame in it
    moving_children = {}
    for k, body in enumerate(bodies):
        # The chain's body frame is the joint frame: the body frame moved to the joint's point.
        parent_shift = shift[body.parent] if body.parent >= 0 else np.zeros(3)
        local = (body.rotation, body.position - parent_shift + body.rotation @ shift[k])
        outer = pose[body.parent] if body.parent >= 0 else identity
        parent_carrier = carrier[body.parent] if body.parent >= 0 else -1
        if body.joint is not None:
            moving_children.setdefault(parent_carrier, []).append(k)
            carrier.append(k)
            pose.append(identity)
            body.tree = _compose(outer, local)
        else:
            carrier.append(parent_carrier)
            pose.append(_compose(outer, local))
    order, current = [], -1
    while moving_children.get(current):
        if len(moving_children[current]) > 1:
            where = "the base" if current < 0 else f"body {bodies[current].name!r}"
            names = [bodies[k].name for k in moving_children[current]]
            raise ValueError(
                f"{label}: {where} carries {len(names)} moving chains (bodies {names}); only "
                "serial chains are supported. Remove the extra branch or make its joints fixed."
            )
        current = moving_children[current][0]
        order.append(current)
    if not order:
        raise ValueError(
            f"{label}: no moving joint; the arm needs at least one hinge/revolute "
            "or slide/prismatic joint"
        )
    position = {k: i for i, k in enumerate(order)}
    parts = {k: [] for k in order}
    frames = {}
    for k, body in enumerate(bodies):
        rotation, origin = pose[k]
        if carrier[k] >= 0:
            parts[carrier[k]].append(
                (
                    body.mass,
                    origin + rotation @ (body.com - shift[k]),
                    rotation @ body.inertia @ rotation.T,
                )
            )
        frames[body.name] = (
            position.get(carrier[k], -1),
            *_compose(pose[k], (np.eye(3), -shift[k])),
        )
    merged = [_merge(parts[k]) for k in order]
    for k, (mass, _, _) in zip(order, merged, strict=True):
        if not mass > 0:
            raise ValueError(
                f"{label}: moving <body/link name={bodies[k].name!r}> has mass {mass!r} "
                "(with the bodies fixed to it); every moving body needs a positive mass. "
                "Give it an <inertial> with mass > 0."
            )
    chain = Chain(
        name=name,
        joint_names=tuple(bodies[k].joint.name for k in order),
        body_names=tuple(bodies[k].name for k in order),
        joint_types=tuple(bodies[k].joint.kind for k in order),
        rotations=np.stack([bodies[k].tree[0] for k in order]),
        translations=np.stack([bodies[k].tree[1] for k in order]),
        axes=np.stack([bodies[k].joint.axis for k in order]),
        armature=np.array([bodies[k].joint.armature for k in order]),
        masses=np.array([m for m, _, _ in merged]),
        coms=np.stack([c for _, c, _ in merged]),
        inertias=np.stack([i for _, _, i in merged]),
    )
    return _Description(chain, frames)


# --------------------------------------------------------------------------
# Entry points
# --------------------------------------------------------------------------


def description_path(source) -> pathlib.Path:
    """The file behind ``source``: a shipped name's MJCF, or the given path (checked to exist)."""
    if isinstance(source, str) and source in SHIPPED:
        resource = importlib.resources.files("rmijax.robots") / "descriptions" / f"{source}.xml"
        with importlib.resources.as_file(resource) as path:
            return pathlib.Path(path)
    if not isinstance(source, (str, os.PathLike)):
        raise TypeError(f"source must be a path or a shipped name {SHIPPED}, got {type(source)}")
    path = pathlib.Path(source)
    if not path.exists():
        if isinstance(source, str) and not path.suffix and os.sep not in source:
            raise ValueError(
                f"unknown shipped robot {source!r}; shipped: {', '.join(SHIPPED)} "
                "(or give the path of a URDF or MJCF file)"
            )
        raise FileNotFoundError(
            f"source {str(path)!r}: no such file; give the path of a URDF "
            f"or MJCF file, or a shipped name ({', '.join(SHIPPED)})"
        )
    return path


def _describe(source, reader="auto"):
    path = description_path(source)
    label = f"{str(path)!r}"
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as error:
        raise ValueError(f"{label} is neither URDF nor MJCF: not XML ({error})") from None
    if root.tag == "robot":
        name, bodies = _read_urdf(root, label)
    elif root.tag == "mujoco":
        try:
            if reader == "mujoco":
                raise _NeedsCompiler("reader='mujoco' asked")
            name, bodies = _read_mjcf_simple(root, label)
        except _NeedsCompiler as reason:
            if reader == "stdlib":
                raise ValueError(
                    f"{label}: {reason} is outside the explicit MJCF subset that "
                    "the built-in reader reads; use reader='auto'"
                ) from None
            name, bodies = _read_mjcf_compiled(path, label, reason)
    else:
        raise ValueError(
            f"{label} is neither URDF (<robot> root) nor MJCF (<mujoco> root); "
            f"its root element is <{root.tag}>"
        )
    return _build_chain(name, bodies, label)


def load_chain(source, *, reader: str = "auto") -> Chain:
    """Read the serial chain of a URDF/MJCF file or shipped description.

    Args:
        source: path (str or pathlib) or a name in :data:`SHIPPED`.
        reader: for MJCF, ``"auto"`` (built-in reader for the explicit subset,
            MuJoCo otherwise), ``"stdlib"`` or ``"mujoco"``.

    Returns:
        The :class:`~rmijax.robots.spatial.Chain` (fixed bodies merged).
    """
    return _describe(source, reader).chain


def _pairs(value, n, argument, joints):
    """(lo, hi) for all joints or per joint (n, 2) -> lo (n,), hi (n,)."""
    array = np.asarray(value, dtype=float)
    if array.shape == (2,):
        array = np.tile(array, (n, 1))
    if array.shape != (n, 2):
        raise ValueError(
            f"{argument} must be (lo, hi) or one pair per joint, shape ({n}, 2); "
            f"got shape {np.shape(value)}"
        )
    for j in range(n):
        lo, hi = array[j]
        if not (np.isfinite(lo) and np.isfinite(hi)) or lo < 0 or hi < 0:
            raise ValueError(
                f"{argument} for joint {joints[j]!r} is ({lo}, {hi}); friction "
                "coefficients must be finite and >= 0"
            )
        if lo > hi:
            raise ValueError(f"{argument} for joint {joints[j]!r} has lo={lo} > hi={hi}; swap them")
    return array[:, 0], array[:, 1]


def load_robot(
    source,
    *,
    mass=0.0,
    payload=None,
    payload_link=None,
    payload_offset=None,
    friction=None,
    dtype=None,
) -> UncertainRobot:
    """Load an arm as an uncertain robot with a box of mass scales, payload and friction.

    Parameters ``th`` are, in order: one mass scale per moving body (base to
    tip; nominal 1), the payload mass in kg (only when ``payload`` is given), then
    the viscous coefficients of all joints and the Coulomb ones (only those named
    in ``friction``). See :mod:`rmijax.robots.spatial`.

    Args:
        source: path (str or pathlib) to a URDF or MJCF file, or a shipped name
            (``"panda"``, ``"iiwa14"``, ``"ur5e"``).
        mass: relative mass uncertainty ``r``, a float or one per moving body:
            each scale lies in ``[1 - r, 1 + r]``; ``0 <= r < 1``. ``r = 0`` keeps the
            scale as a certain parameter (``lo == hi``).
        payload: ``(lo, hi)`` or ``(lo, hi, nominal)`` in kg, ``0 <= lo <= hi``;
            nominal defaults to the midpoint. None: no payload parameter.
        payload_link: name of the link/body carrying the payload (default the
            last moving one); a link fixed to a moving body is fine.
        payload_offset: (3,) payload position in that link's frame, m (default 0).
        friction: ``dict(viscous=(lo, hi), coulomb=(lo, hi))``, each one pair for
            all joints or an (n, 2) array, in N m s/rad and N m (N s/m, N for
            prismatic joints); nominal the midpoint. Joint ``j`` loses
            ``b_j qd_j + c_j tanh(qd_j / 0.1)``: the smooth sign's scale
            :data:`~rmijax.robots.spatial.COULOMB_VELOCITY` is 0.1 rad/s, the sharpest
            scale identified on the Panda (Gaz et al. 2019; it was 0.01 rad/s before,
            sharper than explicit Euler at ``dt = 0.01`` resolves). An omitted key adds
            no parameters (that friction is absent, not zero-with-uncertainty).
            :func:`default_box` gives each arm a range its servo tolerates.
        dtype: float dtype of the box; default float64 when x64 is enabled, else float32
            (as every builder).

    Returns:
        An :class:`UncertainRobot` whose model has a ``LinearDynamics`` structure
        (friction parameters affine).

    Raises:
        FileNotFoundError: no such file.
        ValueError: unknown shipped name, not URDF/MJCF, floating base, branching
            chain, unsupported joint, non-positive moving mass, inconsistent
            inertia, or a bad box argument; the message names the file/element or
            the argument and the fix.
        ImportError: an MJCF outside the explicit subset and MuJoCo not installed.
    """
    description = _describe(source)
    chain = description.chain
    n = chain.n_joints
    ratios = (
        np.broadcast_to(np.asarray(mass, dtype=float), (n,))
        if np.ndim(mass) == 0
        else (np.asarray(mass, dtype=float))
    )
    if ratios.shape != (n,):
        raise ValueError(
            f"mass must be one ratio or {n} (one per moving body "
            f"{list(chain.body_names)}); got shape {np.shape(mass)}"
        )
    for body, r in zip(chain.body_names, ratios, strict=True):
        if not (0 <= r < 1):
            raise ValueError(
                f"mass={float(r)!r} for body {body!r}: the relative mass "
                "uncertainty r must satisfy 0 <= r < 1 (scales lie in [1 - r, 1 + r])"
            )
    lo, hi, nominal = [1 - ratios], [1 + ratios], [np.ones(n)]

    payload_spec = None
    if payload is None:
        if payload_link is not None or payload_offset is not None:
            raise ValueError(
                "payload_link/payload_offset given but payload is None; give payload=(lo, hi) in kg"
            )
    else:
        values = [float(v) for v in payload]
        if len(values) not in (2, 3):
            raise ValueError(f"payload must be (lo, hi) or (lo, hi, nominal) in kg; got {payload}")
        p_lo, p_hi = values[:2]
        p_nom = values[2] if len(values) == 3 else 0.5 * (p_lo + p_hi)
        if p_lo < 0 or p_hi < 0:
            raise ValueError(f"payload=({p_lo}, {p_hi}) kg: payload masses must be >= 0")
        if p_lo > p_hi:
            raise ValueError(f"payload has lo={p_lo} > hi={p_hi} kg; swap them")
        if not p_lo <= p_nom <= p_hi:
            raise ValueError(
                f"payload nominal {p_nom} kg is outside [{p_lo}, {p_hi}]; "
                "give a nominal inside the interval"
            )
        link = chain.body_names[-1] if payload_link is None else payload_link
        if link not in description.frames:
            raise ValueError(
                f"payload_link={link!r} is not a link/body of {source!r}; links: "
                f"{sorted(description.frames)}"
            )
        body, rotation, origin = description.frames[link]
        if body < 0:
            raise ValueError(
                f"payload_link={link!r} is fixed to the base, so a payload there "
                "loads no joint; choose a link of the moving chain"
            )
        offset = np.zeros(3) if payload_offset is None else np.asarray(payload_offset, float)
        if offset.shape != (3,):
            raise ValueError(f"payload_offset must be (x, y, z) in m; got {payload_offset}")
        payload_spec = Payload(body, origin + rotation @ offset)
        lo.append([p_lo])
        hi.append([p_hi])
        nominal.append([p_nom])

    kinds = ()
    if friction is not None:
        unknown = set(friction) - {"viscous", "coulomb"}
        if unknown:
            raise ValueError(
                f"friction has unknown keys {sorted(unknown)}; use 'viscous' and/or 'coulomb'"
            )
        kinds = tuple(k for k in ("viscous", "coulomb") if k in friction)
        for kind in kinds:
            f_lo, f_hi = _pairs(friction[kind], n, f"friction[{kind!r}]", chain.joint_names)
            lo.append(f_lo)
            hi.append(f_hi)
            nominal.append(0.5 * (f_lo + f_hi))

    dynamics = spatial_dynamics(chain, payload=payload_spec, friction=kinds)
    model = RobotModel(
        n_joints=n,
        n_params=len(dynamics.param_names),
        mass_matrix=dynamics.mass_matrix,
        bias=dynamics.bias,
        forward_dynamics=dynamics.forward_dynamics,
        name=chain.name,
        param_names=dynamics.param_names,
        structure=LinearDynamics(
            affine=dynamics.affine,
            terms=dynamics.terms,
            affine_joints=dynamics.affine_joints,
            reach=dynamics.reach,
            terms_tracks_last=dynamics.terms_tracks_last,
            layout=dynamics.layout,
        ),
    )
    return uncertain_robot(
        model,
        np.concatenate(nominal),
        np.concatenate(lo),
        np.concatenate(hi),
        dtype=dtype or _checks.default_float(),
    )
