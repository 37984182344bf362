"""Rigid-body dynamics of fixed-base serial chains (revolute and prismatic joints) in pure JAX.

A :class:`Chain` is a static description (NumPy arrays) of ``n`` joints, each
moving one rigid body. :func:`spatial_dynamics` turns it into pure functions of
``(q, qd, th)``: the mass matrix by the composite-rigid-body algorithm, the bias
forces ``h = C(q, qd) qd + G(q)`` (= inverse dynamics at ``qdd = 0``) by
recursive Newton-Euler, and the linear decomposition ``terms`` of both in the
parameters. Both recursions run in base-frame Plücker coordinates (Featherstone,
*Rigid Body Dynamics Algorithms*, 2008, sections 5.3 and 6.2): once the joint
axes are in the base frame, the outward and inward passes are cumulative sums
over the chain, so only the forward kinematics is a Python loop (unrolled).

Parameter vector ``th`` (this order is the contract):

1. ``s_1..s_n``: one scale per moving body, base to tip, multiplying that
   body's mass, first moment and rotational inertia (its centre of mass stays).
2. ``m_payload`` (kg), only with a payload: a point mass at a fixed point of one body.
3. Friction, only when asked: viscous ``b_1..b_n`` (N m s/rad), then Coulomb
   ``c_1..c_n`` (N m); joint ``j`` loses ``b_j qd_j + c_j tanh(qd_j / v_s)``
   with ``v_s =`` :data:`COULOMB_VELOCITY`.

Gravity is :data:`GRAVITY` along ``-z`` of the base frame. Joint armature adds
to the diagonal of ``M``. Units: rad, m, kg, s (N, m/s, kg for prismatic joints).
Every function follows the dtype of its inputs.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from rmijax._linalg import materialise, spd_solve
from rmijax.robots import _unrolled as _u
from rmijax.robots.model import GRAVITY as _GRAVITY

__all__ = [
    "COULOMB_VELOCITY",
    "GRAVITY",
    "Chain",
    "ChainLayout",
    "Payload",
    "SpatialDynamics",
    "smooth_sign",
    "spatial_dynamics",
]

GRAVITY = _GRAVITY
"""Gravitational acceleration in m/s^2, along ``-z`` of the base frame."""

COULOMB_VELOCITY = 0.1
"""Velocity scale ``v_s`` (rad/s or m/s) of the smooth Coulomb sign ``tanh(qd / v_s)``:
0.76 of full friction at ``v_s``, 0.995 at ``3 v_s``.

