"""The closed loop's perturbation ``gv`` of a spatial serial chain, on jets of any backend.

The counterpart of :func:`rmijax.methods.certified.planar_perturbation_jets` for the
arms of :func:`rmijax.load_robot` (Panda, iiwa14, UR5e, any URDF/MJCF chain): the same
quantity

    gv = qdd - v = M(q; th)^-1 f,
    f = (M(q; th_n) - M(q; th)) v + h(q, qd; th_n) - h(q, qd; th) + tau(y) - tau(x),

with ``v = u - Kd qd - Kp q`` the servo's acceleration on the true state and ``tau(y)``
the nominal computed torque on the readings ``y = x + eta``. Every operation is one of
the tape's (``+ - * /``, ``sin``, ``cos``, ``tanh``, squares), so the same code runs on
interval jets, affine jets (:mod:`rmijax._affine`), the checker's ``mpmath`` intervals
and a :class:`rmijax._intervals.Tape` recording.

Since ``M`` and ``h`` are linear in ``th`` (:mod:`rmijax.robots.spatial`), the first
part of ``f`` is ``-sum_b (th_b - th_n,b) tau_b``: the inverse dynamics of unit inertia
``b`` alone at ``(q, qd, qdd = v)`` (gravity included) for the mass scales and the
payload, ``qd_j`` or ``tanh(qd_j / v_s)`` for friction. It vanishes at the nominal, so
enclosures carry the size of the parameter error, not of ``v``.

The recursions run in *body* frames (Featherstone 2008, sections 5.3 and 6.2: Newton-Euler
outward for velocities and accelerations, inward for forces; composite inertias for ``M``),
written on scalars with the chain's constants folded (:mod:`rmijax.robots._unrolled`:
products with exact 0 and 1 cost nothing). The model's own base-frame form
(:func:`rmijax.robots.spatial.spatial_dynamics`) is the same dynamics, but there every
inertia is taken about the base origin, so a wrist's small inertia is the difference of
terms the size of ``m |c|^2`` and interval enclosures over the box lose it; in body frames
each body's inertia about its own joint is a constant. ``M`` is factored ``U D U'`` from
the tip (``U`` unit upper): ``D_j`` is the articulated inertia of joint ``j`` about its
axis, positive for every ``th`` in the box (an enclosure over a wide box can still hold 0:
then the band is infinite and :func:`rmijax.certified_bounds` says it diverged). With
a preconditioner ``P`` (the certifier's default on chains) the system is solved as
``(P M) x = P rhs`` instead (:func:`solve_preconditioned`): with ``P`` the float inverse
of ``M`` at the enclosure's centre the pivots stay near 1 over wide boxes.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from rmijax.robots import _unrolled as _u
from rmijax.robots.spatial import COULOMB_VELOCITY, GRAVITY, ChainLayout, _skew

__all__ = ["chain_perturbation_jets", "solve_preconditioned"]


class _Local(NamedTuple):
    """A chain's constants in body frames, as nested tuples of floats."""

    fixed: tuple  # C_j: joint frame j in the frame of body j-1 at q_j = 0
    first: tuple  # C_j K_j (Rodrigues: Rot(q) = 1 + sin q K + (1 - cos q) K^2)
    second: tuple  # C_j K_j^2
    offset: tuple  # t_j: joint frame j's origin in body j-1, m
    axis: tuple  # a_j in frame j
    units: tuple  # per unit: (body, mass, first moment m c (3), inertia about the origin)


