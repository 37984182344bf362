"""Shared builders for the tests: random boxes, gains and a simple true-plant simulation."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import rmijax


def random_arm(rng, n, *, certain=()):
    """A planar arm with a random asymmetric box around random nominal values."""
    masses = rng.uniform(2.0, 12.0, n)
    lengths = rng.uniform(0.5, 1.5, n)
    nominal = np.concatenate([masses, lengths])
    below = nominal * rng.uniform(0.01, 0.12, 2 * n)
    above = nominal * rng.uniform(0.01, 0.12, 2 * n)
    lo, hi = nominal - below, nominal + above
    for b in certain:
        lo[b] = hi[b] = nominal[b]
    return rmijax.planar_arm(nominal, lo, hi)


def random_gains(rng, n):
    kp = rng.uniform(40.0, 160.0, n)
    kd = rng.uniform(12.0, 30.0, n)
    return kp, kd


@jax.jit
def simulate_constant(traj, params, th_true):
    """True closed loop with constant parameters ``th_true`` (R, p): states (R, T+1, n, 2).

    A deliberately simple plant: the model's own ``M`` and ``h`` through a
    general linear solve, the controller fed by the true state.
    """
    model, nominal = params.model, params.nominal

    def run(th):
        def step(x, u):
            q, qd = x[:, 0], x[:, 1]
            v = u - traj.kd * qd - traj.kp * q
            tau = model.mass_matrix(q, nominal) @ v + model.bias(q, qd, nominal)
            qdd = jnp.linalg.solve(model.mass_matrix(q, th), tau - model.bias(q, qd, th))
            nxt = jnp.stack([q + traj.dt * qd, qd + traj.dt * qdd], axis=-1)
            return nxt, nxt

        _, rest = jax.lax.scan(step, traj.x_n[0], traj.u_d[:-1])
        return jnp.concatenate([traj.x_n[:1], rest], axis=0)

    return jax.vmap(run)(th_true)


def containment(states, bounds):
    """(fraction of samples inside, fraction of clean runs, worst violation / width)."""
    lower, upper = np.asarray(bounds.lower), np.asarray(bounds.upper)
    states = np.asarray(states)
    below = np.maximum(lower - states, 0.0)
    above = np.maximum(states - upper, 0.0)
    violation = np.maximum(below, above)
    inside = violation <= 1e-9
    width = upper - lower
    relative = np.where(width > 0, violation / np.where(width > 0, width, 1.0), 0.0)
    runs_clean = inside.reshape(inside.shape[0], -1).all(axis=1)
    return inside.mean(), runs_clean.mean(), relative.max()


def mc_parameters(params, draws, seed):
    """All corners plus ``draws`` uniform samples of the box: (K + draws, p)."""
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(params.lo), np.asarray(params.hi)
    uniform = lo + (hi - lo) * rng.uniform(size=(draws, lo.size))
    return np.concatenate([np.asarray(params.corners), uniform], axis=0)
