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

__all__ = ["GRAVITY", "RobotModel", "planar_arm_model"]

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


def planar_forward_dynamics(q, qd, tau, th):
    """Closed-form forward dynamics of the planar point-mass arm, (n,) in rad/s^2.

    Works in absolute angles ``phi = S q``: ``M_phi phidd = S'^-1 tau - c - G_phi``
    with ``M_phi = W o cos(phi_a - phi_b)``, solved by an LDL' factorisation
    written out element by element (``n`` is static), then ``qdd = S^-1 phidd``.
    Written on scalars so that ``vmap`` over corners keeps every
    state-only quantity (the trigonometry) out of the corner axis and XLA
    fuses the rest into one loop; a batched ``jnp.linalg.solve`` over millions
    of tiny matrices is 8-80x slower (PERF_NOTES).
    """
    n = q.shape[-1]
    masses = [th[k] for k in range(n)]
    lengths = [th[n + k] for k in range(n)]
    mu = [None] * n
    running = masses[n - 1]
    mu[n - 1] = running
    for k in range(n - 2, -1, -1):
        running = running + masses[k]
        mu[k] = running
    phi = jnp.cumsum(q)
    phid = jnp.cumsum(qd)
    cos_phi, sin_phi = jnp.cos(phi), jnp.sin(phi)
    cos_a = [cos_phi[a] for a in range(n)]
    sin_a = [sin_phi[a] for a in range(n)]
    phid_sq = [phid[a] * phid[a] for a in range(n)]

    def weight(a, b):
        return mu[max(a, b)] * lengths[a] * lengths[b]

    # M_phi (lower triangle) and right-hand side S'^-1 tau - c - G_phi.
    mass_abs = [[None] * n for _ in range(n)]
    rhs = []
    for a in range(n):
        for b in range(a + 1):
            cos_ab = cos_a[a] * cos_a[b] + sin_a[a] * sin_a[b]
            mass_abs[a][b] = weight(a, b) * cos_ab
        centrifugal = 0.0
        for b in range(n):
            if b == a:
                continue
            sin_ab = sin_a[a] * cos_a[b] - cos_a[a] * sin_a[b]
            centrifugal = centrifugal + weight(a, b) * sin_ab * phid_sq[b]
        torque_diff = tau[a] - tau[a + 1] if a + 1 < n else tau[a]
        rhs.append(torque_diff - centrifugal - GRAVITY * mu[a] * lengths[a] * cos_a[a])

    # LDL' factorisation: M_phi = L D L', unit lower L.
    lower = [[None] * n for _ in range(n)]
    inv_diag = [None] * n
    diag = [None] * n
    for j in range(n):
        d = mass_abs[j][j]
        for k in range(j):
            d = d - lower[j][k] * lower[j][k] * diag[k]
        diag[j] = d
        inv_diag[j] = 1.0 / d
        for i in range(j + 1, n):
            s = mass_abs[i][j]
            for k in range(j):
                s = s - lower[i][k] * lower[j][k] * diag[k]
            lower[i][j] = s * inv_diag[j]
    # Forward (L y = rhs), scale, back (L' x = D^-1 y).
    y = [None] * n
    for i in range(n):
        s = rhs[i]
        for k in range(i):
            s = s - lower[i][k] * y[k]
        y[i] = s
    phidd = [None] * n
    for i in range(n - 1, -1, -1):
        s = y[i] * inv_diag[i]
        for k in range(i + 1, n):
            s = s - lower[k][i] * phidd[k]
        phidd[i] = s
    qdd = [phidd[0]] + [phidd[a] - phidd[a - 1] for a in range(1, n)]
    return jnp.stack(qdd)


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