def _local(layout):
    """The body-frame constants: rounded once to float64 from the chain's data (products
    of its rotations and cross-product matrices, inertias moved to the joint origin), the
    residue ``|x| <= 1e-14`` of exact zeros snapped to 0, as
    :func:`rmijax.robots.spatial._unrolled_frames` does."""
    chain, payload = layout.chain, layout.payload
    snap = 1e-14
    skews = [_skew(a) for a in chain.axes]
    rot = chain.rotations
    units = []
    for b in range(chain.n_joints):
        m, c = float(chain.masses[b]), chain.coms[b]
        about = chain.inertias[b] + m * (np.dot(c, c) * np.eye(3) - np.outer(c, c))
        units.append((b, m, _u.constant(m * c), _u.constant(about)))
    if payload is not None:
        c = np.asarray(payload.point, np.float64)
        about = np.dot(c, c) * np.eye(3) - np.outer(c, c)
        units.append((payload.body, 1.0, _u.constant(c), _u.constant(about)))
    return _Local(
        tuple(_u.constant(r, snap=snap) for r in rot),
        tuple(_u.constant(r @ k, snap=snap) for r, k in zip(rot, skews, strict=True)),
        tuple(_u.constant(r @ k @ k, snap=snap) for r, k in zip(rot, skews, strict=True)),
        tuple(_u.constant(t) for t in chain.translations),
        tuple(_u.constant(a, snap=snap) for a in chain.axes),
        tuple(units),
    )


def _transpose(matrix):
    return tuple(zip(*matrix, strict=True))


def _joints(local, revolute, q):
    """Per joint ``(R_j, p_j)``: body ``j``'s axes and origin in body ``j-1``'s frame."""
    out = []
    for j, turns in enumerate(revolute):
        offset = local.offset[j]
        if turns:
            sin, versin = q[j].sin(), 1.0 - q[j].cos()
            rotation = tuple(
                tuple(
                    _u.add(_u.add(f, _u.mul(sin, a)), _u.mul(versin, b))
                    for f, a, b in zip(*rows, strict=True)
                )
                for rows in zip(local.fixed[j], local.first[j], local.second[j], strict=True)
            )
        else:
            rotation = local.fixed[j]
            slide = _u.matvec(rotation, local.axis[j])
            offset = tuple(_u.add(t, _u.mul(q[j], a)) for t, a in zip(offset, slide, strict=True))
        out.append((rotation, offset))
    return out


def _motion_in(joint, vector):
    """A motion vector of the parent's frame in the child's: ``(R' w, R' (v + w x p))``."""
    rotation, offset = joint
    back = _transpose(rotation)
    ang, lin = vector[:3], vector[3:]
    moved = tuple(map(_u.add, lin, _u.cross(ang, offset)))
    return _u.matvec(back, ang) + _u.matvec(back, moved)


def _force_out(joint, force):
    """A force of the child's frame in the parent's: ``(R n + p x R f, R f)``."""
    rotation, offset = joint
    turned_n, turned_f = _u.matvec(rotation, force[:3]), _u.matvec(rotation, force[3:])
    return tuple(map(_u.add, turned_n, _u.cross(offset, turned_f))) + turned_f


def _axis(local, revolute, j):
    """``S_j`` in frame ``j`` (constants)."""
    zero = (0.0, 0.0, 0.0)
    return local.axis[j] + zero if revolute[j] else zero + local.axis[j]


def _motion(local, revolute, joints, qd, qdd):
    """Body velocities and accelerations in their own frames (gravity as the base's
    acceleration), 6-tuples, angular first."""
    velocity = (0.0,) * 6
    acceleration = (0.0,) * 5 + (GRAVITY,)
    velocities, accelerations = [], []
    for j, joint in enumerate(joints):
        axis = _axis(local, revolute, j)
        rate = tuple(_u.mul(qd[j], x) for x in axis)
        velocity = tuple(map(_u.add, _motion_in(joint, velocity), rate))
        w, v = velocity[:3], velocity[3:]
        bias = _u.cross(w, rate[:3]) + tuple(
            map(_u.add, _u.cross(w, rate[3:]), _u.cross(v, rate[:3]))
        )
        push = tuple(_u.mul(qdd[j], x) for x in axis)
        acceleration = tuple(
            _u.add(_u.add(a, b), c)
            for a, b, c in zip(_motion_in(joint, acceleration), bias, push, strict=True)
        )
        velocities.append(velocity)
        accelerations.append(acceleration)
    return velocities, accelerations


def _apply(inertia, vector):
    """A spatial inertia ``(mass, first moment h, rotational inertia about the origin)``
    times a motion vector: ``(I w + h x v, m v - h x w)``."""
    mass, moment, about = inertia
    ang, lin = vector[:3], vector[3:]
    torque = tuple(map(_u.add, _u.matvec(about, ang), _u.cross(moment, lin)))
    force = tuple(
        _u.sub(_u.mul(mass, x), y) for x, y in zip(lin, _u.cross(moment, ang), strict=True)
    )
    return torque + force