A physical value, taken from measurement: the Panda's identified friction (Gaz et al.,
"Dynamic identification of the Franka Emika Panda robot with retrieval of feasible
parameters using penalty-based optimization", IEEE RA-L 4(4), 2019) is a sigmoid
``phi_1 / (1 + exp(-phi_2 qd))``, i.e. ``(phi_1 / 2) (1 + tanh(qd / (2 / phi_2)))``, with
``2 / phi_2`` between 0.117 rad/s (joint 6) and 0.39 rad/s (joint 1); 0.1 rad/s is the
sharpest of them, rounded down. A much sharper sign (0.01 rad/s was used before) makes
the joint near rest stiffer than explicit Euler at ``dt = 0.01`` resolves and, with the
nominal friction compensated, a locally undamped loop: the true plant then hunts around
rest and leaves the bands of the step-wise corner search (Panda, 3 s move, 0-0.5 N m
friction: worst violation 18 % of the band width at 0.01 rad/s; with
:func:`~rmijax.robots.loaders.default_box` and 0.1 rad/s, 3 %)."""

JOINT_TYPES = ("revolute", "prismatic")


@dataclasses.dataclass(frozen=True, eq=False)
class Chain:
    """Static description of a fixed-base serial chain of ``n`` joints.

    Body ``j`` is moved by joint ``j``; its frame is the joint frame, placed in
    the frame of body ``j-1`` (the base frame for ``j = 0``) by ``rotations[j]``
    and ``translations[j]`` at ``q_j = 0``. A revolute joint turns about
    ``axes[j]`` through the frame origin, a prismatic one slides along it.
    Compared by identity (it holds arrays); treat it as immutable.

    Attributes:
        name: robot name, for reports.
        joint_names, body_names: (n,) labels.
        joint_types: (n,) each ``"revolute"`` or ``"prismatic"``.
        rotations: (n, 3, 3) joint frame axes in the parent body frame.
        translations: (n, 3) joint frame origin in the parent body frame, m.
        axes: (n, 3) unit joint axes in the joint frame.
        armature: (n,) rotor inertia added to ``M``'s diagonal, kg m^2 (kg).
        masses: (n,) body masses, kg.
        coms: (n, 3) centres of mass in the body frame, m.
        inertias: (n, 3, 3) rotational inertia about the centre of mass in
            body-frame axes, kg m^2.
    """

    name: str
    joint_names: tuple[str, ...]
    body_names: tuple[str, ...]
    joint_types: tuple[str, ...]
    rotations: np.ndarray
    translations: np.ndarray
    axes: np.ndarray
    armature: np.ndarray
    masses: np.ndarray
    coms: np.ndarray
    inertias: np.ndarray

    def __post_init__(self):
        n = len(self.joint_types)
        shapes = dict(
            rotations=(n, 3, 3),
            translations=(n, 3),
            axes=(n, 3),
            armature=(n,),
            masses=(n,),
            coms=(n, 3),
            inertias=(n, 3, 3),
        )
        for field, shape in shapes.items():
            value = np.array(getattr(self, field), dtype=np.float64)
            if value.shape != shape:
                raise ValueError(f"Chain.{field} has shape {value.shape}, expected {shape}")
            value.flags.writeable = False
            object.__setattr__(self, field, value)
        for field in ("joint_names", "body_names"):
            if len(getattr(self, field)) != n:
                raise ValueError(f"Chain.{field} needs {n} entries, one per joint")
        bad = [t for t in self.joint_types if t not in JOINT_TYPES]
        if n == 0 or bad:
            raise ValueError(f"Chain needs >= 1 joint of types {JOINT_TYPES}; got {bad or n}")

    @property
    def n_joints(self) -> int:
        return len(self.joint_types)


@dataclasses.dataclass(frozen=True, eq=False)
class Payload:
    """A point mass (its size is a parameter) at ``point`` (3,), m, in the frame of ``body``."""

    body: int
    point: np.ndarray


@dataclasses.dataclass(frozen=True, eq=False)
class ChainLayout:
    """The chain and parameter layout one :func:`spatial_dynamics` was built from.

    For code that evaluates the same dynamics on its own number types (the certified
    method's interval and affine jets, :mod:`rmijax.methods.chain_jets`). Compared and
    hashed by identity; :func:`spatial_dynamics` builds one per content, so two loads of
    one robot with the same payload link and friction kinds share it.

    Attributes:
        chain: the static chain.
        payload: where the payload sits, or None.
        friction: the friction kinds that are parameters, in order.
    """

    chain: Chain
    payload: Payload | None
    friction: tuple[str, ...]


class SpatialDynamics(NamedTuple):
    """The functions of one chain and parameter layout (all single, unbatched arguments).

    Attributes:
        mass_matrix: ``(q (n,), th (p,)) -> M (n, n)``.
        bias: ``(q (n,), qd (n,), th (p,)) -> h (n,)``.
        forward_dynamics: ``(q, qd, tau (n,), th) -> qdd (n,)`` by Cholesky.
        terms: ``(q, qd) -> (M0 (n, n), M_b (p, n, n), h0 (n,), h_b (p, n))`` with
            ``M = M0 + th @ M_b`` and ``h = h0 + th @ h_b``.
        param_names: (p,) labels of ``th``.
        affine: indices of the parameters that enter ``h`` only (friction).
        affine_joints: for each of them the joint whose bias it alone enters.
        reach: per parameter the last joint its terms touch (``M_b``, ``h_b`` vanish
            beyond it): a body's index, the payload's body, a friction's joint.
        terms_tracks_last: ``(q (n, T), qd (n, T)) -> (M0 (n, n, T), M_b (p, n, n, T),
            h0 (n, T), h_b (p, n, T))``, ``terms`` for ``T`` states, tracks last.
        layout: the :class:`ChainLayout` these functions were built from.
    """

    mass_matrix: Callable
    bias: Callable
    forward_dynamics: Callable
    terms: Callable
    param_names: tuple[str, ...]
    affine: tuple[int, ...]
    affine_joints: tuple[int, ...]
    reach: tuple[int, ...]
    terms_tracks_last: Callable
    layout: ChainLayout


def smooth_sign(qd):
    """The smooth Coulomb sign ``tanh(qd / COULOMB_VELOCITY)``, same shape as ``qd``."""
    return jnp.tanh(qd / COULOMB_VELOCITY)


def _skew(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _mv(matrix, vector):
    """Stacked matrix-vector products: (..., 3, 3) x (..., 3) -> (..., 3)."""
    return jnp.einsum("...ij,...j->...i", matrix, vector)


def _cross_point(x):
    """``-[x]^2 = (x.x) 1 - x x'`` for stacked points (k, 3) -> (k, 3, 3)."""
    eye = jnp.eye(3, dtype=x.dtype)[None]
    return jnp.sum(x * x, -1)[:, None, None] * eye - x[:, :, None] * x[:, None, :]


class _Frames(NamedTuple):
    """A chain's constants as nested tuples of floats (:mod:`rmijax.robots._unrolled`)."""

    rotation: tuple  # per joint C_j, the joint frame in the parent frame
    rotation_k: tuple  # C_j K_j, K_j the cross-product matrix of the joint axis
    rotation_k2: tuple  # C_j K_j^2 (Rodrigues: Rot(q) = 1 + sin q K + (1 - cos q) K^2)
    translation: tuple
    tree_axis: tuple  # C_j a_j, the axis in the parent frame
    com: tuple
    inertia: tuple


def _unrolled_frames(chain):
    snap = 1e-14  # the residue of exact zeros in rotation matrices (cos(pi/2) = 6e-17)
    skews = [_skew(a) for a in chain.axes]
    rot = chain.rotations
    return _Frames(
        tuple(_u.constant(r, snap=snap) for r in rot),
        tuple(_u.constant(r @ k, snap=snap) for r, k in zip(rot, skews, strict=True)),
        tuple(_u.constant(r @ k @ k, snap=snap) for r, k in zip(rot, skews, strict=True)),
        tuple(_u.constant(t) for t in chain.translations),
        tuple(_u.constant(a, snap=snap) for a in np.einsum("nij,nj->ni", rot, chain.axes)),
        tuple(_u.constant(c) for c in chain.coms),
        tuple(_u.constant(i) for i in chain.inertias),
    )


def _materialise_tree(tree, tracks):
    """``tree`` with every array leaf computed in one kernel (Python floats stay)."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    where = [i for i, x in enumerate(leaves) if not _u.is_constant(x)]
    kept = materialise([jnp.broadcast_to(leaves[i], (tracks,)) for i in where])
    for i, value in zip(where, kept, strict=True):
        leaves[i] = value
    return jax.tree_util.tree_unflatten(treedef, leaves)


def _unrolled_state(frames, revolute, attach, unit_masses, payload_point, q, qd):
    """Kinematics, velocities and unit inertias in the base frame, one scalar per entry.

    The computation of ``kinematics``, ``velocities`` and ``unit_inertias`` in
    :func:`spatial_dynamics`, entry by entry on arrays of ``T`` tracks (``q``,
    ``qd``: (n, T)), materialised in three kernels (sines and cosines; poses and
    motion axes; the rest). Returns per joint the motion axis
    ``S_j`` and the body's velocity and bias acceleration (6-tuples, angular
    first), and per unit inertia its rotational inertia about the base origin
    (a dict of the lower triangle) and first moment (3-tuple).
    """
    n = len(revolute)
    # sines and cosines first, in a kernel of their own: XLA does not copy an expensive
    # op into several consumers, so otherwise every entry they feed is a kernel apart
    turns = [j for j in range(n) if revolute[j]]
    trig = materialise([jnp.sin(q[j]) for j in turns] + [jnp.cos(q[j]) for j in turns])
    sines = dict(zip(turns, trig[: len(turns)], strict=True))
    cosines = dict(zip(turns, trig[len(turns) :], strict=True))
    rotation = _u.constant(np.eye(3))
    origin = (0.0, 0.0, 0.0)
    rotations, origins, motion = [], [], []
    for j in range(n):
        origin = tuple(map(_u.add, origin, _u.matvec(rotation, frames.translation[j])))
        axis = _u.matvec(rotation, frames.tree_axis[j])
        if revolute[j]:
            sin, versin = sines[j], 1.0 - cosines[j]
            fixed = _u.matmul(rotation, frames.rotation[j])
            first = _u.matmul(rotation, frames.rotation_k[j])
            second = _u.matmul(rotation, frames.rotation_k2[j])
            rotation = tuple(
                tuple(
                    _u.add(_u.add(f, _u.mul(sin, a)), _u.mul(versin, b))
                    for f, a, b in zip(*rows, strict=True)
                )
                for rows in zip(fixed, first, second, strict=True)
            )
            motion.append(axis + _u.cross(origin, axis))
        else:
            rotation = _u.matmul(rotation, frames.rotation[j])
            origin = tuple(_u.add(o, _u.mul(q[j], a)) for o, a in zip(origin, axis, strict=True))
            motion.append((0.0, 0.0, 0.0) + axis)
        rotations.append(rotation)
        origins.append(origin)
    # materialised in stages: one kernel of everything compiles twice as slowly
    rotations, origins, motion = _materialise_tree((rotations, origins, motion), q.shape[-1])
    w, vo = (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)
    aw, av = (0.0, 0.0, 0.0), (0.0, 0.0, GRAVITY)
    velocity, acceleration = [], []
    for j in range(n):
        mw = tuple(_u.mul(qd[j], x) for x in motion[j][:3])
        mv = tuple(_u.mul(qd[j], x) for x in motion[j][3:])
        w, vo = tuple(map(_u.add, w, mw)), tuple(map(_u.add, vo, mv))
        aw = tuple(map(_u.add, aw, _u.cross(w, mw)))
        av = tuple(map(_u.add, av, map(_u.add, _u.cross(w, mv), _u.cross(vo, mw))))
        velocity.append(w + vo)
        acceleration.append(aw + av)
    lower = [(i, k) for i in range(3) for k in range(i + 1)]
    inertia, moment = [], []
    for b, body in enumerate(attach):
        turn, place = rotations[body], origins[body]
        if b < n:
            com = tuple(map(_u.add, place, _u.matvec(turn, frames.com[b])))
            turned = _u.matmul(turn, frames.inertia[b])
            about = {(i, k): _u.dot(turned[i], turn[k]) for i, k in lower}
        else:
            com = tuple(map(_u.add, place, _u.matvec(turn, payload_point)))
            about = dict.fromkeys(lower, 0.0)
        squared = _u.dot(com, com)
        m = unit_masses[b]
        for i, k in lower:  # parallel axis: + m ((c.c) 1 - c c')
            shift = _u.sub(squared if i == k else 0.0, _u.mul(com[i], com[k]))
            about[i, k] = _u.add(about[i, k], _u.mul(m, shift))
        inertia.append(about)
        moment.append(tuple(_u.mul(m, c) for c in com))
    return _materialise_tree((motion, velocity, acceleration, inertia, moment), q.shape[-1])


_BUILT: dict = {}
_BUILT_SIZE = 32


def _content_key(chain: Chain, payload: Payload | None, friction: tuple[str, ...]):
    """What a chain, payload and friction layout hold, as a hashable value (arrays by bytes)."""
    arrays = tuple(
        getattr(chain, f).tobytes()
        for f in ("rotations", "translations", "axes", "armature", "masses", "coms", "inertias")
    )
    names = (chain.name, chain.joint_names, chain.body_names, chain.joint_types)
    where = None
    if payload is not None:
        where = (int(payload.body), np.asarray(payload.point, np.float64).tobytes())
    return names, arrays, where, friction


def spatial_dynamics(
    chain: Chain, *, payload: Payload | None = None, friction: tuple[str, ...] = ()
) -> SpatialDynamics:
    """Build the dynamics functions of ``chain`` for one parameter layout.

    Built once per content: a chain, payload and friction layout equal in every name and
    number to one built before (among the last 32) returns that same object, so two loads
    of one robot give equal models and jitted code that takes the model as a static
    argument does not compile again.

    Args:
        chain: the static chain.
        payload: where the payload point mass sits, or None for no payload parameter.
        friction: which friction coefficients are parameters, a subset of
            ``("viscous", "coulomb")`` in that order.

    Returns:
        A :class:`SpatialDynamics`; its functions close over NumPy constants only.
    """
    friction = tuple(k for k in ("viscous", "coulomb") if k in friction)
    key = _content_key(chain, payload, friction)
    built = _BUILT.get(key)
    if built is None:
        built = _build(chain, payload, friction)
        if len(_BUILT) >= _BUILT_SIZE:
            _BUILT.pop(next(iter(_BUILT)))  # the oldest
        _BUILT[key] = built
    return built


def _build(chain: Chain, payload: Payload | None, friction: tuple[str, ...]) -> SpatialDynamics:
    """:func:`spatial_dynamics` without the memo."""
    n = chain.n_joints
    revolute = [t == "revolute" for t in chain.joint_types]
    # Rodrigues' formula per revolute joint: Rot(q) = 1 + sin q K + (1 - cos q) K^2.
    skews = [_skew(a) for a in chain.axes]
    skews2 = [k @ k for k in skews]
    tree_axes = np.einsum("nij,nj->ni", chain.rotations, chain.axes)  # in the parent frame
    units = n + (payload is not None)  # unit inertias: bodies, then the payload
    attach = np.arange(n) if payload is None else np.append(np.arange(n), payload.body)
    names = [f"mass_scale[{b}]" for b in chain.body_names]
    names += ["payload_mass"] if payload is not None else []
    affine = tuple(range(len(names), len(names) + n * len(friction)))
    names += [f"{kind}[{j}]" for kind in friction for j in chain.joint_names]
    n_params = len(names)
    upper = np.triu(np.ones((n, n), dtype=bool))

    def kinematics(q):
        """World poses and joint motion axes; q (n,) -> R (n,3,3), origins (n,3), S (n,6)."""
        dtype = q.dtype
        rotation, origin = None, None
        rotations, origins, axes_ang, axes_lin = [], [], [], []
        for j in range(n):
            tree_rot = jnp.asarray(chain.rotations[j], dtype)
            tree_pos = jnp.asarray(chain.translations[j], dtype)
            axis = jnp.asarray(tree_axes[j], dtype)
            if rotation is not None:
                origin = origin + rotation @ tree_pos
                axis = rotation @ axis
                tree_rot = rotation @ tree_rot
            else:
                origin = tree_pos
            if revolute[j]:
                turn = (
                    jnp.eye(3, dtype=dtype)
                    + jnp.sin(q[j]) * jnp.asarray(skews[j], dtype)
                    + (1 - jnp.cos(q[j])) * jnp.asarray(skews2[j], dtype)
                )
                rotation = tree_rot @ turn
                axes_ang.append(axis)
                axes_lin.append(jnp.cross(origin, axis))
            else:
                rotation = tree_rot
                origin = origin + q[j] * axis
                axes_ang.append(jnp.zeros(3, dtype))
                axes_lin.append(axis)
            rotations.append(rotation)
            origins.append(origin)
        motion = jnp.concatenate([jnp.stack(axes_ang), jnp.stack(axes_lin)], -1)
        return jnp.stack(rotations), jnp.stack(origins), motion

    def unit_inertias(rotations, origins):
        """Base-frame spatial inertias of the bodies (and the unit payload) at the base origin.

        Returns ``(mass (u,), first moment (u, 3), rotational inertia about the origin
        (u, 3, 3))`` with ``u = n + has_payload``.
        """
        dtype = origins.dtype
        com = origins + _mv(rotations, jnp.asarray(chain.coms, dtype))
        inertia = jnp.einsum(
            "nij,njk,nlk->nil", rotations, jnp.asarray(chain.inertias, dtype), rotations
        )
        mass = jnp.asarray(chain.masses, dtype)
        if payload is not None:
            point = origins[payload.body] + rotations[payload.body] @ jnp.asarray(
                payload.point, dtype
            )
            com = jnp.concatenate([com, point[None]])
            inertia = jnp.concatenate([inertia, jnp.zeros((1, 3, 3), dtype)])
            mass = jnp.concatenate([mass, jnp.ones(1, dtype)])
        inertia = inertia + mass[:, None, None] * _cross_point(com)
        return mass, mass[:, None] * com, inertia

    def apply_inertia(mass, moment, inertia, motion):
        """Spatial inertia times motion: (u,) (u,3) (u,3,3) x (u,..,6) -> force (u,..,6)."""
        ang, lin = motion[..., :3], motion[..., 3:]
        extra = (None,) * (motion.ndim - 2)
        moment = moment[(slice(None), *extra)]
        return jnp.concatenate(
            [
                jnp.einsum("uij,u...j->u...i", inertia, ang) + jnp.cross(moment, lin),
                mass[(slice(None), *extra, None)] * lin - jnp.cross(moment, ang),
            ],
            -1,
        )

    def velocities(motion, qd):
        """Body velocities v (n,6) and bias accelerations a (n,6), gravity included."""
        dtype = motion.dtype
        joint_velocity = motion * qd[:, None]
        velocity = jnp.cumsum(joint_velocity, 0)
        # v_j x (S_j qd_j), the motion cross product (w x m_w, w x m_v + v_o x m_w).
        w, vo = velocity[:, :3], velocity[:, 3:]
        mw, mv = joint_velocity[:, :3], joint_velocity[:, 3:]
        bias = jnp.concatenate([jnp.cross(w, mw), jnp.cross(w, mv) + jnp.cross(vo, mw)], -1)
        gravity = jnp.asarray([0.0, 0.0, 0.0, 0.0, 0.0, GRAVITY], dtype)
        return velocity, gravity[None] + jnp.cumsum(bias, 0)

    def unit_forces(units_inertia, velocity, acceleration):
        """f_b = I_b a_b + v_b x* I_b v_b for every unit inertia b: (u, 6)."""
        v, a = velocity[attach], acceleration[attach]
        momentum = apply_inertia(*units_inertia, v)
        force = apply_inertia(*units_inertia, a)
        w, vo = v[:, :3], v[:, 3:]
        n_, f_ = momentum[:, :3], momentum[:, 3:]
        return force + jnp.concatenate([jnp.cross(w, n_) + jnp.cross(vo, f_), jnp.cross(w, f_)], -1)

    def per_body(values, th):
        """Sum the weighted unit quantities (u, ...) onto their bodies (n, ...)."""
        weights = th[:units].reshape((units,) + (1,) * (values.ndim - 1))
        weighted = weights * values
        if payload is None:
            return weighted
        return weighted[:n].at[payload.body].add(weighted[n])

    def friction_torque(qd, th):
        dtype = qd.dtype
        torque = jnp.zeros(n, dtype)
        for k, kind in enumerate(friction):
            coefficient = th[units + k * n : units + (k + 1) * n]
            torque = torque + coefficient * (qd if kind == "viscous" else smooth_sign(qd))
        return torque

    def mass_matrix(q, th):
        """Mass matrix by CRBA: M_ij = S_i . (I^c_j S_j) for i <= j, (n, n)."""
        q, th = _common(q, th)
        rotations, origins, motion = kinematics(q)
        mass, moment, inertia = (per_body(x, th) for x in unit_inertias(rotations, origins))
        composite = [jnp.flip(jnp.cumsum(jnp.flip(x, 0), 0), 0) for x in (mass, moment, inertia)]
        force = apply_inertia(*composite, motion)  # (n, 6)
        full = motion @ force.T
        matrix = jnp.where(upper, full, full.T)
        return matrix + jnp.diag(jnp.asarray(chain.armature, q.dtype))

    def bias(q, qd, th):
        """Bias forces by RNEA with qdd = 0 (Coriolis, centrifugal, gravity, friction), (n,)."""
        q, qd, th = _common(q, qd, th)
        rotations, origins, motion = kinematics(q)
        velocity, acceleration = velocities(motion, qd)
        forces = per_body(
            unit_forces(unit_inertias(rotations, origins), velocity, acceleration), th
        )
        total = jnp.flip(jnp.cumsum(jnp.flip(forces, 0), 0), 0)
        return jnp.sum(motion * total, -1) + friction_torque(qd, th)

    def forward_dynamics(q, qd, tau, th):
        """qdd = M^-1 (tau - h), (n,) in rad/s^2 (m/s^2 for prismatic joints).

        Solved by :func:`rmijax._linalg.spd_solve` (``LDL'`` written out element by
        element up to 8 joints, a column loop above), not by LAPACK: under ``vmap`` of
        reverse-mode derivatives in float64, jaxlib 0.10.2's batched ``trsm`` (which
        ``cho_solve`` calls) hung on 20 000 items on the 2-core CPU (README, "Known
        problem").
        """
        return spd_solve(mass_matrix(q, th), tau - bias(q, qd, th))

    frames = _unrolled_frames(chain)
    unit_masses = tuple(float(m) for m in chain.masses) + ((1.0,) if payload is not None else ())
    payload_point = _u.constant(payload.point) if payload is not None else None

    def terms_tracks_last(q, qd):
        """Linear decomposition for ``T`` states at once, tracks on the last axis.

        Args:
            q, qd: (n, T) joint positions and velocities.

        Returns:
            ``M0 (n, n, T)``, ``M_b (p, n, n, T)``, ``h0 (n, T)``, ``h_b (p, n, T)``.

        The same recursions as :func:`mass_matrix` and :func:`bias`, written out on
        scalars (one array of ``T`` values each) so that XLA's CPU backend runs them
        as a few fused loops vectorised over the tracks; ``M_b`` is filled only where
        unit ``b`` reaches (``reach``), each entry once (``M_b`` is symmetric).
        """
        q, qd = _common(q, qd)
        dtype, tracks = q.dtype, q.shape[-1]
        motion, velocity, acceleration, inertia, moment = _unrolled_state(
            frames, revolute, attach, unit_masses, payload_point, q, qd
        )
        zero = jnp.zeros((tracks,), dtype)

        def array(x):
            return jnp.full((tracks,), x, dtype) if _u.is_constant(x) else x

        def apply(b, vector):  # spatial inertia of unit b times a motion vector
            ang, lin = vector[:3], vector[3:]
            rows = [[inertia[b][max(i, k), min(i, k)] for k in range(3)] for i in range(3)]
            turn = _u.cross(moment[b], lin)
            torque = tuple(_u.add(_u.dot(row, ang), t) for row, t in zip(rows, turn, strict=True))
            push = _u.cross(moment[b], ang)
            force = tuple(
                _u.sub(_u.mul(unit_masses[b], x), y) for x, y in zip(lin, push, strict=True)
            )
            return torque + force

        entries, places = [], []
        for b in range(units):
            last = int(attach[b])
            for j in range(last + 1):
                projected = apply(b, motion[j])
                for i in range(j + 1):
                    entries.append(_u.dot(motion[i], projected))
                    places.append(("mass", b, i, j))
            v, a = velocity[last], acceleration[last]
            wrench = _u.plus_cross_force(apply(b, a), v, apply(b, v))
            for i in range(last + 1):
                entries.append(_u.dot(motion[i], wrench))
                places.append(("bias", b, i, None))
        kept = iter(materialise([array(x) for x in entries]))
        mass_terms = [[[zero] * n for _ in range(n)] for _ in range(n_params)]
        bias_terms = [[zero] * n for _ in range(n_params)]
        for kind, b, i, j in places:
            value = next(kept)
            if kind == "mass":
                mass_terms[b][i][j] = mass_terms[b][j][i] = value
            else:
                bias_terms[b][i] = value
        for k, kind in enumerate(friction):
            for j in range(n):
                bias_terms[units + k * n + j][j] = (
                    qd[j] if kind == "viscous" else smooth_sign(qd[j])
                )
        mass0 = jnp.broadcast_to(
            jnp.diag(jnp.asarray(chain.armature, dtype))[..., None], (n, n, tracks)
        )
        # one flat stack each (nested stacks become one small kernel per row on CPU)
        flat_mass = [x for m in mass_terms for row in m for x in row]
        flat_bias = [x for row in bias_terms for x in row]
        return (
            mass0,
            jnp.stack(flat_mass).reshape(n_params, n, n, tracks),
            jnp.zeros((n, tracks), dtype),
            jnp.stack(flat_bias).reshape(n_params, n, tracks),
        )

    def terms(q, qd):
        """Linear decomposition: M0 (n,n), M_b (p,n,n), h0 (n,), h_b (p,n)."""
        q, qd = _common(q, qd)
        return tuple(x[..., 0] for x in terms_tracks_last(q[:, None], qd[:, None]))

    def _common(*arrays):
        dtype = jnp.result_type(*arrays)
        if not jnp.issubdtype(dtype, jnp.floating):
            dtype = jnp.result_type(float)
        return tuple(jnp.asarray(x, dtype) for x in arrays)

    for function in (mass_matrix, bias, forward_dynamics, terms, terms_tracks_last):
        function.__qualname__ = f"{chain.name}.{function.__name__}"
        function.__doc__ = (function.__doc__ or "") + f"\n\n    Parameters (p={n_params}): {names}"
    affine_joints = tuple(j for _ in friction for j in range(n))
    last_joint = tuple(int(b) for b in attach) + affine_joints
    return SpatialDynamics(
        mass_matrix,
        bias,
        forward_dynamics,
        terms,
        tuple(names),
        affine,
        affine_joints,
        last_joint,
        terms_tracks_last,
        ChainLayout(chain, payload, friction),
    )
