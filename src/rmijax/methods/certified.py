"""Certified bounds: bands proven to contain every constant-parameter run of the closed loop.

What is certified (see ``docs/methods.md``, section "certified"): for the
discretised closed loop of SPEC section 3 (explicit Euler, the nominal
computed-torque controller fed by the readings, from ``x(0) = x_d(0)`` over
the whole horizon) in exact real arithmetic with the given float64 data
(``dt``, gains, ``u_d``, the box, gravity 9.81), and every *constant*
``th`` in the box, ``y_k(th)`` lies in ``[lower_k, upper_k]``; with sensor
noise in ``[V_lo, V_hi]`` (any sequence, it need not be constant) the band
holds the readings ``y_k + eta_k``, the controller acting on noisy readings
included.

Method: a second-order Taylor model in ``d = th - th_c`` along the centre
run ``x_c`` (``th_c`` the nominal, or a piece's centre when the box is
split),

    x_k(th) = x_c(k) + S_k d + 1/2 Q_k[d, d] + R_k,

whose coefficients are propagated step by step with interval 2-jets of the
perturbation ``gv`` (:mod:`rmijax._intervals`) evaluated at the centre. The
remainder obeys exactly ``R_{k+1} = A R_k + xi_k`` with ``A`` the linear
closed loop of every joint and ``xi_k`` bounded componentwise, ``|xi_k| <=
w_k``, by

- the Lagrange remainder of ``gv``'s second-order expansion in
  ``(d, R, eta)``: the Hessian of ``gv`` enclosed over the whole tube of step
  ``k`` (polynomial part over the box plus ``|R_k| <= r_k``) by interval
  2-jets, minus the centre's Hessian that ``Q`` already carries, plus the
  first-order ``R`` and noise terms;
- the rounding of the stored coefficients (each is the midpoint of its
  interval enclosure; the half-width is added).

Then ``|R_k| <= r_k = sum_j |A^(k-1-j)| w_j`` (the last :data:`KERNEL_STEPS`
powers exactly, older ones through ``||A^M||`` and a geometric tail): an
induction in which every step's ``w_k`` is computed over the tube that
``r_k`` defines. The band is the exact range of the quadratic over the box
(one-dimensional quadratics exactly, cross terms by interval products), plus
``r_k`` and the noise bounds, rounded outward.

That is ``enclosure="interval"``, ``propagate="kernel"``, the default up to two
joints. From three joints the default is ``enclosure="affine"`` (the Hessian over
the tube on affine forms with rounding bounded, :mod:`rmijax._affine`, one symbol per
variable of ``(d, R, eta)``, the state ``x_c + S d + R`` exact in them) and
``propagate="carried"``: ``R = G eps + sum_b d_b G^b eps`` through each piece's own
linearised loop ``A_c`` (``G^b`` picks up ``dt e2 H_b G``, the mass error acting on the
loop's gain), ``2n`` new generators a step sized by the bounded input and the products'
rounding (:func:`_carried_terms`, :func:`_carry_generators`). Tighter, and bounded at
four joints where the kernel diverges. :func:`rmijax.methods.certificate_check.check_certificate`
re-verifies every pair on short runs (its own affine arithmetic and generators on
``mpmath``).

Supported models: the planar point-mass arm (:func:`rmijax.planar_arm`,
:func:`rmijax.preset_arm`, ...), whose ``M`` and ``h`` the jets evaluate in their
closed form, and the serial chains of :func:`rmijax.load_robot` (Panda, iiwa14, UR5e,
any URDF/MJCF chain), evaluated by body-frame Newton-Euler, composite inertias and an
elimination preconditioned by the float inverse of ``M`` at each step's centre
(``solve="preconditioned"``; or the tip-first ``U D U'``, ``"articulated"``) on the
same jets (:mod:`rmijax.methods.chain_jets`; the
chain's constants, joint-frame products and inertias about the joint origins, rounded
once to float64). Other models are refused with a ``NotImplementedError``. On a chain
the default box of :func:`rmijax.robots.loaders.default_box` is wide: in one piece the
remainder diverges within the first second on every arm (within 0.1 s with the
Coulomb sign expanded, ``coulomb="taylor"``). Over the first second of ``rmijax
--robot``'s move a tenth of it is certified on all three arms, its friction ranges alone
on all three with the default ``coulomb="auto"`` (within 1.5x of the worst case at the
median on both sensors), and the UR5e's whole box cut in two along the payload, loosely
(1.6 / 5.7 of the worst case at the median), in 32 pieces within 1.5x at the median (1.08 /
1.46; ``docs/methods.md``, section 7).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from rmijax import _checks
from rmijax._affine import AffineForm, pair_count, paired_over, run_affine_tape
from rmijax._intervals import Interval, Tape, _slots, run_tape, tanh, up
from rmijax.control import coupled_perturbation
from rmijax.methods.base import Bounds, DivergedError, check_types
from rmijax.methods.chain_jets import chain_perturbation_jets, solve_preconditioned
from rmijax.robots.box import UncertainRobot
from rmijax.robots.model import GRAVITY
from rmijax.robots.planar import tail_sums
from rmijax.robots.spatial import COULOMB_VELOCITY, ChainLayout
from rmijax.robots.structure import PlanarPointMass
from rmijax.trajectory import Trajectory

__all__ = [
    "KERNEL_STEPS",
    "Certificate",
    "certified_bounds",
    "planar_perturbation_jets",
    "split_ranking",
]

KERNEL_STEPS = 400
"""Powers ``|A^m|``, ``m < KERNEL_STEPS``, applied exactly to the remainder's past inputs."""

_EPS = 2.0**-52
_TINY = 2.0**-1000
_CHECK_MARGIN = 1e-7
"""Each step's input bound ``w_k`` is raised by this relative amount (besides its rounding):
sound with or without it, it leaves room for the independent checker
(:mod:`rmijax.methods.certificate_check`), whose affine products centre their quadratic
part on its own exact ends rather than these floats. Affine arithmetic is not monotone
in those centres (a later product's ``|c| e`` grows as a centre moves off 0), so its
recomputed bound can come out above the certifier's: by up to 1e-10 of ``w_k`` measured
(the two-joint Coulomb arm, ``coulomb="range"``); without this margin the checker rejects
the certificate there."""
_NEGLIGIBLE = 1e-250  # a remainder radius this small is only the _TINY padding of the steps

AUTO_MAX_PIECES = 64
"""``certified_bounds(..., splits="auto")``: the most pieces the box is cut into."""

AUTO_REFINE = 0.5
"""``splits="auto"``: cut a piece whose remainder exceeds this share of the rest of its
band's half-width at the median step of some output."""

AUTO_CHUNK = 4
"""``splits="auto"`` with interval jets: pieces certified together per call, every call
the same size so that one compilation serves all rounds (affine jets use
:func:`_affine_batch`'s size)."""

ENCLOSURES = ("interval", "affine", "paired", "paired_inertia")
"""``certified_bounds(..., enclosure=...)``: how the Hessian over the tube is enclosed (the
two pairings: :func:`paired_variables`)."""

COULOMB_MODES = ("taylor", "range", "auto")
"""``certified_bounds(..., coulomb=...)``: how a chain's Coulomb errors enter the jets."""

COULOMB_RANGE_SPREAD = COULOMB_VELOCITY
"""``coulomb="auto"``: a joint's Coulomb sign is bounded by its range at a step where the
tube's velocities spread wider than this (rad/s); elsewhere it keeps its expansion.
Roughly, the expansion's remainder there grows like ``(spread / v_s)^2`` and the range's
input like ``spread / v_s``, so they cross near ``v_s``."""

_PIECES = "pieces"  # the vmapped axis of pieces certified together (_certify)

_AFFINE_BUFFER = 2_200_000  # bytes of affine jet buffers evaluated together (_affine_batch)


# --------------------------------------------------------------------------
# The perturbation of the planar arm on jets (any backend)
# --------------------------------------------------------------------------


def _angle_sums(q):
    """``phi_a = q_1 + .. + q_a`` and ``phi_a - phi_b = q_(b+1) + .. + q_a`` (b < a), as sums."""
    n = len(q)
    phi = [q[0]]
    for a in range(1, n):
        phi.append(phi[-1] + q[a])
    diff = [[None] * n for _ in range(n)]
    for a in range(n):
        total = None
        for b in range(a - 1, -1, -1):
            total = q[a] if total is None else total + q[b + 1]
            diff[a][b] = total
    return phi, diff


def _running(values):
    out = [values[0]]
    for value in values[1:]:
        out.append(out[-1] + value)
    return out


def _trig_state(q, qd, accel):
    """cos(phi_a), cos/sin(phi_a - phi_b), phid_a^2 and absolute accelerations, on jets."""
    n = len(q)
    phi, diff = _angle_sums(q)
    cos_phi = [p.cos() for p in phi]
    cos_d = [[None] * n for _ in range(n)]
    sin_d = [[None] * n for _ in range(n)]
    for a in range(n):
        for b in range(a):
            cos_d[a][b] = cos_d[b][a] = diff[a][b].cos()
            sin_d[a][b] = diff[a][b].sin()
            sin_d[b][a] = -sin_d[a][b]
    rate_sq = [r.square() for r in _running(qd)]
    return cos_phi, cos_d, sin_d, rate_sq, _running(accel)


def _torque_terms(weights, cos_phi, cos_d, sin_d, rate_sq, acc, gravity_weights):
    """``sum_b W_ab (C_ab acc_b + Sn_ab rate_b^2) + G_a cos(phi_a)`` per link ``a`` (a list)."""
    n = len(cos_phi)
    out = []
    for a in range(n):
        total = acc[a] * weights[a][a] + cos_phi[a] * gravity_weights[a]
        for b in range(n):
            if b != a:
                total = total + (acc[b] * cos_d[a][b] + rate_sq[b] * sin_d[a][b]) * weights[a][b]
        out.append(total)
    return out


def _articulated_solve(masses, cos_d, sin_d, rhs):
    """Solve ``(Mu o C) psi = rhs`` by eliminating from the tip: pivots without cancellation.

    ``(Mu o C)_ab = e_a' (sum_{k >= max(a, b)} m_k) e_b`` with ``e_a`` the unit vector
    of link ``a``. Eliminating links ``n-1 .. j+1`` leaves, for ``a, b <= j``, the same
    form with the eliminated links' articulated inertia ``kappa_(j+1) n n'`` added
    (``n`` the normal of link ``j+1``), so with ``B_j = m_j I + kappa_(j+1) n n'``:
    pivot ``D_j = e_j' B_j e_j = m_j + kappa_(j+1) sin^2(q_(j+1))``, column
    ``(Mu o C)'_aj = e_a' B_j e_j = m_j cos(phi_a - phi_j) + kappa_(j+1)
    sin(phi_a - phi_(j+1)) sin(phi_j - phi_(j+1))`` (a < j), and ``kappa_j = det B_j /
    D_j = m_j (m_j + kappa_(j+1)) / D_j`` (``kappa_n = 0``). Every pivot is a sum of
    non-negative terms, so interval enclosures stay away from 0 where base-first ``LDL'``
    of the tail sums (``mu_a - ...``, differences of shared masses) does not: at 4 links
    its third pivot's enclosure held 0 even with each mass range cut in 4.

    Args:
        masses: ``n`` link masses (kg); cos_d, sin_d: ``cos/sin(phi_a - phi_b)``
            (``n x n`` lists, the diagonal unused); rhs: ``n`` right-hand sides.

    Returns:
        ``psi``, a list of ``n``, with ``(Mu o C) psi = rhs``.
    """
    n = len(masses)
    column = [[None] * n for _ in range(n)]  # column[j][a] = U_aj (a < j), U unit upper
    inv_pivot = [None] * n
    kappa = None
    for j in range(n - 1, -1, -1):
        if kappa is None:
            pivot = masses[j]
            entries = [masses[j] * cos_d[a][j] for a in range(j)]
            kappa_next = masses[j]
        else:
            pivot = masses[j] + kappa * sin_d[j][j + 1].square()
            entries = [
                masses[j] * cos_d[a][j] + kappa * (sin_d[a][j + 1] * sin_d[j][j + 1])
                for a in range(j)
            ]
            kappa_next = masses[j] * (masses[j] + kappa) / pivot
        inv_pivot[j] = 1.0 / pivot
        column[j] = [entry * inv_pivot[j] for entry in entries]
        kappa = kappa_next
    # U D U' psi = rhs: U z = rhs from the tip, then U' psi = z / D from the base
    z = [None] * n
    for j in range(n - 1, -1, -1):
        total = rhs[j]
        for b in range(j + 1, n):
            total = total - column[b][j] * z[b]
        z[j] = total
    psi = [None] * n
    for j in range(n):
        total = z[j] * inv_pivot[j]
        for a in range(j):
            total = total - column[j][a] * psi[a]
        psi[j] = total
    return psi


