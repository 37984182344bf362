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
    """A method's bounds left the floating-point range (they are not finite).

    Where it happened, for programs that react to it (the message says the same
    in words):

    Attributes:
        step: the first step (or end step, for windowed methods) with a
            non-finite bound, or None where the method cannot tell.
        joint: that output's joint (0-based), or None.
        sensor: ``"encoder"`` or ``"tachometer"``, or None.
    """

    SENSORS = ("encoder", "tachometer")

    def __init__(self, message, *, step=None, joint=None, sensor=None):
        super().__init__(message)
        if sensor is not None and sensor not in self.SENSORS:
            raise ValueError(f"sensor must be one of {self.SENSORS} or None, got {sensor!r}")
        self.step = None if step is None else int(step)
        self.joint = None if joint is None else int(joint)
        self.sensor = sensor

    @classmethod
    def at(cls, where, message):
        """The error for an output index ``where = (step, joint, sensor)`` (sensor 0 or 1),
        as :func:`rmijax._checks.first_non_finite` returns it; ``(joint, sensor)`` without
        a step."""
        *step, joint, sensor = where
        return cls(message, step=step[0] if step else None, joint=joint, sensor=cls.SENSORS[sensor])

    def __reduce__(self):  # keep the attributes through pickling (process pools)
        return (
            _diverged,
            (str(self), dict(step=self.step, joint=self.joint, sensor=self.sensor)),
        )


def _diverged(message, where):
    return DivergedError(message, **where)


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
