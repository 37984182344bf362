"""Robot models: a rigid arm as a pair of pure JAX functions of a parameter vector.

RMI needs nothing from a robot but its mass matrix ``M(q, th)`` and bias forces
``h(q, qd, th)`` (SPEC section 1), so :class:`RobotModel` holds exactly that
pair, plus an optional fast forward-dynamics routine. The planar point-mass arm
of the paper is one such model (:func:`planar_arm_model`); any other robot is
brought by writing its two functions.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp

__all__ = ["GRAVITY", "RobotModel", "is_planar_arm", "planar_arm_model"]

GRAVITY = 9.81
"""Gravitational acceleration in m/s^2, along ``-y``."""


@dataclasses.dataclass(frozen=True)
class RobotModel:
    """A rigid robot described by pure JAX functions of a parameter vector.

    Every function takes single (unbatched) arguments; the RMI engine `vmap`s
    them over parameter corners and tracks. They must be traceable by JAX and
    must not close over arrays that change between calls (they are static).

    Attributes:
        n_joints: number of joints ``n``.
        n_params: length ``p`` of the parameter vector ``th``.
        mass_matrix: ``(q (n,), th (p,)) -> M (n, n)``, symmetric positive
            definite, in kg m^2 (revolute) or kg (prismatic).
        bias: ``(q (n,), qd (n,), th (p,)) -> h (n,)``: Coriolis, centrifugal
            and gravity forces in N m (or N), so ``M qdd + h = tau``.
        forward_dynamics: optional ``(q, qd, tau, th) -> qdd (n,)``. It must
            equal ``solve(M, tau - h)``; give one when a closed form is faster
            than a general linear solve.
        name: a label for reports.
        param_names: one label per parameter, for reports.
    """

    n_joints: int
    n_params: int
    mass_matrix: Callable[[jax.Array, jax.Array], jax.Array]
    bias: Callable[[jax.Array, jax.Array, jax.Array], jax.Array]
    forward_dynamics: Callable[..., jax.Array] | None = None
    name: str = "robot"
    param_names: tuple[str, ...] = ()

    def __post_init__(self):
        if int(self.n_joints) < 1:
            raise ValueError(f"n_joints must be >= 1, got {self.n_joints}")
        if int(self.n_params) < 0:
            raise ValueError(f"n_params must be >= 0, got {self.n_params}")
        if self.param_names and len(self.param_names) != self.n_params:
            raise ValueError(
                f"param_names has {len(self.param_names)} entries but n_params is "
                f"{self.n_params}: give one name per parameter or none"
            )

    def accelerations(self, q, qd, tau, th):
        """Joint accelerations ``qdd = M(q; th)^-1 (tau - h(q, qd; th))``, shape ``(n,)``."""
        if self.forward_dynamics is not None:
            return self.forward_dynamics(q, qd, tau, th)
        return jnp.linalg.solve(self.mass_matrix(q, th), tau - self.bias(q, qd, th))

    def torques(self, q, qd, qdd, th):
        """Inverse dynamics ``tau = M(q; th) qdd + h(q, qd; th)``, shape ``(n,)``."""
        return self.mass_matrix(q, th) @ qdd + self.bias(q, qd, th)


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


def ldl_factor(matrix):
    """``LDL'`` factorisation of a symmetric matrix given element by element.

    Args:
        matrix: ``matrix[a][b]`` for ``b <= a`` (the lower triangle), each an
            array of any shape (the factorisation runs elementwise over it).

    Returns:
        ``(lower, diag, inv_diag)``: ``lower[i][j]`` for ``j < i`` of the unit
        lower factor, the pivots and their reciprocals.
    """
    n = len(matrix)
    lower = [[None] * n for _ in range(n)]
    diag, inv_diag = [None] * n, [None] * n
    for j in range(n):
        d = matrix[j][j]
        for k in range(j):
            d = d - lower[j][k] * lower[j][k] * diag[k]
        diag[j] = d
        inv_diag[j] = 1.0 / d
        for i in range(j + 1, n):
            s = matrix[i][j]
            for k in range(j):
                s = s - lower[i][k] * lower[j][k] * diag[k]
            lower[i][j] = s * inv_diag[j]
    return lower, diag, inv_diag


def ldl_solve(lower, inv_diag, rhs):
    """Solve ``L D L' x = rhs`` with the factors of :func:`ldl_factor` (lists in, list out)."""
    n = len(rhs)
    y = list(rhs)
    for i in range(n):
        for k in range(i):
            y[i] = y[i] - lower[i][k] * y[k]
    x = [None] * n
    for i in range(n - 1, -1, -1):
        s = y[i] * inv_diag[i]
        for k in range(i + 1, n):
            s = s - lower[k][i] * x[k]
        x[i] = s
    return x


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


def is_planar_arm(model) -> bool:
    """True when ``model`` is the planar point-mass arm of :func:`planar_arm_model`.

    Decided by its functions, not its name, so that a user model is never
    mistaken for it: RMI then uses the arm's exact factored corner search.
    """
    return (
        model.mass_matrix is planar_mass_matrix
        and model.bias is planar_bias
        and model.forward_dynamics is planar_forward_dynamics
        and model.n_params == 2 * model.n_joints
    )


def planar_arm_model(n_links: int) -> RobotModel:
    """The planar serial arm of ``n_links`` point masses (SPEC section 1).

    Parameters are ``th = (m_1..m_n, l_1..l_n)`` in kg and m. Gravity acts
    along ``-y``; ``q_1`` is measured from the horizontal ``x`` axis and
    ``q_i`` (i > 1) relative to link ``i-1``.
    """
    n = int(n_links)
    if n < 1:
        raise ValueError(f"n_links must be >= 1, got {n_links}")
    names = tuple(f"m{k + 1}" for k in range(n)) + tuple(f"l{k + 1}" for k in range(n))
    return RobotModel(
        n_joints=n,
        n_params=2 * n,
        mass_matrix=planar_mass_matrix,
        bias=planar_bias,
        forward_dynamics=planar_forward_dynamics,
        name=f"planar_arm_{n}",
        param_names=names,
    )