def planar_perturbation_jets(q, qd, th, nominal, u, kp, kd, noise=None, precond=None):
    """``gv = qdd - v`` of the planar point-mass arm on jets: a list of ``n`` jets.

    Written as ``gv = M(q; th)^-1 f`` with
    ``f = (M(q; th_n) - M(q; th)) v + h(q, qd; th_n) - h(q, qd; th) + tau(y) - tau(x)``,
    whose terms each vanish at ``th = th_n`` (and the last at zero noise), so
    interval enclosures do not carry the size of ``v``. In absolute angles
    ``M = S' (W o C) S`` and ``h = S' (W o Sn) phid^2 + S' g mu l cos phi``
    (SPEC section 1), and ``M x = S' b`` is solved as
    ``(Mu o C)(l o S x) = b / l`` by eliminating from the tip (:func:`_articulated_solve`).

    Args:
        q, qd: the true state, lists of ``n`` jets (rad, rad/s).
        th: ``2n`` jets, masses (kg) then lengths (m).
        nominal: ``2n`` constants (intervals of the backend): the controller's ``th_n``.
        u, kp, kd: ``n`` constants each: feed-forward (rad/s^2) and gains.
        noise: None, or ``(eq, eqd)``: lists of ``n`` jets, the reading errors
            that the controller sees (``y = x + eta``).
        precond: None (the tip-first articulated solve), or ``n x n`` constants ``P``:
            ``(Mu o C) psi = b`` is solved as ``P (Mu o C) psi = P b`` by elimination
            (:func:`rmijax.methods.chain_jets.solve_preconditioned`; any ``P``).

    Returns:
        ``n`` jets of ``gv`` (rad/s^2).
    """
    n = len(q)
    masses, lengths = th[:n], th[n:]
    nominal_masses, nominal_lengths = nominal[:n], nominal[n:]
    mu = tail_sums(masses)
    mu_n = tail_sums(nominal_masses)

    def servo(qq, qqd):
        return [(qqd[i] * kd[i] + qq[i] * kp[i]) * -1.0 + u[i] for i in range(n)]

    nominal_w = [
        [mu_n[max(a, b)] * nominal_lengths[a] * nominal_lengths[b] for b in range(n)]
        for a in range(n)
    ]
    delta_w = [
        [(mu[max(a, b)] * lengths[a] * lengths[b]) * -1.0 + nominal_w[a][b] for b in range(n)]
        for a in range(n)
    ]
    nominal_g = [mu_n[a] * nominal_lengths[a] * GRAVITY for a in range(n)]
    delta_g = [(mu[a] * lengths[a]) * -GRAVITY + nominal_g[a] for a in range(n)]
    v = servo(q, qd)
    cos_phi, cos_d, sin_d, rate_sq, acc = _trig_state(q, qd, v)
    f_phi = _torque_terms(delta_w, cos_phi, cos_d, sin_d, rate_sq, acc, delta_g)
    if noise is not None:
        eq, eqd = noise
        yq = [q[i] + eq[i] for i in range(n)]
        yqd = [qd[i] + eqd[i] for i in range(n)]
        measured = _torque_terms(nominal_w, *_trig_state(yq, yqd, servo(yq, yqd)), nominal_g)
        true = _torque_terms(nominal_w, cos_phi, cos_d, sin_d, rate_sq, acc, nominal_g)
        f_phi = [f_phi[a] + measured[a] - true[a] for a in range(n)]
    rhs = [f_phi[a] / lengths[a] for a in range(n)]
    if precond is None:
        psi = _articulated_solve(masses, cos_d, sin_d, rhs)
    else:
        matrix = [
            [mu[a] if a == b else mu[max(a, b)] * cos_d[a][b] for b in range(n)] for a in range(n)
        ]
        psi = solve_preconditioned(matrix, rhs, precond)
    phidd = [psi[a] / lengths[a] for a in range(n)]
    return [phidd[0]] + [phidd[a] - phidd[a - 1] for a in range(1, n)]


# --------------------------------------------------------------------------
# Certificate
# --------------------------------------------------------------------------


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Certificate:
    """Everything needed to re-verify a certified band.

    See :func:`rmijax.methods.certificate_check.check_certificate`.

    ``P`` pieces of the box (one unless split), ``T`` steps, ``n`` joints,
    ``p`` parameters, ``M`` kernel steps.

    Attributes:
        center: (P, p) expansion point ``th_c`` of each piece.
        lo, hi: (P, p) each piece's box (their union is the whole box).
        state: (P, T+1, n, 2) the centre run's coefficients ``x_c(k)``.
        sens: (P, T+1, n, 2, p) first-order coefficients ``S_k``.
        sens2: (P, T+1, n, 2, p, p) second-order coefficients ``Q_k``.
        injected: (P, T, n, 2) ``w_k``: bound on the remainder's input at step k.
        remainder: (P, T+1, n, 2) ``r_k``: bound on ``|R_k|``.
        kernel: (M, n, 2, 2) upper bounds of ``|A_i^m|``.
        tail: (n,) bound on ``sum_{m >= M} ||A_i^m||_inf``.
        lower, upper: (T+1, n, 2) the band (noise included).
        noise_lo, noise_hi: (n, 2) sensor noise bounds.
        segments: radial segments of the Lagrange remainder (static).
        enclosure: one of :data:`ENCLOSURES`: how the Hessian over the tube was
            enclosed (static; the pairings follow from it and the box,
            :func:`paired_variables`).
        propagate: ``"kernel"`` (``remainder`` from ``injected`` through ``kernel``
            and ``tail``) or ``"carried"`` (through the pieces' own loops; the
            generators are not stored: :func:`check_certificate` carries its own) (static).
        solve: ``"articulated"`` or ``"preconditioned"``: how the jets solve ``M gv =
            f`` (the preconditioner is recomputed, not stored: any is sound) (static).
        coulomb: ``"taylor"``, ``"range"`` or ``"auto"``: how a chain's Coulomb errors
            entered the jets (the sign's enclosures are recomputed from each step's tube,
            not stored) (static).
        keep: with ``coulomb="auto"``, (P, T, n): 1 where joint ``j``'s sign kept its
            expansion at step ``k``, 0 where it was bounded by its range (a choice, sound
            either way: the checker follows it); else None.
    """

    center: jax.Array
    lo: jax.Array
    hi: jax.Array
    state: jax.Array
    sens: jax.Array
    sens2: jax.Array
    injected: jax.Array
    remainder: jax.Array
    kernel: jax.Array
    tail: jax.Array
    lower: jax.Array
    upper: jax.Array
    noise_lo: jax.Array
    noise_hi: jax.Array
    segments: int = dataclasses.field(default=3, metadata=dict(static=True))
    enclosure: str = dataclasses.field(default="interval", metadata=dict(static=True))
    propagate: str = dataclasses.field(default="kernel", metadata=dict(static=True))
    solve: str = dataclasses.field(default="articulated", metadata=dict(static=True))
    coulomb: str = dataclasses.field(default="taylor", metadata=dict(static=True))
    keep: jax.Array | None = None

    @property
    def n_pieces(self) -> int:
        return self.center.shape[0]


# --------------------------------------------------------------------------
# Float helpers with rounding bounds
# --------------------------------------------------------------------------


def _sum_up(terms, axes, count):
    """Upper bound of the exact sum of non-negative float products summed over ``axes``."""
    return jnp.sum(terms, axis=axes) * (1.0 + (count + 8) * _EPS) + _TINY


def _poly_range(sens, sens2, d_lo, d_hi):
    """Sound range of ``s' d + 1/2 d' Q d`` over the box ``d_lo <= d <= d_hi``.

    Args:
        sens: (..., p); sens2: (..., p, p); d_lo, d_hi: (p,) with ``d_lo <= 0 <= d_hi``.

    Returns:
        ``(low, high)`` (...) floats bounding the exact range outward: each
        one-dimensional quadratic ``s_b d_b + 1/2 Q_bb d_b^2`` exactly (ends and
        vertex), each cross term ``Q_ab d_a d_b`` by its exact interval, summed.
    """
    p = sens.shape[-1]
    d_lo, d_hi = jnp.broadcast_to(d_lo, sens.shape), jnp.broadcast_to(d_hi, sens.shape)
    diag = 0.5 * jnp.diagonal(sens2, axis1=-2, axis2=-1)  # (..., p)
    ends = jnp.stack([sens * d_lo + diag * d_lo**2, sens * d_hi + diag * d_hi**2])
    safe = jnp.where(diag == 0, 1.0, diag)
    vertex = -sens / (2.0 * safe)
    inside = (diag != 0) & (vertex > d_lo) & (vertex < d_hi)
    vertex_value = jnp.where(inside, -(sens**2) / (4.0 * safe), ends[0])
    low_b = jnp.minimum(jnp.min(ends, axis=0), vertex_value)
    high_b = jnp.maximum(jnp.max(ends, axis=0), vertex_value)
    radius = jnp.maximum(-d_lo, d_hi)
    magnitude = jnp.sum(jnp.abs(sens) * radius + jnp.abs(diag) * radius**2, axis=-1)
    sym = 0.5 * (sens2 + jnp.swapaxes(sens2, -1, -2))
    off = jnp.broadcast_to(1.0 - jnp.eye(p, dtype=sens.dtype), sym.shape)
    a_lo, a_hi = d_lo[..., :, None], d_hi[..., :, None]
    b_lo, b_hi = d_lo[..., None, :], d_hi[..., None, :]
    products = jnp.stack(
        [a_lo * b_lo, a_lo * b_hi, a_hi * b_lo, a_hi * b_hi]
    )  # (4, p, p): d_a d_b at the box's corners (its exact range is their hull)
    pair_lo, pair_hi = jnp.min(products, axis=0), jnp.max(products, axis=0)
    cross = 0.5 * sym * off  # the pair (a, b) and (b, a) together: Q_ab d_a d_b
    cross_lo = jnp.sum(jnp.minimum(cross * pair_lo, cross * pair_hi), axis=(-2, -1))
    cross_hi = jnp.sum(jnp.maximum(cross * pair_lo, cross * pair_hi), axis=(-2, -1))
    magnitude = magnitude + jnp.sum(
        jnp.abs(cross) * radius[..., :, None] * radius[..., None, :], axis=(-2, -1)
    )
    slack = (p * p + 4 * p + 16) * _EPS * magnitude + _TINY
    return jnp.sum(low_b, -1) + cross_lo - slack, jnp.sum(high_b, -1) + cross_hi + slack


def _kernel(kp, kd, dt, steps):
    """Upper bounds ``|A_i^m|`` (steps, n, 2, 2) and the tail coefficient (n,).

    ``A_i = [[1, dt], [-Kp dt, 1 - Kd dt]]`` with its entries as exact reals;
    powers in interval arithmetic. Tail: with ``a = ||A^M||_inf < 1``,
    ``sum_{m >= M} ||A^m|| <= a sum_{j < M} ||A^j|| / (1 - a)``.
    """
    one = jnp.ones_like(kp)
    a11, a12 = Interval(one), Interval(dt * one)
    a21 = Interval(kp) * (-dt)
    a22 = Interval(one) - Interval(kd) * dt

    def body(power, _):
        (p11, p12), (p21, p22) = power
        nxt = (
            (a11 * p11 + a12 * p21, a11 * p12 + a12 * p22),
            (a21 * p11 + a22 * p21, a21 * p12 + a22 * p22),
        )
        return nxt, jnp.stack(
            [jnp.stack([p11.mag(), p12.mag()], -1), jnp.stack([p21.mag(), p22.mag()], -1)], -2
        )

    zero = Interval(jnp.zeros_like(kp))
    start = ((Interval(one), zero), (zero, Interval(one)))
    last, mags = jax.lax.scan(body, start, None, length=steps)
    (p11, p12), (p21, p22) = last
    power_norm = up(jnp.maximum(p11.mag() + p12.mag(), p21.mag() + p22.mag()))
    norms = jnp.max(jnp.sum(mags, axis=-1), axis=-1)  # (steps, n)
    total = _sum_up(norms, 0, steps)
    tail = up(up(power_norm * total) / jnp.maximum(1.0 - power_norm, _TINY))
    tail = jnp.where(power_norm < 1.0, tail, jnp.inf)
    return mags, tail


