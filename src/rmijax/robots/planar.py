"""The paper's planar serial arm of point masses (SPEC section 1) and its presets.

Parameters are ``th = (m_1..m_n, l_1..l_n)`` (kg, m). The model declares its
structure (:class:`~rmijax.robots.structure.PlanarPointMass`), from which the
RMI engine takes the arm's exact factored corner search.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from rmijax import _checks
from rmijax._linalg import ldl_factor, ldl_solve
from rmijax.robots.box import UncertainRobot, uncertain_robot
from rmijax.robots.model import GRAVITY, RobotModel
from rmijax.robots.structure import PlanarPointMass

__all__ = [
    "paper_arm2",
    "paper_pendulum",
    "planar_arm",
    "planar_arm_model",
    "preset_arm",
]


# --------------------------------------------------------------------------
# Planar serial arm of point masses (SPEC section 1)
# --------------------------------------------------------------------------


def _tail_sum(z, axis=0):
    """``(S' z)_i = sum_{a >= i} z_a`` along ``axis``."""
    return jnp.flip(jnp.cumsum(jnp.flip(z, axis), axis), axis)


def _planar_split(q, th):
    n = q.shape[-1]
    return th[:n], th[n:]


def _planar_weights(masses, lengths):
    """``W_ab = mu_max(a,b) l_a l_b`` with ``mu_a = sum_{k >= a} m_k``; also ``mu``."""
    n = masses.shape[0]
    mu = _tail_sum(masses)
    index = jnp.arange(n)
    mu_max = mu[jnp.maximum(index[:, None], index[None, :])]
    return mu_max * lengths[:, None] * lengths[None, :], mu


def planar_mass_matrix(q, th):
    """Mass matrix of the planar point-mass arm, ``M = S' (W o cos(phi_a - phi_b)) S``.

    Args:
        q: joint angles (n,), rad; ``q_1`` from the horizontal, others relative.
        th: parameters (2n,) = masses (kg) then lengths (m).

    Returns:
        ``M`` (n, n) in kg m^2.
    """
    masses, lengths = _planar_split(q, th)
    weights, _ = _planar_weights(masses, lengths)
    phi = jnp.cumsum(q)
    inertia_abs = weights * jnp.cos(phi[:, None] - phi[None, :])
    mass = _tail_sum(_tail_sum(inertia_abs, 0), 1)
    return 0.5 * (mass + mass.T)  # exactly symmetric (the two tail sums round differently)


def planar_bias(q, qd, th):
    """Bias forces ``h = S' (c + G_phi)`` of the planar point-mass arm, (n,) in N m."""
    masses, lengths = _planar_split(q, th)
    weights, mu = _planar_weights(masses, lengths)
    phi = jnp.cumsum(q)
    phid = jnp.cumsum(qd)
    centrifugal = (weights * jnp.sin(phi[:, None] - phi[None, :])) @ (phid**2)
    gravity = GRAVITY * mu * lengths * jnp.cos(phi)
    return _tail_sum(centrifugal + gravity)


def tail_sums(values):
    """``out[a] = sum_{k >= a} values[k]`` for a Python list of arrays (``mu`` from masses)."""
    out = list(values)
    for k in range(len(out) - 2, -1, -1):
        out[k] = out[k + 1] + out[k]
    return out


def running_sums(values):
    """``out[a] = sum_{k <= a} values[k]`` for a Python list (absolute angles from joint angles)."""
    out = list(values)
    for k in range(1, len(out)):
        out[k] = out[k - 1] + out[k]
    return out


@dataclasses.dataclass(frozen=True)
class PlanarState:
    """State-only quantities of the planar arm in absolute angles ``phi = S q``.

    Every entry is a Python list (or list of lists) of arrays of one shape.

    Attributes:
        cos, sin: ``cos(phi_a)``, ``sin(phi_a)``.
        cos_diff, sin_diff: ``cos(phi_a - phi_b)``, ``sin(phi_a - phi_b)``.
        rate_sq: ``phid_a^2`` (absolute angular rate squared, rad^2/s^2).
    """

    cos: list
    sin: list
    cos_diff: list
    sin_diff: list
    rate_sq: list

    @classmethod
    def of(cls, q, qd):
        """From lists of joint angles ``q`` (rad) and rates ``qd`` (rad/s)."""
        n = len(q)
        phi, rate = running_sums(q), running_sums(qd)
        cos = [jnp.cos(p) for p in phi]
        sin = [jnp.sin(p) for p in phi]
        cos_diff = [[cos[a] * cos[b] + sin[a] * sin[b] for b in range(n)] for a in range(n)]
        sin_diff = [[sin[a] * cos[b] - cos[a] * sin[b] for b in range(n)] for a in range(n)]
        return cls(cos, sin, cos_diff, sin_diff, [r * r for r in rate])


def planar_torque_differences(state, mu, lengths, accel_abs):
    """``S'^-1 tau = M_phi(S qdd) + c + G_phi``: joint torque differences (N m), a list.

    ``tau_a - tau_{a+1}`` of the inverse dynamics for absolute accelerations
    ``accel_abs = S qdd``, with ``mu`` the tail sums of the masses.
    """
    n = len(lengths)
    out = []
    for a in range(n):
        total = GRAVITY * mu[a] * lengths[a] * state.cos[a]
        for b in range(n):
            weight = mu[max(a, b)] * lengths[a] * lengths[b]
            total = total + weight * (
                state.cos_diff[a][b] * accel_abs[b] + state.sin_diff[a][b] * state.rate_sq[b]
            )
        out.append(total)
    return out


def planar_scaled_accelerations(state, mu, lengths, inv_lengths, torque_diff):
    """Scaled absolute accelerations ``psi_a = l_a phidd_a`` of the planar arm, a list.

    Solves ``(Mu o C) psi = S'^-1 tau / l - (Mu o Sn)(l o phid^2) - g mu o cos``
    with ``Mu_ab = mu_max(a,b)``; the matrix depends on the masses and the state
    only, so RMI can factor it once per mass corner (``planar_search``).
    """
    n = len(lengths)
    matrix = [[mu[a] * state.cos_diff[a][b] for b in range(a + 1)] for a in range(n)]
    lower, _, inv_diag = ldl_factor(matrix)
    rhs = []
    for a in range(n):
        total = torque_diff[a] * inv_lengths[a] - GRAVITY * mu[a] * state.cos[a]
        for b in range(n):
            total = total - mu[max(a, b)] * state.sin_diff[a][b] * lengths[b] * state.rate_sq[b]
        rhs.append(total)
    return ldl_solve(lower, inv_diag, rhs)


def planar_forward_dynamics(q, qd, tau, th):
    """Closed-form forward dynamics of the planar point-mass arm, (n,) in rad/s^2.

    In absolute angles ``phi = S q`` and with ``psi_a = l_a phidd_a`` the
    dynamics reads ``(Mu o C) psi = S'^-1 tau / l - (Mu o Sn)(l o phid^2) - g mu o cos phi``
    (``Mu_ab = mu_max(a,b)``, ``C``, ``Sn`` the cosines and sines of
    ``phi_a - phi_b``), solved by an ``LDL'`` factorisation written out element
    by element (``n`` is static); then ``qdd = S^-1 (psi / l)``. Written on
    scalars so that ``vmap`` keeps the trigonometry out of the parameter axis
    and XLA fuses the rest; a batched ``jnp.linalg.solve`` over millions of
    tiny matrices is 8-80x slower (PERF_NOTES).
    """
    n = q.shape[-1]
    masses = [th[k] for k in range(n)]
    lengths = [th[n + k] for k in range(n)]
    state = PlanarState.of([q[a] for a in range(n)], [qd[a] for a in range(n)])
    torque_diff = [tau[a] - tau[a + 1] if a + 1 < n else tau[a] for a in range(n)]
    inv_lengths = [1.0 / length for length in lengths]
    psi = planar_scaled_accelerations(state, tail_sums(masses), lengths, inv_lengths, torque_diff)
    phidd = [psi[a] * inv_lengths[a] for a in range(n)]
    return jnp.stack([phidd[0]] + [phidd[a] - phidd[a - 1] for a in range(1, n)])


def planar_arm_model(n_links: int) -> RobotModel:
    """The planar serial arm of ``n_links`` point masses (SPEC section 1).

    Parameters are ``th = (m_1..m_n, l_1..l_n)`` in kg and m. Gravity acts
    along ``-y``; ``q_1`` is measured from the horizontal ``x`` axis and
    ``q_i`` (i > 1) relative to link ``i-1``.
    """
    n = _checks.integer("n_links", n_links, minimum=1, unit="links")
    names = tuple(f"m{k + 1}" for k in range(n)) + tuple(f"l{k + 1}" for k in range(n))
    return RobotModel(
        n_joints=n,
        n_params=2 * n,
        mass_matrix=planar_mass_matrix,
        bias=planar_bias,
        forward_dynamics=planar_forward_dynamics,
        name=f"planar_arm_{n}",
        param_names=names,
        structure=PlanarPointMass(),
        trusted=True,
    )


def planar_arm(nominal, lo, hi, *, dtype=None) -> UncertainRobot:
    """The uncertain planar point-mass arm (SPEC sections 1-2).

    Args:
        nominal, lo, hi: (2n,) = masses (kg) then lengths (m) of links 1..n.
        dtype: float dtype; default follows the inputs.

    Returns:
        An :class:`UncertainRobot` with ``p = 2n`` parameters.

    Raises:
        ValueError: if the vectors differ in length or have odd length, if
            any bound is not positive, or as :func:`uncertain_robot`.
    """
    nominal_np = np.asarray(nominal) if _checks.is_concrete(nominal) else None
    size = np.shape(nominal)[-1] if np.ndim(nominal) == 1 else None
    if size is None or size % 2:
        raise ValueError(
            f"nominal must be a 1-D vector (m_1..m_n, l_1..l_n) of even length 2n; "
            f"got shape {np.shape(nominal)}"
        )
    for label, value in (("lo", lo), ("hi", hi)):
        if np.shape(value) != (size,):
            raise ValueError(
                f"{label} has shape {np.shape(value)} but nominal has shape ({size},): "
                "give masses then lengths for every link in all three vectors"
            )
    robot = uncertain_robot(planar_arm_model(size // 2), nominal, lo, hi, dtype=dtype)
    if nominal_np is not None and _checks.is_concrete(robot.lo):
        low = np.asarray(robot.lo)
        bad = np.flatnonzero(low <= 0)
        if bad.size:
            b = int(bad[0])
            raise ValueError(
                f"lo of parameter {robot.model.param_names[b]} is {low[b]!r}: masses and "
                "lengths must be positive (the mass matrix is singular otherwise)"
            )
    return robot


def paper_pendulum(*, dtype=None) -> UncertainRobot:
    """The paper's pendulum: ``m = 10 [9, 11]`` kg, ``l = 1 [0.99, 1.01]`` m."""
    return planar_arm([10.0, 1.0], [9.0, 0.99], [11.0, 1.01], dtype=dtype)


def preset_arm(n: int, *, dtype=None) -> UncertainRobot:
    """The ``n``-link scaling preset: link 1 as the paper's two-joint arm's link 1
    (``m = 12 [11, 13]`` kg, ``l = 1.5 [1.49, 1.51]`` m), every other link as its
    link 2 (``m = 10 [9, 11]`` kg, ``l = 1 [0.99, 1.01]`` m)."""
    n = _checks.integer("n", n, minimum=1, unit="links")
    masses = [12.0] + [10.0] * (n - 1)
    masses_lo = [11.0] + [9.0] * (n - 1)
    masses_hi = [13.0] + [11.0] * (n - 1)
    lengths = [1.5] + [1.0] * (n - 1)
    lengths_lo = [1.49] + [0.99] * (n - 1)
    lengths_hi = [1.51] + [1.01] * (n - 1)
    return planar_arm(masses + lengths, masses_lo + lengths_lo, masses_hi + lengths_hi, dtype=dtype)


def paper_arm2(*, dtype=None) -> UncertainRobot:
    """The paper's two-joint arm: link 1 ``m1 = 12 [11, 13]``, ``l1 = 1.5 [1.49, 1.51]``;
    link 2 as the pendulum."""
    return preset_arm(2, dtype=dtype)
