"""Robot model: SPEC section 1 oracles, the Lagrangian, the fast forward dynamics."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rmijax
from rmijax.robots.planar import planar_bias, planar_forward_dynamics, planar_mass_matrix

from reference_numpy import PlanarArmNumpy

G = rmijax.GRAVITY


def random_state(rng, n):
    th = np.concatenate([rng.uniform(1.0, 12.0, n), rng.uniform(0.4, 1.6, n)])
    return rng.uniform(-np.pi, np.pi, n), rng.uniform(-3.0, 3.0, n), th


def test_pendulum_oracle(rng):
    q, qd, th = random_state(rng, 1)
    m, l = th
    np.testing.assert_allclose(planar_mass_matrix(q, th), [[m * l**2]], rtol=1e-14)
    np.testing.assert_allclose(planar_bias(q, qd, th), [m * G * l * np.cos(q[0])], rtol=1e-14)


def test_two_joint_oracle(rng):
    for _ in range(5):
        q, qd, th = random_state(rng, 2)
        m1, m2, l1, l2 = th
        (q1, q2), (qd1, qd2) = q, qd
        m11 = (m1 + m2) * l1**2 + m2 * l2**2 + 2 * m2 * l1 * l2 * np.cos(q2)
        m12 = m2 * l2**2 + m2 * l1 * l2 * np.cos(q2)
        m22 = m2 * l2**2
        h1 = (
            -m2 * l1 * l2 * np.sin(q2) * (2 * qd1 * qd2 + qd2**2)
            + (m1 + m2) * G * l1 * np.cos(q1)
            + m2 * G * l2 * np.cos(q1 + q2)
        )
        h2 = m2 * l1 * l2 * np.sin(q2) * qd1**2 + m2 * G * l2 * np.cos(q1 + q2)
        np.testing.assert_allclose(
            planar_mass_matrix(q, th), [[m11, m12], [m12, m22]], rtol=1e-13, atol=1e-12
        )
        np.testing.assert_allclose(planar_bias(q, qd, th), [h1, h2], rtol=1e-13, atol=1e-11)


@jax.jit
def lagrangian_terms(q, qd, th):
    """``M`` and ``h`` from the Lagrangian of the mass positions alone (autodiff)."""
    n = q.shape[0]
    masses, lengths = th[:n], th[n:]

    def positions(q):
        phi = jnp.cumsum(q)
        return jnp.cumsum(lengths[:, None] * jnp.stack([jnp.cos(phi), jnp.sin(phi)], -1), axis=0)

    def kinetic(q, qd):
        velocities = jax.jvp(positions, (q,), (qd,))[1]
        return 0.5 * jnp.sum(masses * jnp.sum(velocities**2, axis=-1))

    def potential(q):
        return G * jnp.sum(masses * positions(q)[:, 1])

    mass = jax.hessian(kinetic, argnums=1)(q, qd)
    # d/dt (dT/dqd) = M qdd + (d/dq dT/dqd) qd; h = (d/dq dT/dqd) qd - dT/dq + dV/dq
    mixed = jax.jacfwd(jax.grad(kinetic, argnums=1), argnums=0)(q, qd)
    bias = mixed @ qd - jax.grad(kinetic, argnums=0)(q, qd) + jax.grad(potential)(q)
    return mass, bias


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 6])
def test_lagrangian_and_positive_definite(rng, n):
    for _ in range(3):
        q, qd, th = random_state(rng, n)
        mass, bias = lagrangian_terms(jnp.asarray(q), jnp.asarray(qd), jnp.asarray(th))
        m_model = np.asarray(planar_mass_matrix(q, th))
        np.testing.assert_allclose(m_model, mass, rtol=1e-12, atol=1e-10)
        np.testing.assert_allclose(planar_bias(q, qd, th), bias, rtol=1e-11, atol=1e-9)
        np.testing.assert_array_equal(m_model, m_model.T)
        assert np.linalg.eigvalsh(m_model).min() > 0


@pytest.mark.parametrize("n", [1, 2, 3, 4, 6, 8])
def test_closed_form_forward_dynamics_equals_solve(rng, n):
    for _ in range(3):
        q, qd, th = random_state(rng, n)
        tau = rng.uniform(-200.0, 200.0, n)
        expected = np.linalg.solve(
            planar_mass_matrix(q, th), tau - np.asarray(planar_bias(q, qd, th))
        )
        np.testing.assert_allclose(
            planar_forward_dynamics(jnp.asarray(q), jnp.asarray(qd), jnp.asarray(tau), th),
            expected,
            rtol=1e-10,
            atol=1e-10,
        )


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_numpy_reference_model_agrees(rng, n):
    """The NumPy reference's triple-sum model (the engine's oracle) matches the JAX model."""
    reference = PlanarArmNumpy(n)
    q, qd, th = random_state(rng, n)
    np.testing.assert_allclose(
        reference.mass_matrix(q, th)[0], planar_mass_matrix(q, th), rtol=1e-12, atol=1e-12
    )
    np.testing.assert_allclose(
        reference.bias(q, qd, th)[0], planar_bias(q, qd, th), rtol=1e-11, atol=1e-10
    )


def test_model_validation():
    with pytest.raises(ValueError, match="n_links"):
        rmijax.planar_arm_model(0)
    with pytest.raises(ValueError, match="param_names"):
        rmijax.RobotModel(1, 2, planar_mass_matrix, planar_bias, param_names=("a",))


def test_generic_accelerations_use_solve(rng):
    """A model without a closed form falls back to a linear solve of M and h."""
    model = rmijax.RobotModel(2, 4, planar_mass_matrix, planar_bias)
    q, qd, th = random_state(rng, 2)
    tau = rng.uniform(-50.0, 50.0, 2)
    fast = rmijax.planar_arm_model(2).accelerations(q, qd, tau, th)
    np.testing.assert_allclose(model.accelerations(q, qd, tau, th), fast, rtol=1e-12)
    np.testing.assert_allclose(model.torques(q, qd, fast, th), tau, rtol=1e-11, atol=1e-10)


@pytest.mark.parametrize("dtype, rtol", [(jnp.float64, 1e-12), (jnp.float32, 1e-4)])
def test_spd_solve_equals_lapack_and_its_derivatives(rng, dtype, rtol):
    # The library's M qdd = tau - h (spatial arms, user models, locked joints) is solved
    # by the element-wise LDL' of rmijax._linalg.spd_solve, not LAPACK (README, "Known
    # problem"): same answer as numpy's LU, batched, n = 1..7 written out and 9, 16 by
    # the column loop (above UNROLL_MAX), and the same reverse-mode derivative as
    # jnp.linalg.solve.
    from rmijax._linalg import UNROLL_MAX, spd_solve

    assert UNROLL_MAX == 8  # the sizes below cover both paths
    for n in [*range(1, 8), 9, 16]:
        basis = rng.normal(size=(20, n, n))
        matrix = basis @ np.swapaxes(basis, 1, 2) + n * np.eye(n)
        rhs = rng.normal(size=(20, n))
        expected = np.linalg.solve(matrix, rhs[..., None])[..., 0]
        got = spd_solve(jnp.asarray(matrix, dtype), jnp.asarray(rhs, dtype))
        assert got.shape == (20, n) and got.dtype == dtype
        np.testing.assert_allclose(got, expected, rtol=rtol, atol=rtol)

        # reverse-mode: the derivative along a symmetric direction E (spd_solve reads
        # only the lower triangle, so only symmetric directions are comparable)
        direction = rng.normal(size=(20, n, n))
        direction = jnp.asarray(direction + np.swapaxes(direction, 1, 2), dtype)
        along = []
        for solve in (spd_solve, jnp.linalg.solve):

            def last(m, r, solve=solve):
                return solve(m, r)[-1]

            grad = jax.vmap(jax.grad(last))(jnp.asarray(matrix, dtype), jnp.asarray(rhs, dtype))
            along.append(np.sum(np.asarray(grad) * np.asarray(direction), axis=(1, 2)))
        np.testing.assert_allclose(along[0], along[1], rtol=10 * rtol, atol=10 * rtol)