# --------------------------------------------------------------------------
# The certified run of one piece
# --------------------------------------------------------------------------


def perturbation_jets(layout):
    """The function ``(q, qd, th, nominal, u, kp, kd, noise, precond) -> gv`` jets of a model:
    :func:`planar_perturbation_jets` for ``layout=None`` (the planar arm), else
    :func:`rmijax.methods.chain_jets.chain_perturbation_jets` for that chain."""
    if layout is None:
        return planar_perturbation_jets
    return functools.partial(chain_perturbation_jets, layout)


def _layout(params):
    """``None`` for the planar arm, the chain's layout for a loaded arm; refuses others."""
    structure = params.model.structure
    if isinstance(structure, PlanarPointMass):
        return None
    layout = getattr(structure, "layout", None)
    if isinstance(layout, ChainLayout):
        return layout
    raise NotImplementedError(
        f"certified_bounds supports the planar point-mass arm (rmijax.planar_arm, "
        f"preset_arm, paper_arm2, paper_pendulum) and the serial chains of "
        f"rmijax.load_robot only, got model {params.model.name!r}: its mass matrix and "
        "bias must be evaluated on interval 2-jets (rmijax.methods.chain_jets shows what "
        "is needed)"
    )


@functools.cache
def _perturbation_tape(layout, n, p, noisy, precond=False, ranged=False):
    """The tape of :func:`perturbation_jets` for ``n`` joints and ``p`` parameters, and its
    output rows.

    Leaves, in order: ``q (n), qd (n), th (p)``, with noise ``eq (n), eqd (n)``,
    then the constants ``nominal (p), u (n), kp (n), kd (n)``, with ``precond`` the
    preconditioner ``P (n * n)`` of the solve, row by row
    (:func:`rmijax.methods.chain_jets.solve_preconditioned`), and with ``ranged`` (a
    chain only; ``"range"`` or ``"auto"``, the ``coulomb`` option) with ``"auto"`` the
    multipliers ``keep (n)`` of the smooth signs, then the Coulomb signs' enclosures
    ``(n)``.
    """
    tape = Tape(_tape_leaves(n, p, noisy, precond, ranged))
    leaves = tape.leaves()
    take = iter(leaves)
    q, qd = [next(take) for _ in range(n)], [next(take) for _ in range(n)]
    th = [next(take) for _ in range(p)]
    noise = None
    if noisy:
        noise = ([next(take) for _ in range(n)], [next(take) for _ in range(n)])
    nominal = [next(take) for _ in range(p)]
    u, kp, kd = ([next(take) for _ in range(n)] for _ in range(3))
    matrix = [[next(take) for _ in range(n)] for _ in range(n)] if precond else None
    extra = {}
    if ranged == "auto":
        extra["keep"] = [next(take) for _ in range(n)]
    if ranged:
        extra["sign"] = [next(take) for _ in range(n)]
    gv = perturbation_jets(layout)(q, qd, th, nominal, u, kp, kd, noise, matrix, **extra)
    return tape.arrays(), tuple(node.index for node in gv)


def _tape_leaves(n, p, noisy, precond=False, ranged=False):
    """How many leaves :func:`_perturbation_tape` has for ``n`` joints, ``p`` parameters."""
    leaves = 2 * n + p + (2 * n if noisy else 0) + p + 3 * n + (n * n if precond else 0)
    return leaves + (n if ranged else 0) + (n if ranged == "auto" else 0)


def _constants(consts):
    """The tape's constant leaves as ``(lo, hi)``: nominal, u, kp, kd, the preconditioner
    and the signs' multipliers ``consts["keep"]`` if given (all points), then the Coulomb
    signs' enclosures if given (``consts["sign"]``, a pair of (n,) ends)."""
    parts = [consts["nominal"], consts["u"], consts["kp"], consts["kd"]]
    if consts.get("precond") is not None:
        parts.append(jnp.asarray(consts["precond"]).reshape(-1))
    if consts.get("keep") is not None:
        parts.append(consts["keep"])
    points = jnp.concatenate(parts)
    if consts.get("sign") is None:
        return points, points
    sign_lo, sign_hi = consts["sign"]
    return jnp.concatenate([points, sign_lo]), jnp.concatenate([points, sign_hi])


def _tape_flags(consts):
    """``(precond, ranged)`` of the tape that ``consts`` feed."""
    ranged = False
    if consts.get("sign") is not None:
        ranged = "auto" if consts.get("keep") is not None else "range"
    return consts.get("precond") is not None, ranged


def solve_matrix(params):
    """``(q, th) -> A`` (n, n) float: the matrix that the perturbation's jets solve with,
    for :func:`_preconditioner`: ``M(q; th)`` of a chain, ``Mu o C`` (``(Mu o C)_ab =
    mu_max(a, b) cos(phi_a - phi_b)``, ``mu`` the tail sums of the masses) of the planar
    arm."""
    if _layout(params) is not None:
        return params.model.mass_matrix

    def planar(q, th):
        n = q.shape[0]
        mu = jnp.cumsum(th[:n][::-1])[::-1]
        phi = jnp.cumsum(q)
        index = jnp.maximum(jnp.arange(n)[:, None], jnp.arange(n)[None, :])
        return mu[index] * jnp.cos(phi[:, None] - phi[None, :])

    return planar


def _preconditioner(matrix_fn, xc, center, fixed, free):
    """``A(q_c; th_c)^-1`` in float64 (``matrix_fn`` from :func:`solve_matrix`): the
    preconditioner of the solve at a centre state. Any matrix is sound there (see
    :func:`rmijax.methods.chain_jets.solve_preconditioned`); this one keeps its pivots
    near 1."""
    th = center if free is None else fixed.at[np.asarray(free, dtype=np.int32)].set(center)
    return jnp.linalg.inv(matrix_fn(xc[:, 0], th))


def _cat(*parts):
    return Interval(
        jnp.concatenate([p.lo for p in parts], 0), jnp.concatenate([p.hi for p in parts], 0)
    )


def _evaluate(state, state_grad_d, sens2, th_value, noise_value, consts, layout=None, free=None):
    """``gv`` jets in the variables ``(d (p), R (2n)[, eta (2n)])`` of one step.

    Args:
        state: Interval (n, 2) values of the state; state_grad_d: Interval (n, 2, p)
            its derivative in ``d``; sens2: (n, 2, p, p) its second derivative.
        th_value: Interval (p,); noise_value: Interval (n, 2) or None.
        consts: dict of nominal (p,), u, kp, kd (n,), with ``free`` fixed (all
            parameters), and precond (n, n) (:func:`_preconditioner`) or None.
        layout: the model's (:func:`_layout`).
        free: None, or the indices of the uncertain parameters (static): then ``d``,
            ``th_value`` and the state's derivatives hold those only, and the certain
            ones enter as the constants ``consts["fixed"]`` (the box's ``lo == hi``).

    Returns:
        Intervals ``gv`` (n,), gradient (n, m), Hessian (n, m, m).
    """
    n, p = state.shape[0], state_grad_d.shape[-1]
    noisy = noise_value is not None
    m = p + 2 * n + (2 * n if noisy else 0)
    dtype = state.lo.dtype
    eye = jnp.eye(m, dtype=dtype)
    unit_r = eye[p : p + 2 * n].reshape(n, 2, m)
    grad_d_full = Interval(
        jnp.zeros((n, 2, m), dtype).at[..., :p].set(state_grad_d.lo) + unit_r,
        jnp.zeros((n, 2, m), dtype).at[..., :p].set(state_grad_d.hi) + unit_r,
    )
    hess = jnp.zeros((n, 2, m, m), dtype).at[..., :p, :p].set(sens2)
    swap = lambda x: jnp.swapaxes(x, 0, 1).reshape((2 * n,) + x.shape[2:])  # noqa: E731
    th_grad = eye[:p]
    if free is not None:  # the certain parameters: constants of the tape
        fixed, rows = consts["fixed"], np.asarray(free, dtype=np.int32)
        th_value = Interval(fixed.at[rows].set(th_value.lo), fixed.at[rows].set(th_value.hi))
        th_grad = jnp.zeros((fixed.shape[0], m), dtype).at[rows].set(th_grad)
    width = th_grad.shape[0]  # the tape's parameters
    values = [Interval(swap(state.lo), swap(state.hi)), th_value]
    grads = [Interval(swap(grad_d_full.lo), swap(grad_d_full.hi)), Interval(th_grad)]
    hessians = [Interval(swap(hess)), Interval(jnp.zeros((width, m, m), dtype))]
    if noisy:
        values.append(Interval(swap(noise_value.lo), swap(noise_value.hi)))
        grads.append(Interval(swap(eye[p + 2 * n :].reshape(n, 2, m))))
        hessians.append(Interval(jnp.zeros((2 * n, m, m), dtype)))
    const_lo, const_hi = _constants(consts)
    values.append(Interval(const_lo, const_hi))
    grads.append(Interval(jnp.zeros((const_lo.shape[0], m), dtype)))
    hessians.append(Interval(jnp.zeros((const_lo.shape[0], m, m), dtype)))
    value, grad, hessian = _cat(*values), _cat(*grads), _cat(*hessians)
    tape, rows = _perturbation_tape(layout, n, width, noisy, *_tape_flags(consts))
    leaves = (value.lo, value.hi, grad.lo, grad.hi, hessian.lo, hessian.hi)
    return run_tape(tape, leaves, np.asarray(rows))