def _unit_force(inertia, velocity, acceleration):
    """``I a + v x* (I v)``."""
    return _u.plus_cross_force(_apply(inertia, acceleration), velocity, _apply(inertia, velocity))


def _inverse_dynamics(local, revolute, joints, qd, qdd, weights):
    """``sum_b weight_b tau_b(q, qd, qdd)`` over the unit inertias (no armature, no
    friction), by recursive Newton-Euler in body frames: a list of ``n``."""
    n = len(joints)
    velocities, accelerations = _motion(local, revolute, joints, qd, qdd)
    total = [(0.0,) * 6 for _ in range(n)]
    for (body, mass, moment, about), weight in zip(local.units, weights, strict=True):
        force = _unit_force((mass, moment, about), velocities[body], accelerations[body])
        total[body] = tuple(
            _u.add(t, _u.mul(weight, f)) for t, f in zip(total[body], force, strict=True)
        )
    out, carried = [None] * n, (0.0,) * 6
    for j in range(n - 1, -1, -1):
        if j < n - 1:
            carried = _force_out(joints[j + 1], carried)
        carried = tuple(map(_u.add, carried, total[j]))
        out[j] = _u.dot(_axis(local, revolute, j), carried)
    return out


def _inertia_out(joint, inertia):
    """A spatial inertia of the child's frame in the parent's: with ``R``, ``p``, ``h_r =
    R h``: ``(m, h_r + m p, R I R' + m (p.p 1 - p p') + 2 (p.h_r) 1 - p h_r' - h_r p')``."""
    rotation, offset = joint
    mass, moment, about = inertia
    turned = _u.matmul(_u.matmul(rotation, about), _transpose(rotation))
    h = _u.matvec(rotation, moment)
    pp, ph = _u.dot(offset, offset), _u.dot(offset, h)
    rows = []
    for i in range(3):
        row = []
        for k in range(3):
            shift = _u.sub(
                _u.mul(mass, pp) if i == k else 0.0, _u.mul(mass, _u.mul(offset[i], offset[k]))
            )
            cross = _u.sub(
                _u.mul(2.0, ph) if i == k else 0.0,
                _u.add(_u.mul(offset[i], h[k]), _u.mul(h[i], offset[k])),
            )
            row.append(_u.add(_u.add(turned[i][k], shift), cross))
        rows.append(tuple(row))
    moved = tuple(_u.add(a, _u.mul(mass, b)) for a, b in zip(h, offset, strict=True))
    return mass, moved, tuple(rows)


def _mass_matrix(local, revolute, joints, weights, armature):
    """``M = diag(armature) + sum_b weight_b M_b`` by composite rigid bodies in body frames:
    ``M_jj = S_j . I^c_j S_j``, and ``M_ij = S_i . F`` with ``F = I^c_j S_j`` carried to
    frame ``i``. An ``n x n`` list of lists (the same entry object above and below)."""
    n = len(joints)
    zero3 = ((0.0,) * 3,) * 3
    own = [[0.0, (0.0,) * 3, zero3] for _ in range(n)]
    for (body, mass, moment, about), weight in zip(local.units, weights, strict=True):
        total = own[body]
        total[0] = _u.add(total[0], _u.mul(weight, mass))
        total[1] = tuple(
            _u.add(a, _u.mul(weight, b)) for a, b in zip(total[1], moment, strict=True)
        )
        total[2] = tuple(
            tuple(_u.add(a, _u.mul(weight, b)) for a, b in zip(ra, rb, strict=True))
            for ra, rb in zip(total[2], about, strict=True)
        )
    matrix = [[None] * n for _ in range(n)]
    composite = None
    for j in range(n - 1, -1, -1):
        if composite is None:
            composite = tuple(own[j])
        else:
            mass, moment, about = _inertia_out(joints[j + 1], composite)
            composite = (
                _u.add(mass, own[j][0]),
                tuple(map(_u.add, moment, own[j][1])),
                tuple(tuple(map(_u.add, ra, rb)) for ra, rb in zip(about, own[j][2], strict=True)),
            )
        force = _apply(composite, _axis(local, revolute, j))
        for i in range(j, -1, -1):
            if i < j:
                force = _force_out(joints[i + 1], force)
            entry = _u.dot(_axis(local, revolute, i), force)
            if i == j and armature[j] != 0:
                entry = _u.add(entry, float(armature[j]))
            matrix[i][j] = matrix[j][i] = entry
    return matrix


