"""Robot models: a rigid arm as a pair of pure JAX functions of a parameter vector.

RMI needs nothing from a robot but its mass matrix ``M(q, th)`` and bias forces
``h(q, qd, th)`` (SPEC section 1), so :class:`RobotModel` holds exactly that
pair, plus an optional fast forward-dynamics routine and a declaration of its
structure (:mod:`rmijax.robots.structure`). The planar point-mass arm
of the paper is one such model (:mod:`rmijax.robots.planar`); any other robot is
brought by writing its two functions.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax

from rmijax import _checks
from rmijax._linalg import spd_solve

__all__ = ["GRAVITY", "RobotModel"]

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
        structure: an optional declaration of how the parameters enter the
            dynamics (:mod:`rmijax.robots.structure`); exact RMI takes a
            faster search from it. None: every corner is evaluated.
        trusted: skip :func:`rmijax.check_model` (the sanity check of ``M``,
            ``h`` and ``forward_dynamics`` run before every band computation).
            The library's own models set it (the test suite holds them to the
            SPEC's oracles); set it only for a model you have tested yourself.
    """

    n_joints: int
    n_params: int
    mass_matrix: Callable[[jax.Array, jax.Array], jax.Array]
    bias: Callable[[jax.Array, jax.Array, jax.Array], jax.Array]
    forward_dynamics: Callable[..., jax.Array] | None = None
    name: str = "robot"
    param_names: tuple[str, ...] = ()
    structure: object = None
    trusted: bool = False

    def __post_init__(self):
        _checks.integer("n_joints", self.n_joints, minimum=1, unit="joints")
        _checks.integer("n_params", self.n_params, minimum=0, unit="parameters")
        _checks.boolean("trusted", self.trusted)
        for name in ("mass_matrix", "bias"):
            if not callable(getattr(self, name)):
                raise TypeError(
                    f"{name} must be a function (a pure JAX function of q"
                    f"{', qd' if name == 'bias' else ''} and th), got {getattr(self, name)!r}"
                )
        if self.forward_dynamics is not None and not callable(self.forward_dynamics):
            raise TypeError(
                "forward_dynamics must be None or a function (q, qd, tau, th) -> qdd, "
                f"got {self.forward_dynamics!r}"
            )
        if isinstance(self.param_names, str) or not all(
            isinstance(label, str) for label in self.param_names
        ):
            raise TypeError(
                "param_names must be a tuple of strings, one per parameter, got "
                f"{self.param_names!r}"
            )
        if self.param_names and len(self.param_names) != self.n_params:
            raise ValueError(
                f"param_names has {len(self.param_names)} entries but n_params is "
                f"{self.n_params}: give one name per parameter or none"
            )

    def accelerations(self, q, qd, tau, th):
        """Joint accelerations ``qdd = M(q; th)^-1 (tau - h(q, qd; th))``, shape ``(n,)``.

        The model's ``forward_dynamics`` where given, else ``M`` (positive definite)
        solved by :func:`rmijax._linalg.spd_solve`.
        """
        if self.forward_dynamics is not None:
            return self.forward_dynamics(q, qd, tau, th)
        return spd_solve(self.mass_matrix(q, th), tau - self.bias(q, qd, th))

    def torques(self, q, qd, qdd, th):
        """Inverse dynamics ``tau = M(q; th) qdd + h(q, qd; th)``, shape ``(n,)``."""
        return self.mass_matrix(q, th) @ qdd + self.bias(q, qd, th)
