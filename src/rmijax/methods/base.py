"""Types every band method shares: the :class:`Bounds` it returns and the errors it raises.

As optax keeps the types its transformations share in one small ``base.py``,
the methods here depend on this module and on nothing of each other's.
"""

from __future__ import annotations

import dataclasses

import jax

from rmijax import _checks
from rmijax.robots.box import UncertainRobot
from rmijax.trajectory import Trajectory

__all__ = ["Bounds", "DivergedError", "ProblemTooLargeError", "check_types"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Bounds:
    """RMI bounds; ``[..., 0]`` is the encoder (rad), ``[..., 1]`` the tachometer (rad/s).

    Attributes:
        lower, upper: (T+1, n, 2) from :func:`rmi`, (n, 2) from :func:`rmi_step`.
        nominal: the nominal output ``c x_n(t_f)``, same shape.
        crossed: bool mask, same shape, where ``upper < lower`` (the greedy
            max track ended below the min track); never swapped silently.
        dt: the step in s of the grid the bounds live on (static), or None.
    """

    lower: jax.Array
    upper: jax.Array
    nominal: jax.Array
    crossed: jax.Array
    dt: float | None = dataclasses.field(default=None, metadata=dict(static=True))

    @property
    def width(self) -> jax.Array:
        """``upper - lower``, same shape as the bounds."""
        return self.upper - self.lower


ProblemTooLargeError = _checks.ProblemTooLargeError


class DivergedError(ArithmeticError):
    """The worst-case tracks of RMI left the floating-point range (the bounds are not finite)."""


def check_types(traj, params):
    """Refuse a ``traj`` that is not a Trajectory or ``params`` not an UncertainRobot."""
    if not isinstance(traj, Trajectory):
        raise TypeError(
            f"traj must be a rmijax.Trajectory (from rmijax.trajectory or "
            f"rmijax.trajectory_from_samples), got {type(traj).__name__}"
        )
    if not isinstance(params, UncertainRobot):
        raise TypeError(
            f"params must be a rmijax.UncertainRobot (from rmijax.planar_arm, "
            f"rmijax.preset_arm, ...), got {type(params).__name__}"
        )