def _evaluate_affine(
    xc, sens, sens2, center, d_rad, rhat, eta_hat, scale, consts, layout=None, free=None,
    paired=False,
):  # fmt: skip
    """The Hessian of ``gv`` in ``z = (d, R[, eta])`` over the box ``scale Z``, enclosed
    by affine arithmetic with rounding bounded (:mod:`rmijax._affine`).

    Each variable of ``z`` is one symbol: ``d_b = scale d_rad_b eps_b``, ``R_(i, s) =
    scale rhat_(i, s) eps``, ``eta`` alike. The state enters as ``x = x_c + S d + R``
    exactly in those symbols (``1/2 Q[d, d]`` bounded into its error term) and its
    ``d``-gradient as ``S + Q d``, so the dependence of the state on the parameters,
    which interval arithmetic forgets, is kept. (With ``R`` in the error terms instead
    of symbols the evaluation is 1.5x faster, but the 4-link induction diverged at step
    48 where with symbols it stays bounded.)

    Args:
        xc: (n, 2) centre state; sens: (n, 2, p); sens2: (n, 2, p, p) (symmetric).
        center: (p,) ``th_c``; d_rad: (p,) the piece's half-widths (upper bounds);
        rhat: (n, 2) remainder bound; eta_hat: (n, 2) noise bound, or None.
        scale: the segment's end ``s``; consts, layout, free: as :func:`_evaluate`.
        paired: (static) False, or the forms are :class:`rmijax._affine.PairedForm`: the
            products' first-order parts, and the state's ``1/2 Q[d, d]``, carried in pair
            symbols, of every variable (True) or of those of a sorted tuple of indices of
            ``z`` (:func:`paired_variables`).

    Returns:
        ``(lo, hi)`` (n, m, m): bounds of every Hessian entry over the box.
    """
    n, p = xc.shape[0], center.shape[0]
    noisy = eta_hat is not None
    m = p + 2 * n + (2 * n if noisy else 0)
    dtype = xc.dtype
    rad_parts = [d_rad, rhat.reshape(-1)] + ([eta_hat.reshape(-1)] if noisy else [])
    rad = jnp.concatenate(rad_parts) * scale
    rad = rad * (1.0 + 4 * _EPS)  # a symbol may cover a little more than its variable
    eye = jnp.eye(m, dtype=dtype)
    swap = lambda x: jnp.swapaxes(x, 0, 1).reshape((2 * n,) + x.shape[2:])  # noqa: E731

    def exact(c, a, e):  # the rounding of c and a is added to e
        slack = (jnp.abs(c) + jnp.sum(jnp.abs(a), axis=-1)) * 2.0**-50
        return AffineForm(c, a, (e + slack) * (1.0 + 16 * _EPS) + _TINY)

    # state values: x_c + S d + R (+ the quadratic in the error term)
    coef = jnp.zeros((n, 2, m), dtype).at[..., :p].set(sens)
    coef = coef + eye[p : p + 2 * n].reshape(n, 2, m)
    quad = 0.5 * jnp.sum(
        jnp.abs(sens2) * (rad[:p, None] * rad[None, :p])[None, None], axis=(-2, -1)
    )
    quad = quad * (1.0 + (p * p + 8) * _EPS)
    x_form = exact(swap(xc), swap(coef) * rad[None], swap(quad))
    # the gradient: S + Q d in d, unit vectors in R
    g_a = jnp.zeros((n, 2, m, m), dtype).at[..., :p, :p].set(sens2 * rad[None, None, None, :p])
    g_form = exact(swap(coef), swap(g_a), jnp.zeros((2 * n, m), dtype))
    h_x = jnp.zeros((n, 2, m, m), dtype).at[..., :p, :p].set(sens2)
    th_c, th_a, th_grad = center, eye[:p] * rad[None], eye[:p]
    if free is not None:  # the certain parameters: constants of the tape
        fixed, rows = consts["fixed"], np.asarray(free, dtype=np.int32)
        th_c = fixed.at[rows].set(center)
        th_a = jnp.zeros((fixed.shape[0], m), dtype).at[rows].set(th_a)
        th_grad = jnp.zeros((fixed.shape[0], m), dtype).at[rows].set(th_grad)
    width = th_c.shape[0]  # the tape's parameters
    th_form = exact(th_c, th_a, jnp.zeros((width,), dtype))
    values, grads, hess = [x_form, th_form], [g_form], [swap(h_x)]
    grads.append(AffineForm.point(th_grad, m))
    hess.append(jnp.zeros((width, m, m), dtype))
    if noisy:
        eta_c = jnp.zeros((2 * n,), dtype)
        unit_eta = swap(eye[p + 2 * n :].reshape(n, 2, m))
        values.append(exact(eta_c, unit_eta * rad[None], eta_c))
        grads.append(AffineForm.point(unit_eta, m))
        hess.append(jnp.zeros((2 * n, m, m), dtype))
    const_lo, const_hi = _constants(consts)
    count = const_lo.shape[0]
    points = count - (n if consts.get("sign") is not None else 0)
    values.append(AffineForm.point(const_lo[:points], m))
    if points < count:  # the Coulomb signs' enclosures: centre and radius (rounding in e)
        sign_c = 0.5 * (const_lo[points:] + const_hi[points:])
        sign_e = jnp.maximum(const_hi[points:] - sign_c, sign_c - const_lo[points:])
        values.append(exact(sign_c, jnp.zeros((n, m), dtype), sign_e))
    grads.append(AffineForm.point(jnp.zeros((count, m), dtype), m))
    hess.append(jnp.zeros((count, m, m), dtype))

    def cat(forms):
        parts = [jnp.concatenate([getattr(f, key) for f in forms], 0) for key in "cae"]
        return AffineForm(*parts)

    leaves = (cat(values), cat(grads), cat([AffineForm.point(h, m) for h in hess]))
    form = AffineForm
    if paired is not False and paired is not None:
        index = tuple(range(m)) if paired is True else paired
        form = paired_over(m, index)
        leaves = _paired_leaves(leaves, x_form, sens2, rad, n, p, form, index)
    tape, rows = _perturbation_tape(layout, n, width, noisy, *_tape_flags(consts))
    _, _, h = run_affine_tape(tape, leaves, np.asarray(rows), form)
    return h.bounds()


def _paired_leaves(leaves, x_form, sens2, rad, n, p, form, index):
    """The leaves of :func:`_evaluate_affine` as ``form`` jets (a class of
    :func:`rmijax._affine.paired_over` pairing the variables ``index``): every form padded
    with zero pair coefficients, and the states' ``1/2 Q[d, d]`` (``d_b = rad_b eps_b``)
    moved from their error terms into the pair symbols of ``d``: ``Q_bc rad_b rad_c`` on
    ``eps_b eps_c`` (``b < c``) and ``1/4 Q_bb rad_b^2`` on ``2 eps_b^2 - 1`` and in the
    centre, for the pairs of paired variables; the other pairs' ``1/2 |Q_bc| rad_b rad_c``
    stay in the error terms, with the rounding."""
    m = rad.shape[0]
    total = pair_count(m, len(index))

    def pad(f):
        zeros = jnp.zeros(f.a.shape[:-1] + (total - m,), f.a.dtype)
        return form(f.c, jnp.concatenate([f.a, zeros], -1), f.e)

    value, grad, hess = (pad(f) for f in leaves)
    index = np.asarray(index, dtype=np.int32)
    rows, cols = (index[i] for i in np.triu_indices(index.size))
    inner = (rows < p) & (cols < p)  # the pairs of d's symbols
    rr, cc = rows[inner], cols[inner]
    weight = rad[rr] * rad[cc]
    swap = lambda x: jnp.swapaxes(x, 0, 1).reshape((2 * n,) + x.shape[2:])  # noqa: E731
    q = swap(sens2)[:, rr, cc] * weight[None]  # (2n, pairs)
    coef = jnp.where((rr == cc)[None], 0.25 * q, q)
    centre = jnp.sum(jnp.where((rr == cc)[None], 0.25 * q, 0.0), -1)
    where = np.flatnonzero(inner) + m
    states = 2 * n  # the leaves start with the 2n states (x_form)
    c = value.c.at[:states].add(centre)
    a = value.a.at[:states, where].set(coef)
    # the error term held 1/2 sum |Q| rad rad; now the rounding of the state's centre and
    # coefficients (as exact() in _evaluate_affine) and of the carried terms: q (3 ulps),
    # the centre's sum of p terms, its addition to c; and the pairs of d not carried
    own = (jnp.abs(x_form.c) + jnp.sum(jnp.abs(x_form.a), -1)) * 2.0**-50
    carried = jnp.sum(jnp.abs(q), -1) * ((p + 8) * _EPS) + jnp.abs(c[:states]) * _EPS
    d_paired = np.isin(np.arange(p), index)
    left = ~(d_paired[:, None] & d_paired[None, :])  # (p, p): the pairs of d not carried
    rest = 0.0
    if left.any():
        weights = jnp.where(left, rad[:p, None] * rad[None, :p], 0.0)[None]
        rest = 0.5 * jnp.sum(jnp.abs(swap(sens2)) * weights, (-2, -1))
        rest = rest * (1.0 + (p * p + 8) * _EPS)
    e = value.e.at[:states].set((own + carried + rest) * (1.0 + 16 * _EPS) + _TINY)
    return form(c, a, e), grad, hess


def paired_variables(enclosure, layout, n, p, free=None, noisy=False):
    """The variables of ``z = (d, R[, eta])`` whose products the jets carry in pair symbols
    (static, a sorted tuple of indices), or None (``"interval"``, ``"affine"``).

    ``"paired"``: every variable. ``"paired_inertia"``: those of the uncertain parameters
    that enter ``M`` (every parameter of the planar arm; a chain's mass scales and payload,
    not its friction coefficients, which enter ``h`` affinely and multiply only the joint
    velocities) and of the remainder ``R``, not the noise ``eta``. Any choice is sound (the
    products of the others are bounded as in the affine forms); this one is the checker's
    too.

    Args:
        enclosure: the ``enclosure`` option; layout: the chain's layout or None (planar);
        n: joints; p: the uncertain parameters (``d``'s length); free: their indices among
        all parameters (None: all); noisy: ``z`` holds ``eta``.
    """
    if enclosure not in ("paired", "paired_inertia"):
        return None
    m = p + 2 * n + (2 * n if noisy else 0)
    if enclosure == "paired":
        return tuple(range(m))
    if layout is None:
        d = tuple(range(p))
    else:  # a chain's parameters: the mass scales, the payload, then the friction
        inertial = n + (layout.payload is not None)
        d = tuple(i for i, b in enumerate(range(p) if free is None else free) if b < inertial)
    return d + tuple(range(p, p + 2 * n))


