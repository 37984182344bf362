"""The paper's baseline: constant thresholds from fault-free runs (SPEC section 7).

Per output, the largest ``|y - y_n|`` seen over ``runs`` fault-free runs with true
parameters drawn uniformly in the box, times a safety factor, as a constant band
around the nominal output ``y_n``.
"""

from __future__ import annotations

import jax.numpy as jnp

from rmijax import _checks
from rmijax.methods.base import Bounds, check_types
from rmijax.plant import simulate
from rmijax.robots.box import UncertainRobot, monte_carlo_parameters
from rmijax.trajectory import Trajectory

__all__ = ["empirical_thresholds"]


def empirical_thresholds(
    traj: Trajectory,
    params: UncertainRobot,
    *,
    runs: int = 20,
    safety: float = 1.2,
    seed: int = 0,
    noise_lo=0.0,
    noise_hi=0.0,
) -> Bounds:
    """The paper's baseline: constant thresholds tuned on fault-free runs.

    Per output, the largest ``|y - y_n|`` seen over ``runs`` fault-free runs
    with true parameters drawn uniformly in the box, times ``safety``, as a
    constant band around the nominal output.

    Returns:
        :class:`~rmijax.methods.base.Bounds` of shape (T+1, n, 2).
    """
    check_types(traj, params)
    runs = _checks.integer("runs", runs, minimum=1, unit="runs")
    safety = _checks.real("safety", safety, positive=True)
    seed = _checks.seed(seed)
    th = monte_carlo_parameters(params, runs, seed=seed, corners=False)
    _, readings = simulate(traj, params, th, noise_lo=noise_lo, noise_hi=noise_hi, seed=seed)
    nominal = jnp.asarray(traj.x_n)
    deviation = jnp.max(jnp.abs(readings - nominal[None]), axis=(0, 1))  # (n, 2)
    band = jnp.broadcast_to(safety * deviation, nominal.shape)
    return Bounds(
        lower=nominal - band,
        upper=nominal + band,
        nominal=nominal,
        crossed=jnp.zeros(nominal.shape, bool),
        dt=traj.dt,
    )