def _solve_tip_first(matrix, rhs):
    """Solve ``M x = rhs`` by ``M = U D U'`` (``U`` unit upper), eliminating from the tip.

    ``D_j = M_jj - sum_(k > j) U_jk^2 D_k`` is the articulated inertia of joint ``j``
    (the chain beyond it free to move), positive for a physical chain.
    """
    n = len(rhs)
    upper = [[None] * n for _ in range(n)]  # upper[i][k] = U_ik, i < k
    pivot, inverse = [None] * n, [None] * n
    for k in range(n - 1, -1, -1):
        total = matrix[k][k]
        for t in range(k + 1, n):
            total = _u.sub(total, _u.mul(_u.mul(upper[k][t], upper[k][t]), pivot[t]))
        pivot[k] = total
        inverse[k] = 1.0 / total
        for i in range(k):
            entry = matrix[i][k]
            for t in range(k + 1, n):
                entry = _u.sub(entry, _u.mul(_u.mul(upper[i][t], upper[k][t]), pivot[t]))
            upper[i][k] = _u.mul(entry, inverse[k])
    z = [None] * n  # U z = rhs, from the tip
    for i in range(n - 1, -1, -1):
        total = rhs[i]
        for k in range(i + 1, n):
            total = _u.sub(total, _u.mul(upper[i][k], z[k]))
        z[i] = total
    x = [None] * n  # U' x = z / D, from the base
    for i in range(n):
        total = _u.mul(z[i], inverse[i])
        for k in range(i):
            total = _u.sub(total, _u.mul(upper[k][i], x[k]))
        x[i] = total
    return x


def solve_preconditioned(matrix, rhs, precond):
    """Solve ``M x = rhs`` as ``(P M) x = P rhs`` by Gaussian elimination without pivoting.

    ``P`` (``n x n`` constants of the backend) is any matrix: the solution is the same
    for every invertible ``P``, so it needs no proof; with ``P`` close to ``M^-1`` at the
    centre of an enclosure, ``P M`` is close to the identity over it, its pivots stay
    near 1 and the enclosure keeps the dependence on the parameters that the
    elimination of ``M`` itself loses over a wide box (where a pivot's enclosure can
    hold 0). A singular ``P`` gives a pivot that holds 0: an infinite enclosure, never
    a wrong one.
    """
    n = len(rhs)
    columns = [[matrix[k][j] for k in range(n)] for j in range(n)]
    a = [[_u.dot(precond[i], columns[j]) for j in range(n)] for i in range(n)]
    b = [_u.dot(precond[i], rhs) for i in range(n)]
    inverse = [None] * n
    for k in range(n):
        inverse[k] = 1.0 / a[k][k]
        for i in range(k + 1, n):
            factor = _u.mul(a[i][k], inverse[k])
            for j in range(k + 1, n):
                a[i][j] = _u.sub(a[i][j], _u.mul(factor, a[k][j]))
            b[i] = _u.sub(b[i], _u.mul(factor, b[k]))
    x = [None] * n
    for i in range(n - 1, -1, -1):
        total = b[i]
        for j in range(i + 1, n):
            total = _u.sub(total, _u.mul(a[i][j], x[j]))
        x[i] = _u.mul(total, inverse[i])
    return x


def _smooth_sign(qd):
    return (qd * (1.0 / COULOMB_VELOCITY)).tanh()


def _servo(q, qd, u, kp, kd):
    return [(qd[i] * kd[i] + q[i] * kp[i]) * -1.0 + u[i] for i in range(len(q))]