def _certify_piece(
    center,
    lo,
    hi,
    traj,
    nominal,
    noise_lo,
    noise_hi,
    kernel,
    tail,
    noisy,
    scale,
    segments,
    diagnostics=False,
    enclosure="interval",
    propagate="kernel",
    layout=None,
    free=None,
    fixed=None,
    matrix_fn=None,
    axis_name=None,
    coulomb="taylor",
    coulomb_spread=COULOMB_RANGE_SPREAD,
):
    """The Taylor-model induction over the whole run for one piece of the box.

    ``scale`` multiplies the remainder (1 in use; the tests' mutations set it to
    0 or 0.5 to show that it matters). With ``free`` (static) the piece's ``center``,
    ``lo``, ``hi`` hold the uncertain parameters only and ``fixed`` (p,) gives the
    others. With ``matrix_fn`` (static, :func:`solve_matrix`) the solve is preconditioned
    by its inverse at each step's centre. With ``diagnostics`` (static) the output also
    holds ``w_blocks`` (T, n, 10):
    ``w_k`` split by source (see :func:`_w_blocks`), and ``w_rest`` (T, n, 2): the rest of
    ``w_k``'s velocity row, the carried propagation's bounded terms (``extra`` of
    :func:`_carried_terms`) and the stored coefficients' enclosure radius over ``dt`` (their
    rounding and, with Coulomb ranges, the sign's range). Once the remainder radius is not
    finite the remaining steps are skipped (their outputs set to ``inf``); under a
    ``vmap`` named ``axis_name`` only once every piece's is not finite. With
    ``coulomb="range"`` (static) the Coulomb errors move an enclosure of their sign over
    each step's tube (:func:`_sign_range`) instead of its Taylor expansion; with
    ``"auto"`` where the tube's velocities spread wider than ``coulomb_spread`` (rad/s;
    static) (the output also holds ``keep``
    (T, n), the choice per step).
    """
    n = traj.n_joints
    p = center.shape[0]
    dtype = center.dtype
    d_lo = Interval(lo) - Interval(center)
    d_hi = Interval(hi) - Interval(center)
    d_lo, d_hi = jnp.minimum(d_lo.lo, 0.0), jnp.maximum(d_hi.hi, 0.0)
    d_box = Interval(d_lo, d_hi)
    d_rad = jnp.maximum(-d_lo, d_hi)
    d_outer = d_rad[:, None] * d_rad[None, :]
    # the noise variables are expanded at 0, so their box must hold 0
    noise_box = Interval(jnp.minimum(noise_lo, 0.0), jnp.maximum(noise_hi, 0.0)) if noisy else None
    kp, kd, dt = traj.kp, traj.kd, traj.dt
    eta_hat = jnp.maximum(jnp.abs(noise_lo), jnp.abs(noise_hi))
    steps = kernel.shape[0]
    # radial segments [j/J, (j+1)/J] and their weights int (1 - s) ds (rounded up)
    seg_hi = (np.arange(segments) + 1.0) / segments
    seg_lo = np.arange(segments) / segments
    seg_weight = up(jnp.asarray((seg_hi - seg_lo) - 0.5 * (seg_hi**2 - seg_lo**2), dtype))
    seg_hi = jnp.asarray(seg_hi, dtype)
    m = p + 2 * n + (2 * n if noisy else 0)
    carried = propagate == "carried"
    n_steps = traj.u_d.shape[0] - 1
    columns = 2 * n * n_steps if carried else 1  # the remainder's generators

    def step(carry, u):
        rhat = carry[5]
        alive = jnp.all(jnp.isfinite(rhat))
        if axis_name is not None:  # pieces certified together stop when all have diverged
            alive = jax.lax.pmax(alive.astype(jnp.int32), axis_name) > 0
        return jax.lax.cond(alive, live_step, dead_step, carry, u)

    def dead_step(carry, u):
        """After the remainder stopped being finite (every band from here on is not finite,
        as it would be with ``live_step``): skip the work."""
        xc, sens, sens2, buf, tail_max, rhat, gens, gens_d, k = carry
        rhat = jnp.full_like(rhat, jnp.inf)
        blocks = jnp.full((n, 12), jnp.inf, dtype) if diagnostics else None
        ys = tuple(jnp.full_like(a, jnp.inf) for a in (xc, sens, sens2, rhat, rhat))
        keep = jnp.ones((n,), dtype) if coulomb == "auto" else None
        return (xc, sens, sens2, buf, tail_max, rhat, gens, gens_d, k + 1), (*ys, blocks, keep)

    def live_step(carry, u):
        xc, sens, sens2, buf, tail_max, rhat, gens, gens_d, k = carry
        consts = _step_consts(
            xc, sens, sens2, center, d_lo, d_hi, rhat, u, nominal, kp, kd, fixed,
            matrix_fn=matrix_fn, free=free, coulomb=coulomb, coulomb_spread=coulomb_spread,
        )  # fmt: skip
        keep = consts.get("keep")
        # --- the centre: coefficients of the next Taylor model ---------------
        zero_noise = Interval(jnp.zeros((n, 2), dtype)) if noisy else None
        g0, g1, g2 = _evaluate(
            Interval(xc), Interval(sens), sens2, Interval(center), zero_noise, consts, layout, free
        )
        kp_c, kd_c = kp[:, None], kd[:, None]
        q, qd = Interval(xc[:, 0]), Interval(xc[:, 1])
        c0 = (q + qd * dt, qd + ((Interval(u) - qd * kd - q * kp) + g0) * dt)
        sq, sqd = Interval(sens[:, 0]), Interval(sens[:, 1])
        c1 = (sq + sqd * dt, sqd + ((sqd * (-kd_c) + sq * (-kp_c)) + g1[:, :p]) * dt)
        qq, qqd = Interval(sens2[:, 0]), Interval(sens2[:, 1])
        c2 = (
            qq + qqd * dt,
            qqd + ((qqd * (-kd_c[..., None]) + qq * (-kp_c[..., None])) + g2[:, :p, :p]) * dt,
        )
        new = [jnp.stack([c[0].mid(), c[1].mid()], axis=1) for c in (c0, c1, c2)]
        new[2] = 0.5 * (new[2] + jnp.swapaxes(new[2], -1, -2))  # exactly symmetric
        eps = [
            jnp.stack([c[0].radius_about(v[:, 0]), c[1].radius_about(v[:, 1])], axis=1)
            for c, v in zip((c0, c1, c2), new, strict=True)
        ]
        rounding = (
            eps[0]
            + _sum_up(eps[1] * d_rad[None, None, :], -1, p)
            + 0.5 * _sum_up(eps[2] * d_outer[None, None], (-2, -1), p * p)
        ) * (1.0 + 8 * _EPS)
        # --- the Hessian over the tube, on nested boxes s Z (radial segments) -----
        if carried:  # every block's centre value is used: the spread is about it
            centre_h = g2
        else:
            centre_h = Interval(
                jnp.zeros((n, m, m), dtype).at[:, :p, :p].set(g2.lo[:, :p, :p]),
                jnp.zeros((n, m, m), dtype).at[:, :p, :p].set(g2.hi[:, :p, :p]),
            )

        def segment_spread(s_hi, weight):
            if enclosure != "interval":  # affine or paired forms
                h_box = Interval(
                    *_evaluate_affine(
                        xc,
                        sens,
                        sens2,
                        center,
                        d_rad,
                        rhat,
                        eta_hat if noisy else None,
                        s_hi,
                        consts,
                        layout,
                        free,
                        paired=paired_variables(enclosure, layout, n, p, free, noisy) or False,
                    )
                )
            else:
                sd_box = d_box * s_hi  # rounded outward: holds s D for every s <= s_hi
                low, high = _poly_range(sens, sens2, sd_box.lo, sd_box.hi)
                tube = Interval(xc) + Interval(low, high) + Interval(-rhat, rhat) * s_hi
                grad_d = Interval(sens) + (Interval(sens2) * sd_box[None, None, None, :]).sum(-1)
                th_box = Interval(center) + sd_box
                noise_s = noise_box * s_hi if noisy else None
                _, _, h_box = _evaluate(tube, grad_d, sens2, th_box, noise_s, consts, layout, free)
            return (h_box - centre_h).mag() * weight

        spread = jnp.sum(jax.vmap(segment_spread)(seg_hi, seg_weight), axis=0)
        spread = spread * (1.0 + (segments + 4) * _EPS)
        parts = [d_rad, rhat.reshape(-1)] + ([eta_hat.reshape(-1)] if noisy else [])
        v_hat = jnp.concatenate(parts)
        quadratic = spread * v_hat[None, :, None] * v_hat[None, None, :]
        if carried:
            linear = g1.mag()[:, p + 2 * n :] * v_hat[None, p + 2 * n :]  # noise only
            extra, a_c, a_err, mixed = _carried_terms(
                g1, g2, v_hat, d_rad, gens_d, n, p, kp, kd, dt
            )
        else:
            linear = g1.mag()[:, p:] * v_hat[None, p:]
            extra = 0.0
        w = _sum_up(linear, -1, m) + _sum_up(quadratic, (-2, -1), m * m) + extra
        if diagnostics:  # w_blocks, then w_rest (the bounded terms, the radius over dt)
            rest = [jnp.broadcast_to(extra, (n,)), rounding[:, 1] / dt]
            blocks = jnp.concatenate([_w_blocks(linear, quadratic, n, p), jnp.stack(rest, -1)], -1)
        else:
            blocks = None
        w = w * (1.0 + _CHECK_MARGIN) + _TINY  # rounding (4 ulps) and the checker's margin
        injected = rounding.at[:, 1].add(up(dt * w) * scale)
        injected = injected * (1.0 + 4 * _EPS) + _TINY
        # --- the remainder bound of the next step -----------------------------
        if carried:
            gens, gens_d, rhat_next = _carry_generators(
                gens, gens_d, a_c, a_err, mixed, injected, rhat, d_rad, k, n, dt
            )
        else:
            dropped = buf[-1]
            buf = jnp.concatenate([injected[None], buf[:-1]], axis=0)
            tail_max = jnp.maximum(tail_max, jnp.max(dropped, axis=-1))
            rhat_next = (
                _sum_up(kernel * buf[:, :, None, :], (0, -1), 2 * steps)
                + up(tail * tail_max)[:, None]
            )
            rhat_next = rhat_next * (1.0 + 4 * _EPS) + _TINY
        carry = (new[0], new[1], new[2], buf, tail_max, rhat_next, gens, gens_d, k + 1)
        return carry, (new[0], new[1], new[2], injected, rhat_next, blocks, keep)

    x0 = traj.x_n[0]
    init = (
        x0,
        jnp.zeros((n, 2, p), dtype),
        jnp.zeros((n, 2, p, p), dtype),
        jnp.zeros((steps, n, 2), dtype),
        jnp.zeros((n,), dtype),
        jnp.zeros((n, 2), dtype),
        jnp.zeros((2 * n, columns), dtype),
        jnp.zeros((p, 2 * n, columns), dtype),
        jnp.asarray(0, jnp.int32),
    )
    _, (xs, ss, qs, injected, rhats, blocks, keeps) = jax.lax.scan(step, init, traj.u_d[:-1])
    cat = lambda first, rest: jnp.concatenate([first[None], rest], 0)  # noqa: E731
    state = cat(x0, xs)
    sens = cat(init[1], ss)
    sens2 = cat(init[2], qs)
    remainder = cat(init[5], rhats)
    low, high = _poly_range(sens, sens2, d_lo, d_hi)
    band = Interval(state) + Interval(low, high) + Interval(-remainder, remainder)
    band = band + Interval(*(jnp.broadcast_to(v, state.shape) for v in (noise_lo, noise_hi)))
    out = dict(
        state=state,
        sens=sens,
        sens2=sens2,
        injected=injected,
        remainder=remainder,
        lower=band.lo,
        upper=band.hi,
    )
    out |= dict(keep=keeps) if coulomb == "auto" else {}
    diag = dict(w_blocks=blocks[..., :10], w_rest=blocks[..., 10:]) if diagnostics else {}
    return out | diag


def _step_consts(
    xc,
    sens,
    sens2,
    center,
    d_lo,
    d_hi,
    rhat,
    u,
    nominal,
    kp,
    kd,
    fixed,
    matrix_fn=None,
    free=None,
    coulomb="taylor",
    coulomb_spread=COULOMB_RANGE_SPREAD,
):
    """The constants of one step's jets (``consts`` of :func:`_evaluate`): the nominal
    parameters, the command ``u`` (n,), the gains, ``fixed``; with ``matrix_fn`` the
    preconditioner at the centre state (:func:`_preconditioner`); with ``coulomb`` other
    than ``"taylor"`` the Coulomb signs' enclosure over the tube ``"sign"`` and ``"keep"``
    (:func:`_sign_range`). Shared by :func:`_certify_piece` and the benchmarks that
    re-evaluate one of its steps."""
    consts = dict(nominal=nominal, u=u, kp=kp, kd=kd, fixed=fixed)
    if matrix_fn is not None:
        consts["precond"] = _preconditioner(matrix_fn, xc, center, fixed, free)
    if coulomb != "taylor":
        auto = coulomb == "auto"
        *consts["sign"], keep = _sign_range(
            xc, sens, sens2, d_lo, d_hi, rhat, auto=auto, spread=coulomb_spread
        )
        consts["keep"] = keep
    return consts


def _sign_range(xc, sens, sens2, d_lo, d_hi, rhat, auto=False, spread=COULOMB_RANGE_SPREAD):
    """``(lo, hi, keep)`` (n,) each: an enclosure of the smooth Coulomb sign ``tanh(qd_j /
    v_s)`` over the tube of one step (``x_c + range(S d + 1/2 Q[d, d]) + [-r, r]``, every
    ``d`` of the piece), rounded outward, the same expression as the jets' (``qd * (1 /
    v_s)``); ``keep`` None. With ``auto`` only where the tube's velocities spread wider
    than ``spread`` (rad/s): elsewhere ``keep = 1`` and the enclosure is 0 (the
    sign keeps its expansion)."""
    low, high = _poly_range(sens, sens2, d_lo, d_hi)
    qd = Interval(xc[:, 1]) + Interval(low[:, 1], high[:, 1]) + Interval(-rhat[:, 1], rhat[:, 1])
    sign = tanh(qd * (1.0 / COULOMB_VELOCITY))
    if not auto:
        return sign.lo, sign.hi, None
    wide = (qd.hi - qd.lo) > spread
    zero = jnp.zeros_like(sign.lo)
    return jnp.where(wide, sign.lo, zero), jnp.where(wide, sign.hi, zero), jnp.where(wide, 0.0, 1.0)


