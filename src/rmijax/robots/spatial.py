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

import jax.numpy as jnp
import numpy as np
from jax.scipy.linalg import cho_factor, cho_solve

from rmijax.robots.model import GRAVITY as _GRAVITY

__all__ = [
    "COULOMB_VELOCITY",
    "GRAVITY",
    "Chain",
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
    """

    mass_matrix: Callable
    bias: Callable
    forward_dynamics: Callable
    terms: Callable
    param_names: tuple[str, ...]
    affine: tuple[int, ...]
    affine_joints: tuple[int, ...]
    reach: tuple[int, ...]


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


def spatial_dynamics(
    chain: Chain, *, payload: Payload | None = None, friction: tuple[str, ...] = ()
) -> SpatialDynamics:
    """Build the dynamics functions of ``chain`` for one parameter layout.

    Args:
        chain: the static chain.
        payload: where the payload point mass sits, or None for no payload parameter.
        friction: which friction coefficients are parameters, a subset of
            ``("viscous", "coulomb")`` in that order.

    Returns:
        A :class:`SpatialDynamics`; its functions close over NumPy constants only.
    """
    n = chain.n_joints
    friction = tuple(k for k in ("viscous", "coulomb") if k in friction)
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
    # reach[b, i]: joint i moves unit inertia b (it is inboard of b's body).
    reach = np.arange(n)[None, :] <= attach[:, None]

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
        """qdd = M^-1 (tau - h) by Cholesky, (n,)."""
        factor = cho_factor(mass_matrix(q, th))
        return cho_solve(factor, tau - bias(q, qd, th))

    def terms(q, qd):
        """Linear decomposition: M0 (n,n), M_b (p,n,n), h0 (n,), h_b (p,n)."""
        q, qd = _common(q, qd)
        dtype = q.dtype
        rotations, origins, motion = kinematics(q)
        velocity, acceleration = velocities(motion, qd)
        inertias = unit_inertias(rotations, origins)
        # M_b = J_b' I_b J_b: J_b holds the axes of the joints inboard of unit b.
        projected = apply_inertia(*inertias, jnp.broadcast_to(motion, (units, n, 6)))
        mass_terms = jnp.einsum("ik,bjk->bij", motion, projected)
        mass_terms = jnp.where(reach[:, :, None] & reach[:, None, :], mass_terms, 0)
        bias_terms = jnp.where(reach, unit_forces(inertias, velocity, acceleration) @ motion.T, 0)
        if friction:
            eye = jnp.eye(n, dtype=dtype)
            rows = [eye * (qd if k == "viscous" else smooth_sign(qd))[None, :] for k in friction]
            bias_terms = jnp.concatenate([bias_terms, *rows])
            mass_terms = jnp.concatenate([mass_terms, jnp.zeros((n * len(friction), n, n), dtype)])
        mass0 = jnp.diag(jnp.asarray(chain.armature, dtype))
        return mass0, mass_terms, jnp.zeros(n, dtype), bias_terms

    def _common(*arrays):
        dtype = jnp.result_type(*arrays)
        if not jnp.issubdtype(dtype, jnp.floating):
            dtype = jnp.result_type(float)
        return tuple(jnp.asarray(x, dtype) for x in arrays)

    for function in (mass_matrix, bias, forward_dynamics, terms):
        function.__qualname__ = f"{chain.name}.{function.__name__}"
        function.__doc__ = (function.__doc__ or "") + f"\n\n    Parameters (p={n_params}): {names}"
    affine_joints = tuple(j for _ in friction for j in range(n))
    last_joint = tuple(int(b) for b in attach) + affine_joints
    return SpatialDynamics(
        mass_matrix, bias, forward_dynamics, terms, tuple(names), affine, affine_joints, last_joint
    )