def _nominal_torque(layout, local, revolute, q, qd, nominal, u, kp, kd):
    """The computed torque ``M(q; th_n) v + h(q, qd; th_n)`` on a state (the controller)."""
    chain = layout.chain
    n = chain.n_joints
    count = len(local.units)
    v = _servo(q, qd, u, kp, kd)
    joints = _joints(local, revolute, q)
    torque = _inverse_dynamics(local, revolute, joints, qd, v, nominal[:count])
    out = []
    for j in range(n):
        total = torque[j]
        if chain.armature[j] != 0:
            total = _u.add(total, _u.mul(float(chain.armature[j]), v[j]))
        for k, kind in enumerate(layout.friction):
            moved = qd[j] if kind == "viscous" else _smooth_sign(qd[j])
            total = _u.add(total, _u.mul(nominal[count + k * n + j], moved))
        out.append(total)
    return out


def chain_perturbation_jets(
    layout: ChainLayout,
    q,
    qd,
    th,
    nominal,
    u,
    kp,
    kd,
    noise=None,
    precond=None,
    sign=None,
    keep=None,
):
    """``gv = qdd - v`` of a spatial chain on jets: a list of ``n`` jets.

    Args:
        layout: the chain and parameter layout (:class:`rmijax.robots.spatial.ChainLayout`).
        q, qd: the true state, lists of ``n`` jets (rad, rad/s; m, m/s for prismatic).
        th: ``p`` jets in the order of :mod:`rmijax.robots.spatial` (mass scales, payload
            mass, viscous then Coulomb friction).
        nominal: ``p`` constants of the backend: the controller's ``th_n``.
        u, kp, kd: ``n`` constants each: feed-forward acceleration and gains.
        noise: None, or ``(eq, eqd)``: lists of ``n`` jets, the reading errors the
            controller sees.
        precond: None (the tip-first ``U D U'`` solve, pivots the articulated
            inertias), or ``n x n`` constants ``P`` (:func:`solve_preconditioned`).
        sign: None (the Coulomb parameters' error moves ``tanh(qd_j / v_s)``), or ``n``
            constants of the backend, each an enclosure of ``tanh(qd_j / v_s)`` over
            the states the jets stand for: the Coulomb error then moves that constant
            (a bounded input: for every state there is one value in the enclosure
            that gives the same ``gv``, so jets over the enclosure hold the true
            expansion; the controller's own compensation keeps ``tanh``).
        keep: None, or with ``sign`` ``n`` constants, each 0 or 1: joint ``j``'s Coulomb
            error moves ``keep_j tanh(qd_j / v_s) + sign_j`` (1 and an enclosure of 0:
            the expansion; 0 and the sign's enclosure: the bounded input).

    Returns:
        ``n`` jets of ``gv`` (rad/s^2).
    """
    chain = layout.chain
    n = chain.n_joints
    local = _local(layout)
    revolute = [t == "revolute" for t in chain.joint_types]
    count = len(local.units)
    delta = [th[b] - nominal[b] for b in range(len(th))]
    v = _servo(q, qd, u, kp, kd)
    joints = _joints(local, revolute, q)
    torque = _inverse_dynamics(local, revolute, joints, qd, v, delta[:count])
    f = []
    for j in range(n):
        total = -torque[j]
        for k, kind in enumerate(layout.friction):
            if kind == "viscous":
                moved = qd[j]
            elif sign is None:
                moved = _smooth_sign(qd[j])
            elif keep is None:
                moved = sign[j]
            else:
                moved = _smooth_sign(qd[j]) * keep[j] + sign[j]
            total = total - delta[count + k * n + j] * moved
        f.append(total)
    if noise is not None:
        eq, eqd = noise
        yq = [q[i] + eq[i] for i in range(n)]
        yqd = [qd[i] + eqd[i] for i in range(n)]
        measured = _nominal_torque(layout, local, revolute, yq, yqd, nominal, u, kp, kd)
        true = _nominal_torque(layout, local, revolute, q, qd, nominal, u, kp, kd)
        f = [f[j] + measured[j] - true[j] for j in range(n)]
    matrix = _mass_matrix(local, revolute, joints, th[:count], chain.armature)
    if precond is not None:
        return solve_preconditioned(matrix, f, precond)
    return _solve_tip_first(matrix, f)