def _carried_terms(g1, g2, v_hat, d_rad, gens_d, n, p, kp, kd, dt):
    """What ``propagate="carried"`` needs of one step's centre jets.

    The remainder obeys exactly ``R_(k+1) = A_c R_k + dt e2 (d' H_dR R_k + xi_k)``
    with ``A_c`` the piece centre's own linearised loop (``A`` plus ``dt e2 gv_R``)
    and ``H_dR`` the centre's ``d``-``R`` block of the Hessian: both are carried
    exactly (their float midpoints; the rest of their enclosures goes into
    ``a_err``). With ``R = R^0 + sum_b d_b R^b``, ``d' H_dR R`` splits into ``sum_b
    d_b H_b R^0`` (a coefficient of ``d_b``: carried into ``R^b``) and ``sum_(b, c)
    d_b d_c H_b R^c`` (bounded here). Also bounded here: ``1/2 z' H(centre) z`` over
    the blocks that are not carried (``R``-``R``, and every block with the noise).

    Returns:
        ``extra`` (n,): the bounded terms (added to ``w``); ``a_c`` (2n, 2n) floats;
        ``a_err`` (2n, 2n): ``|A_true - A_c|`` over the centre's enclosure;
        ``mixed`` (n, p, 2n): the float ``H_b`` rows (joint, d_b, R).
    """
    dtype = v_hat.dtype
    mid = g2.mid()
    mask = jnp.ones_like(mid).at[:, :p, : p + 2 * n].set(0.0).at[:, : p + 2 * n, :p].set(0.0)
    centre_abs = 0.5 * _sum_up(
        jnp.abs(mid) * mask * v_hat[None, :, None] * v_hat[None, None, :],
        (-2, -1),
        v_hat.shape[0] ** 2,
    )
    mixed = mid[:, :p, p : p + 2 * n]  # (n, p, 2n)
    through = jnp.einsum("ibs,csj->ibcj", mixed, gens_d)  # H_b R^c, per generator
    second = jnp.einsum("ibcj,b,c->i", jnp.abs(through), d_rad, d_rad)
    second = second * (1.0 + (2 * n + p * p + gens_d.shape[-1] + 8) * _EPS) + _TINY
    # A_c: the PD loop's exact reals plus dt gv_R, enclosed, then their midpoints
    joints, q_cols = jnp.arange(n), 2 * jnp.arange(n)
    own_p = Interval(kp) * (-dt)
    own_d = Interval(jnp.ones_like(kp)) - Interval(kd) * dt
    grad_r = g1[:, p : p + 2 * n] * dt  # (n, 2n)
    base_lo = jnp.zeros((n, 2 * n), dtype).at[joints, q_cols].set(own_p.lo)
    base_hi = jnp.zeros((n, 2 * n), dtype).at[joints, q_cols].set(own_p.hi)
    base_lo = base_lo.at[joints, q_cols + 1].set(own_d.lo)
    base_hi = base_hi.at[joints, q_cols + 1].set(own_d.hi)
    qd_rows = grad_r + Interval(base_lo, base_hi)
    qd_mid = qd_rows.mid()
    rows_q = jnp.zeros((n, 2 * n), dtype).at[joints, q_cols].set(1.0)
    rows_q = rows_q.at[joints, q_cols + 1].set(dt)  # q + dt qd: exact reals
    a_c = jnp.zeros((2 * n, 2 * n), dtype).at[0::2].set(rows_q).at[1::2].set(qd_mid)
    a_err = jnp.zeros((2 * n, 2 * n), dtype).at[1::2].set(qd_rows.radius_about(qd_mid))
    return centre_abs + second, a_c, a_err, mixed


def _carry_generators(gens, gens_d, a_c, a_err, mixed, injected, rhat, d_rad, k, n, dt):
    """One step of the carried remainder ``R = G eps + sum_b d_b G^b eps``.

    ``G <- A_c G``, ``G^b <- A_c G^b + dt e2 H_b G``, then ``2n`` new generators, one
    per state row, whose size is the step's bounded input: ``injected`` (the Lagrange
    and bounded terms, the Taylor coefficients' rounding), ``a_err |R_k|`` and the
    rounding of the two products (``gamma_k |A_c| |G|`` and alike, added as bounds).
    Returns the new ``(gens, gens_d, rhat)`` with ``|R_(k+1)| <= rhat``.
    """
    size = 2 * n
    gamma = (size + 8) * _EPS
    abs_rows = jnp.sum(jnp.abs(gens), axis=-1)  # (2n,) sum_j |G_sj|
    abs_rows_d = jnp.sum(jnp.abs(gens_d), axis=-1)  # (p, 2n)
    new_gens = a_c @ gens
    pushed = jnp.einsum("ibs,sj->bij", mixed, gens) * dt  # (p, n, columns)
    new_gens_d = jnp.einsum("st,btj->bsj", a_c, gens_d)
    new_gens_d = new_gens_d.at[:, 1::2].add(pushed)
    err = gamma * (jnp.abs(a_c) @ abs_rows)
    err_d = gamma * (jnp.einsum("st,bt->bs", jnp.abs(a_c), abs_rows_d))
    err_d = err_d.at[:, 1::2].add(gamma * dt * jnp.einsum("ibs,s->bi", jnp.abs(mixed), abs_rows))
    columns = gens.shape[-1]
    err = err * (1.0 + gamma) + jnp.sum(err_d * d_rad[:, None], axis=0) * (1.0 + gamma)
    err = err + (a_err @ rhat.reshape(-1)) * (1.0 + gamma)
    err = err * (1.0 + (columns + 8) * _EPS) + _TINY
    box = injected.reshape(-1) * (1.0 + 4 * _EPS) + err
    block = jnp.diag(box)  # (2n, 2n): one generator per state row
    new_gens = jax.lax.dynamic_update_slice(new_gens, block, (jnp.int32(0), k * size))
    rows = jnp.sum(jnp.abs(new_gens), axis=-1)
    rows_d = jnp.sum(jnp.abs(new_gens_d), axis=-1)  # (p, 2n)
    total = rows + jnp.sum(rows_d * d_rad[:, None], axis=0)
    rhat_next = total * (1.0 + (columns + gens_d.shape[0] + 8) * _EPS) + _TINY
    return new_gens, new_gens_d, rhat_next.reshape(n, 2)


def _w_blocks(linear, quadratic, n, p):
    """Where ``w_k`` comes from (diagnostics, not part of the certificate): (n, 10).

    The first-order terms in ``(R, eta)``, then the quadratic term by blocks of
    masses, lengths and ``(R, eta)`` (``th = (m_1..m_n, l_1..l_n)`` on the planar
    arm), row-major: mm, ml, mx, lm, ll, lx, xm, xl, xx.
    """
    edges = (0, n, p, quadratic.shape[-1])
    spans = list(zip(edges[:-1], edges[1:], strict=True))
    return jnp.stack(
        [jnp.sum(linear, axis=-1)]
        + [
            jnp.sum(quadratic[:, a0:a1, b0:b1], axis=(-2, -1))
            for a0, a1 in spans
            for b0, b1 in spans
        ],
        axis=-1,
    )


@functools.partial(
    jax.jit,
    static_argnames=(
        "noisy",
        "kernel_steps",
        "segments",
        "diagnostics",
        "enclosure",
        "propagate",
        "layout",
        "free",
        "solve",
        "coulomb",
        "coulomb_spread",
    ),
)
def _certify(
    traj,
    params,
    centers,
    los,
    his,
    noise_lo,
    noise_hi,
    scale,
    *,
    noisy,
    kernel_steps,
    segments,
    diagnostics=False,
    enclosure="interval",
    propagate="kernel",
    layout=None,
    free=None,
    fixed=None,
    solve="articulated",
    coulomb="taylor",
    coulomb_spread=COULOMB_RANGE_SPREAD,
):
    kernel, tail = _kernel(traj.kp, traj.kd, traj.dt, kernel_steps)
    run = functools.partial(
        _certify_piece,
        traj=traj,
        nominal=params.nominal,
        noise_lo=noise_lo,
        noise_hi=noise_hi,
        kernel=kernel,
        tail=tail,
        noisy=noisy,
        scale=scale,
        segments=segments,
        diagnostics=diagnostics,
        enclosure=enclosure,
        propagate=propagate,
        layout=layout,
        free=free,
        fixed=fixed,
        matrix_fn=solve_matrix(params) if solve == "preconditioned" else None,
        axis_name=_PIECES,
        coulomb=coulomb,
        coulomb_spread=coulomb_spread,
    )
    n, p = traj.n_joints, params.n_params
    if enclosure != "interval":
        precond, ranged = solve == "preconditioned", coulomb != "taylor" and coulomb
        paired = paired_variables(enclosure, layout, n, centers.shape[1], free, noisy)
        batch = _affine_batch(layout, n, p, centers.shape[1], noisy, precond, ranged, paired)
    else:
        batch = centers.shape[0]
    count = centers.shape[0]
    batch = min(batch, count)
    groups = -(-count // batch)
    together = jax.vmap(run, axis_name=_PIECES)
    if groups == 1:
        pieces = together(centers, los, his)
    else:  # pieces in batches: the affine jets' buffers are large
        pad = groups * batch - count  # copies of the last piece, dropped below
        boxes = [
            jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)]).reshape(groups, batch, -1)
            for a in (centers, los, his)
        ]
        pieces = jax.lax.map(lambda a: together(*a), tuple(boxes))
        pieces = jax.tree_util.tree_map(lambda v: v.reshape((-1,) + v.shape[2:])[:count], pieces)
    return pieces, kernel, tail


def _affine_batch(layout, n, p, variables, noisy, precond=False, ranged=False, paired=None):
    """How many pieces to evaluate together on affine jets: as many as keep the tape's
    buffers (live rows x packed Hessian, gradient and value x (symbols + 2) floats) within
    :data:`_AFFINE_BUFFER`, at least one (``paired``: :class:`rmijax._affine.PairedForm`
    jets pairing these variables, :func:`paired_variables`; ``pair_count(m, len(paired))``
    symbols). Measured on this 2-core CPU (the Intel Xeon
    host, before the buffers held the live rows only): the two-joint arm's 2 s run (16
    pieces, 0.5 MB each) took 5.3 / 4.7 / 4.4 / 7.4 / 8.6 s once compiled in batches of 1
    / 2 / 4 / 8 / 16, one 4-link evaluation (9 MB) 13.8 ms alone and 20.8 ms per piece in
    batches of 16: larger batches leave the cache."""
    (ops, args, _), outputs = _perturbation_tape(layout, n, p, noisy, precond, ranged)
    m = variables + 2 * n + (2 * n if noisy else 0)  # (d, R[, eta]): uncertain ``d`` only
    rows = _slots(ops, args, _tape_leaves(n, p, noisy, precond, ranged), outputs)[3]
    symbols = m if paired is None else pair_count(m, len(paired))
    per_piece = rows * (m * (m + 1) // 2 + m + 1) * (symbols + 2) * 8
    return max(1, _AFFINE_BUFFER // per_piece)


# --------------------------------------------------------------------------
# Splitting the box
# --------------------------------------------------------------------------


def _pieces(params, splits):
    """Pieces of the box: a product grid, ``splits[b]`` equal parts along parameter ``b``.

    Returns ``(centers, lo, hi)``, each (P, p). A single piece is expanded at the
    nominal (where ``gv`` vanishes identically); split pieces at their centres.
    """
    lo, hi, nominal = (np.asarray(a, np.float64) for a in (params.lo, params.hi, params.nominal))
    p = lo.shape[0]
    if all(s == 1 for s in splits):
        return nominal[None], lo[None], hi[None]
    cuts = [np.linspace(lo[b], hi[b], splits[b] + 1) for b in range(p)]
    for b in range(p):  # ends exactly at the box's bounds
        cuts[b][0], cuts[b][-1] = lo[b], hi[b]
    grid = np.stack(np.meshgrid(*[np.arange(s) for s in splits], indexing="ij"), -1)
    grid = grid.reshape(-1, p)
    piece_lo = np.stack([cuts[b][grid[:, b]] for b in range(p)], -1)
    piece_hi = np.stack([cuts[b][grid[:, b] + 1] for b in range(p)], -1)
    centers = 0.5 * (piece_lo + piece_hi)
    return centers, piece_lo, piece_hi


def _split_counts(params, splits):
    p = params.n_params
    chain = not isinstance(params.model.structure, PlanarPointMass)
    if splits is None:
        if chain:
            splits = 1
        else:
            splits = 4 if params.n_joints <= 2 else 3 if params.n_joints <= 4 else 2
    if isinstance(splits, (int, np.integer)) and not isinstance(splits, bool):
        if splits < 1:
            raise ValueError(f"splits must be >= 1, got {splits}")
        if splits == 1:
            return (1,) * p
        # split the masses (the parameters gv is most non-linear in) into `splits` parts:
        # the planar arm's n masses; a chain's uncertain mass scales and payload
        n = params.n_joints
        if chain:
            units = n + ("payload_mass" in params.model.param_names)
            uncertain = np.asarray(params.hi) > np.asarray(params.lo)
            return tuple(int(splits) if b < units and uncertain[b] else 1 for b in range(p))
        return tuple(int(splits) if b < n else 1 for b in range(p))
    if isinstance(splits, dict):  # parts per named parameter, 1 for the others
        names = tuple(params.model.param_names)
        unknown = [name for name in splits if name not in names]
        if unknown:
            raise ValueError(
                f"splits names unknown parameters {unknown}: use names from "
                f"params.model.param_names, {list(names)}"
            )
        splits = [splits.get(name, 1) for name in names]
    counts = tuple(int(s) for s in splits)
    if len(counts) != p or any(s < 1 for s in counts):
        raise ValueError(
            f"splits must be an int >= 1, {p} ints >= 1 or a dict of parameter names to "
            f"ints >= 1, got {splits!r}"
        )
    return counts


def split_ranking(traj: Trajectory, params: UncertainRobot, splits=1) -> list[tuple[str, float]]:
    """The uncertain parameters, ranked by how much their range moves the nominal loop.

    A hint for ``splits``, not part of any certificate. For parameter ``b`` the score
    is ``r_b max_k max_i sum_j |d/dth_b d gv_i / d x_j|``: the half-width ``r_b`` of a
    piece's range (the range over its parts in ``splits``) times the largest row sum of
    the derivative of ``gv``'s state Jacobian along the desired run ``x_n(k)``, at the
    nominal parameters (rad/s^2 per rad or rad/s).
    This is how far the parameter's range can move the closed loop's state Jacobian
    away from the nominal one, the term that makes the remainder grow or stop
    contracting (e.g. a joint's Coulomb friction range where the joint is at rest and
    the smooth sign is steepest, acting through ``M^-1``'s coupling on light joints).

    Args:
        traj: the desired motion, gains and step.
        params: the robot and its box (float64).
        splits: the cuts already made, as :func:`certified_bounds` takes them.

    Returns:
        ``[(name, score), ...]`` for the parameters with ``lo < hi``, largest score first.
    """
    check_types(traj, params)
    if params.n_joints != traj.n_joints:
        raise ValueError(
            f"traj has {traj.n_joints} joints but params describes a {params.n_joints}-joint robot"
        )
    rows = _mixed_rows(traj, params)
    counts = np.asarray(_split_counts(params, splits))
    radius = 0.5 * (np.asarray(params.hi) - np.asarray(params.lo))
    score = radius / counts * rows
    names = params.model.param_names
    ranked = sorted(np.flatnonzero(radius > 0), key=lambda b: -score[b])
    return [(names[b], float(score[b])) for b in ranked]


def _mixed_rows(traj, params):
    """(p,) ``max_k max_i sum_j |d/dth_b d gv_i / d x_j|`` along ``x_n`` at the nominal
    parameters: how far a unit of parameter ``b`` moves the closed loop's state Jacobian
    (:func:`split_ranking`)."""
    model, nominal = params.model, params.nominal
    kp, kd = traj.kp, traj.kd

    def gv(x, th, u):
        return coupled_perturbation(model, th, nominal, x[:, 0], x[:, 1], u, kp, kd)

    mixed = jax.jit(jax.vmap(jax.jacfwd(jax.jacfwd(gv, 0), 1), (0, None, 0)))
    jac = np.abs(np.asarray(mixed(traj.x_n[:-1], nominal, traj.u_d[:-1])))  # (T, n, n, 2, p)
    return jac.sum(axis=(2, 3)).max(axis=(0, 1))


def _bisect(lo, hi, weights):
    """Two halves of the piece ``[lo, hi]``, cut across the parameter with the largest
    ``weights * (hi - lo)`` (the widest relative range where every weight is 0)."""
    width = hi - lo
    score = weights * width
    if not np.any(score > 0):
        score = np.where(width > 0, 1.0, 0.0)
    b = int(np.argmax(score))
    cut = 0.5 * (lo[b] + hi[b])
    left_hi, right_lo = hi.copy(), lo.copy()
    left_hi[b], right_lo[b] = cut, cut
    return (lo, left_hi), (right_lo, hi)


def _looseness(piece):
    """How loose one finished piece's remainder is: the largest over outputs of the median
    over steps ``k >= 1`` of its remainder radius over the rest of its band's half-width
    (Taylor polynomial and noise); ``piece`` is its arrays (no leading piece axis)."""
    radius = piece["remainder"][1:]  # (T, n, 2)
    rest = 0.5 * (piece["upper"] - piece["lower"])[1:] - radius
    # an output with no remainder to speak of is not loose, even with no range
    ratio = np.where(radius > _NEGLIGIBLE, radius / np.maximum(rest, _TINY), 0.0)
    return float(np.max(np.median(ratio, axis=0)))


def _in_chunks(certify, pending, chunk):
    """``certify`` on the boxes ``pending`` (a list of ``(center, lo, hi)``), ``chunk`` at
    a time, the last chunk padded with copies of its last box: every call has the same
    shapes, so one compilation serves every round. The pieces' arrays, numpy, leading
    axis ``len(pending)``."""
    outs = []
    for start in range(0, len(pending), chunk):
        part = pending[start : start + chunk]
        part = part + [part[-1]] * (chunk - len(part))
        boxes = tuple(np.stack([box[i] for box in part]) for i in range(3))
        outs.append({key: np.asarray(value) for key, value in certify(boxes).items()})
    return {key: np.concatenate([out[key] for out in outs])[: len(pending)] for key in outs[0]}


def _auto_boxes(traj, params, certify, max_pieces, refine, chunk=1):
    """Adaptive bisection of the box (``splits="auto"``): ``(centers, los, his, pieces)``.

    Starts from the whole box (expanded at the nominal); each round certifies the
    pending pieces, ``chunk`` at a time (:func:`_in_chunks`: one compilation for every
    round), and cuts in two, across the parameter of :func:`_bisect` (weighted by
    :func:`_mixed_rows`), every piece whose band is not finite; in a round where every
    piece is finite, while ``max_pieces`` allows, the pieces whose
    :func:`_looseness` is above ``refine`` (worst first). ``certify(boxes)`` maps
    ``(centers, los, his)`` (chunk, p) to the pieces' arrays (leading axis chunk).
    Raises :class:`DivergedError` when a piece still diverges and cutting it would pass
    ``max_pieces``.
    """
    lo, hi = np.asarray(params.lo, np.float64), np.asarray(params.hi, np.float64)
    weights = _mixed_rows(traj, params)
    pending = [(np.asarray(params.nominal, np.float64), lo, hi)]
    done = []  # (center, lo, hi, pieces' arrays of this piece, looseness)
    while pending:
        pieces = _in_chunks(certify, pending, chunk)
        diverged = []
        for i, box in enumerate(pending):
            arrays = {key: value[i] for key, value in pieces.items()}
            where = _checks.first_non_finite(arrays["upper"], arrays["lower"])
            if where is not None:
                diverged.append((box, where))
            else:
                done.append((*box, arrays, _looseness(arrays)))
        room = max_pieces - len(done) - 2 * len(diverged)
        if diverged and room < 0:
            box, where = diverged[0]
            raise DivergedError.at(
                where,
                f"certified bounds are not finite (step {where[0]}, joint {where[1]} "
                f"{DivergedError.SENSORS[where[2]]}) on {len(diverged)} of "
                f"{len(done) + len(diverged)} pieces cut by bisection, and cutting them "
                f"again would pass max_pieces={max_pieces}. Raise max_pieces, narrow the "
                "parameter box or use stiffer gains.",
            )
        cut = [box for box, _ in diverged]
        if not diverged:  # finite first, then tight: the loosest while room allows
            loose = [j for j, entry in enumerate(done) if entry[4] > refine]
            chosen = sorted(loose, key=lambda j: -done[j][4])[:room]
            cut += [done[j][:3] for j in chosen]
            skip = set(chosen)
            done = [entry for j, entry in enumerate(done) if j not in skip]
        pending = [
            (0.5 * (half_lo + half_hi), half_lo, half_hi)
            for _, piece_lo, piece_hi in cut
            for half_lo, half_hi in _bisect(piece_lo, piece_hi, weights)
        ]
    centers, los, his = (np.stack([entry[i] for entry in done]) for i in range(3))
    pieces = {key: np.stack([entry[3][key] for entry in done]) for key in done[0][3]}
    return centers, los, his, pieces


def _free_parameters(params):
    """The indices of ``params``' uncertain parameters (``hi > lo``), the variables of
    the jets; None when every parameter is uncertain (nothing to fold). The certain
    ones are constants of the jets at their value."""
    lo, hi = np.asarray(params.lo), np.asarray(params.hi)
    free = tuple(int(b) for b in np.flatnonzero(hi > lo))
    return None if len(free) == lo.size else free


def _certify_box(
    traj,
    params,
    noise_lo,
    noise_hi,
    splits,
    kernel_steps=KERNEL_STEPS,
    segments=3,
    remainder_scale=1.0,
    diagnostics=False,
    enclosure="interval",
    propagate="kernel",
    solve="articulated",
    max_pieces=None,
    refine=None,
    coulomb="taylor",
    coulomb_spread=COULOMB_RANGE_SPREAD,
):
    """Split the box and certify every piece: ``(centers, los, his, pieces, kernel, tail)``.

    Inputs as checked by :func:`certified_bounds` (noise bounds (n, 2) float64);
    ``pieces`` holds each piece's arrays with a leading (P,) axis, and ``w_blocks``, ``w_rest``
    with ``diagnostics``.
    """
    noisy = bool(np.any(np.asarray(noise_lo) != 0) or np.any(np.asarray(noise_hi) != 0))
    layout = _layout(params)
    lo = np.asarray(params.lo)
    free = _free_parameters(params)
    fixed = None if free is None else jnp.asarray(lo)  # the certain ones' values
    kernels = []  # the kernel and tail, the same on every call

    def certify(boxes):
        variables = boxes if free is None else tuple(a[:, list(free)] for a in boxes)
        pieces, kernel, tail = _certify(
            traj,
            params,
            *(jnp.asarray(a) for a in variables),
            jnp.asarray(noise_lo),
            jnp.asarray(noise_hi),
            jnp.asarray(remainder_scale, jnp.asarray(noise_lo).dtype),
            noisy=noisy,
            kernel_steps=kernel_steps,
            segments=segments,
            diagnostics=diagnostics,
            enclosure=enclosure,
            propagate=propagate,
            layout=layout,
            free=free,
            fixed=fixed,
            solve=solve,
            coulomb=coulomb,
            coulomb_spread=coulomb_spread,
        )
        if free is not None:  # back to every parameter: the certain ones' coefficients are 0
            rows = np.asarray(free, dtype=np.int32)
            p = lo.size
            sens, sens2 = pieces["sens"], pieces["sens2"]
            full = jnp.zeros(sens.shape[:-1] + (p,), sens.dtype).at[..., rows].set(sens)
            full2 = jnp.zeros(sens2.shape[:-2] + (p, p), sens2.dtype)
            full2 = full2.at[..., rows[:, None], rows[None, :]].set(sens2)
            pieces = pieces | dict(sens=full, sens2=full2)
        kernels[:] = [kernel, tail]
        return pieces

    if isinstance(splits, str):  # "auto", as certified_bounds checked
        if enclosure != "interval":  # the batch that keeps the affine buffers in cache
            variables = lo.size if free is None else len(free)
            precond = solve == "preconditioned"
            ranged = coulomb != "taylor" and coulomb
            paired = paired_variables(enclosure, layout, traj.n_joints, variables, free, noisy)
            chunk = _affine_batch(
                layout, traj.n_joints, lo.size, variables, noisy, precond, ranged, paired
            )
        else:
            chunk = AUTO_CHUNK
        *boxes, pieces = _auto_boxes(traj, params, certify, max_pieces, refine, chunk)
        pieces = {key: jnp.asarray(value) for key, value in pieces.items()}
    else:
        boxes = _pieces(params, _split_counts(params, splits))  # (centers, los, his)
        pieces = certify(boxes)
    return *boxes, pieces, *kernels


# --------------------------------------------------------------------------
# Public entry point
# --------------------------------------------------------------------------


def certified_bounds(
    traj: Trajectory,
    params: UncertainRobot,
    *,
    mode: str = "coupled",
    window=None,
    noise_lo=0.0,
    noise_hi=0.0,
    splits=None,
    kernel_steps: int = KERNEL_STEPS,
    segments: int = 3,
    remainder_scale: float = 1.0,
    enclosure: str | None = None,
    propagate: str | None = None,
    solve: str | None = None,
    max_pieces: int = AUTO_MAX_PIECES,
    refine: float = AUTO_REFINE,
    coulomb: str = "auto",
    coulomb_spread: float = COULOMB_RANGE_SPREAD,
) -> tuple[Bounds, Certificate]:
    """Bands proven to contain the output of every constant-parameter run, and their certificate.

    See the module docstring for what is certified and how. The whole horizon
    from ``x(0) = x_d(0)`` (no window restart).

    Args:
        traj: the desired motion, gains and step.
        params: a planar point-mass arm or a serial chain of :func:`rmijax.load_robot`,
            with its parameter box.
        mode: must be ``"coupled"`` (the true plant).
        window: must be None (the certificate covers the whole run).
        noise_lo, noise_hi: sensor noise bounds, scalar, (2,) or (n, 2): added to
            the band, and their effect through the controller is enclosed.
        splits: 1 (no split), an int ``s`` (each mass range in ``s`` equal parts:
            ``s^n`` pieces; a chain's uncertain mass scales and payload), ``p`` ints
            (parts per parameter), a dict of parts per parameter name (others 1, e.g.
            ``{"coulomb[joint4]": 2}``; names from ``params.model.param_names``), or
            None: on the planar arm 4 up to two joints, 3 up to four (81 pieces at four
            joints: fewer diverge with the default enclosure), 2 above; on a chain 1.
            Or ``"auto"``: adaptive bisection from the whole box, each piece whose band
            is not finite or whose remainder is loose (see ``refine``) cut in two across
            the parameter that moves the nominal loop most over the piece's range
            (:func:`split_ranking`'s score), up to ``max_pieces`` pieces.
            The band is the union of the pieces' bands.
        kernel_steps: ``M``, powers of ``A`` applied exactly to the remainder.
        segments: ``J``, radial segments of the Lagrange remainder: the Hessian
            is enclosed over the boxes ``(j / J) Z``, weighted by
            ``int (1 - s) ds`` over each segment (more: tighter and slower).
        remainder_scale: multiplies the remainder's input; anything but 1 voids
            the guarantee (for mutation tests only).
        enclosure: how the Hessian of the perturbation is enclosed over the tube:
            ``"interval"`` (interval 2-jets) or ``"affine"`` (affine forms in the
            parameters and the remainder, rounding bounded: tighter, about 2x slower
            at two joints, needed from three) or ``"paired"`` (affine forms that also
            carry every product of two variables in a symbol of its own,
            :class:`rmijax._affine.PairedForm`: tighter again, ``m (m + 1) / 2`` more
            symbols for ``m`` variables, so slower and larger) or ``"paired_inertia"``
            (pair symbols for the parameters that enter ``M`` and the remainder only, not
            for friction and noise: on the UR5e's box 221 symbols instead of 527,
            :func:`paired_variables`). None: interval up to two joints, affine above.
        propagate: how the remainder bound is carried from step to step:
            ``"kernel"`` (the nominal loop's powers, every feedback of the
            remainder on itself in absolute value) or ``"carried"`` (generators
            through each piece's own linearised loop, the parameters' effect on that
            loop a coefficient: bounded at four joints where ``"kernel"`` diverges).
            None: kernel up to two joints, carried above. The certificate checker
            re-verifies every pair.
        solve: how ``M gv = f`` is solved on the jets: ``"articulated"`` (eliminating
            from the tip, the pivots the articulated inertias) or ``"preconditioned"``
            (``P M gv = P f`` by elimination, ``P`` the float inverse of ``M`` at each
            step's centre: pivots near 1, so the enclosures keep the parameters'
            dependence over wide boxes; any ``P`` gives the same ``gv``, so ``P`` needs
            no proof). None: articulated on the planar arm, preconditioned on a chain
            (where an articulated pivot's enclosure held 0 over the Panda's default
            masses and payload).
        max_pieces: with ``splits="auto"``, the most pieces to cut the box into: a piece
            still diverging beyond it raises :class:`DivergedError`; loose pieces stay
            as they are.
        refine: with ``splits="auto"``, once every piece is finite, a piece whose
            remainder radius exceeds ``refine`` times the rest of its band's half-width
            (the Taylor polynomial's range and the noise) at the median step of some
            output is cut while ``max_pieces`` allows, largest first (a tightness
            target: the remainder is what a band holds beyond the polynomial's range).
        coulomb: how the Coulomb ranges of a chain enter the jets: ``"taylor"`` (the
            smooth sign ``tanh(qd / v_s)`` expanded with the rest), ``"range"`` (each
            step, the Coulomb error moves an enclosure of the sign over that step's
            tube: a bounded input, no curvature; near rest, where the tube's velocities
            spread wider than ``v_s``, the Taylor expansion's remainder diverges on the
            shipped arms' default box) or ``"auto"`` (per joint and step: the range
            where the tube's velocities spread wider than
            :data:`COULOMB_RANGE_SPREAD`, the expansion elsewhere; the default: on the
            shipped arms' friction boxes over the first second of their move it was the
            tightest of the three or equal to the tightest, and it alone certified all
            three, ``docs/methods.md``). No effect without uncertain Coulomb ranges (the
            certificate then records ``"taylor"``).
        coulomb_spread: with ``coulomb="auto"``, the spread of a step's tube velocities
            (rad/s, > 0) above which a joint's sign is bounded by its range. A choice:
            sound at any value (the certificate's ``keep`` records it per joint and step,
            and the checker follows it); it moves only the band's width.

    Returns:
        ``(bounds, certificate)``: :class:`~rmijax.methods.base.Bounds` with
        ``lower``, ``upper``, ``nominal``, ``crossed`` (T+1, n, 2), and the
        :class:`Certificate`.

    Raises:
        NotImplementedError: a model other than the planar point-mass arm or a loaded
            serial chain.
        ValueError: not float64, ``per_joint`` mode, a window, bad splits.
        DivergedError: the remainder bound is not finite (box too wide or the
            loop not contracting over it).
    """
    check_types(traj, params)
    if mode != "coupled":
        raise ValueError(
            f"certified_bounds needs mode='coupled', got {mode!r}: it certifies the true "
            "coupled plant with constant parameters"
        )
    if window is not None:
        raise ValueError(
            "certified_bounds has no window: it certifies the whole run from x(0) = x_d(0)"
        )
    _layout(params)  # refuses a model it cannot evaluate, before any other check
    if params.n_joints != traj.n_joints:
        raise ValueError(
            f"traj has {traj.n_joints} joints but params describes a {params.n_joints}-joint robot"
        )
    dtype = jnp.result_type(traj.dtype, params.dtype)
    if dtype != jnp.float64:
        raise ValueError(
            f"certified_bounds works in float64 (rounding is bounded for it), got {dtype}; "
            'enable it with jax.config.update("jax_enable_x64", True) and pass float64 arrays'
        )
    _checks.check_stable(traj.kp, traj.kd, traj.dt)
    n = traj.n_joints
    lo_noise, hi_noise = _checks.noise_interval(noise_lo, noise_hi, n, dtype)
    lo_noise = jnp.broadcast_to(lo_noise, (n, 2))
    hi_noise = jnp.broadcast_to(hi_noise, (n, 2))
    kernel_steps = _checks.positive_int("kernel_steps", kernel_steps, "steps")
    segments = _checks.positive_int("segments", segments)
    enclosure = _choice("enclosure", enclosure, ENCLOSURES, n)
    propagate = _choice("propagate", propagate, ("kernel", "carried"), n)
    solve = _solve_choice(solve, params)
    coulomb = _coulomb_choice(coulomb, params)
    coulomb_spread = _checks.real("coulomb_spread", coulomb_spread, positive=True, unit="rad/s")
    if isinstance(splits, str):
        if splits != "auto":
            raise ValueError(f"splits must be a count, counts, a dict or 'auto', got {splits!r}")
        max_pieces = _checks.positive_int("max_pieces", max_pieces, "pieces")
        refine = _checks.real("refine", refine, positive=True)
    centers, los, his, pieces, kernel, tail = _certify_box(
        traj,
        params,
        lo_noise,
        hi_noise,
        splits,
        kernel_steps,
        segments,
        remainder_scale,
        enclosure=enclosure,
        propagate=propagate,
        solve=solve,
        max_pieces=max_pieces,
        refine=refine,
        coulomb=coulomb,
        coulomb_spread=coulomb_spread,
    )
    lower = jnp.min(pieces["lower"], axis=0)
    upper = jnp.max(pieces["upper"], axis=0)
    where = _checks.first_non_finite(upper, lower)
    if where is not None:
        step, joint, sensor = where
        counts = _split_counts(params, splits)
        ranked = split_ranking(traj, params, counts)
        hint = "splits=..."
        if ranked:
            name = ranked[0][0]
            parts = 2 * counts[params.model.param_names.index(name)]
            hint = (
                f"e.g. {name!r} in {parts} parts: the range that moves the nominal loop "
                "most per piece, see split_ranking"
            )
        uncertain = np.asarray(params.hi) > np.asarray(params.lo)
        names = params.model.param_names
        note = ""
        ranges = np.asarray(names)[uncertain]
        if coulomb == "taylor" and any(name.startswith("coulomb[") for name in ranges):
            note = (
                " With Coulomb friction uncertain: its smooth sign is steep within "
                f"{COULOMB_VELOCITY} rad/s of rest, and where the other ranges spread the "
                "joint velocities wider than that its curvature makes the remainder diverge "
                "(the shipped arms' default box within 0.1 s; docs/methods.md, 'Why the "
                "default box diverges'): leave coulomb at its default 'auto' or pass "
                "coulomb='range' (the sign bounded by its range over the tube where it "
                "spreads wide, or everywhere), or narrow the Coulomb or the mass and "
                "payload ranges."
            )
        raise DivergedError.at(
            where,
            f"certified bounds are not finite (step {step}, joint {joint} "
            f"{DivergedError.SENSORS[sensor]}): the remainder bound diverged. Narrow the "
            f"parameter box, split it ({hint}) or use stiffer gains.{note}",
        )
    bounds = Bounds(lower=lower, upper=upper, nominal=traj.x_n, crossed=upper < lower, dt=traj.dt)
    certificate = Certificate(
        center=jnp.asarray(centers),
        lo=jnp.asarray(los),
        hi=jnp.asarray(his),
        state=pieces["state"],
        sens=pieces["sens"],
        sens2=pieces["sens2"],
        injected=pieces["injected"],
        remainder=pieces["remainder"],
        kernel=kernel,
        tail=tail,
        lower=lower,
        upper=upper,
        noise_lo=lo_noise,
        noise_hi=hi_noise,
        segments=segments,
        enclosure=enclosure,
        propagate=propagate,
        solve=solve,
        coulomb=coulomb,
        keep=pieces.get("keep"),
    )
    return bounds, certificate


def _choice(name, value, options, n_joints):
    """``value`` if it is one of ``options``; None: the first up to two joints, else the
    second."""
    if value is None:
        return options[0] if n_joints <= 2 else options[1]
    if value not in options:
        raise ValueError(f"{name} must be one of {options} or None, got {value!r}")
    return value


def _coulomb_choice(coulomb, params):
    """``coulomb`` if it is ``"taylor"``, ``"range"`` or ``"auto"``; ``"taylor"`` where the
    model has no Coulomb parameters (nothing to bound: the certificate records what was
    done)."""
    if coulomb not in COULOMB_MODES:
        raise ValueError(f"coulomb must be one of {COULOMB_MODES}, got {coulomb!r}")
    layout = _layout(params)
    if layout is None or "coulomb" not in layout.friction:
        return "taylor"
    return coulomb


def _solve_choice(solve, params):
    """``solve`` if it is one of the two solves; None: articulated on the planar arm
    (unchanged to the bit), preconditioned on a chain (where an articulated pivot's
    enclosure held 0 over the Panda's default box)."""
    if solve is None:
        return "articulated" if _layout(params) is None else "preconditioned"
    if solve not in ("articulated", "preconditioned"):
        raise ValueError(f"solve must be 'articulated', 'preconditioned' or None, got {solve!r}")
    return solve
