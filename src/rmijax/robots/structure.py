"""What a robot model declares about how its parameters enter the dynamics.

Exact RMI needs, at every track and step, the parameter corner that maximises
the costate-weighted perturbation (SPEC section 5). Without more knowledge the
engine evaluates all ``2^p`` corners. A model that knows its structure declares
it here (``RobotModel(..., structure=...)``) and the engine takes a faster
exact search from the declaration, never from the model's type:

- ``None``: nothing declared; every corner is evaluated (the definition).
- :class:`AffineBias`: some parameters enter ``h`` only, affinely (friction
  coefficients, a constant disturbance). For a fixed choice of the others the
  score is affine in them, so each is chosen by the sign of its coefficient
  and only the ``2^(p - a)`` other corners are evaluated.
- :class:`LinearDynamics`: ``M`` and ``h`` are affine in *every* parameter
  (a rigid-body chain in its inertial scales, payload mass and friction). The
  model gives the terms once per state; every corner's ``M`` and ``h`` is a
  contraction, and the ``h``-only parameters are chosen by sign as above.
- :class:`PlanarPointMass`: the paper's planar arm, ``th = (m, l)``, whose
  inertia factor depends on the masses only and whose rest is affine in the
  lengths and their reciprocals (the exact factored search).

Each declaration is a promise about the model's functions; the tests hold each
search equal to enumeration. The searches live with the band methods
(:mod:`rmijax.methods.choosers`), so this layer imports nothing above it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

__all__ = ["AffineBias", "LinearDynamics", "PlanarPointMass", "affine_indices"]


def _indices(name, values):
    out = tuple(int(b) for b in values)
    if len(set(out)) != len(out) or any(b < 0 for b in out):
        raise ValueError(f"{name} must be distinct non-negative parameter indices, got {values!r}")
    return out


@dataclasses.dataclass(frozen=True)
class AffineBias:
    """Parameters that enter only the bias ``h``, and affinely.

    For these ``b``: ``M(q, th)`` does not depend on ``th_b`` and
    ``h(q, qd, th) = h'(q, qd, th_rest) + sum_b th_b y_b(q, qd)``.

    Attributes:
        affine: indices of those parameters in ``th``.
    """

    affine: tuple[int, ...]

    def __post_init__(self):
        object.__setattr__(self, "affine", _indices("affine", self.affine))


@dataclasses.dataclass(frozen=True)
class LinearDynamics:
    """``M`` and ``h`` affine in every parameter, with the terms given per state.

    ``M(q, th) = M0 + sum_b th_b M_b`` and ``h(q, qd, th) = h0 + sum_b th_b h_b``.

    Attributes:
        affine: indices of the parameters with ``M_b = 0`` (they enter ``h``
            only and are chosen by sign).
        terms: ``(q (n,), qd (n,)) -> (M0 (n, n), M_b (p, n, n), h0 (n,), h_b (p, n))``.
        affine_joints: optional, one joint per affine parameter: ``h_b`` is zero
            but for that joint's entry (friction acts on its own joint). The
            search then scores each affine parameter with one product instead of
            an ``n``-term dot product. None: ``h_b`` may be dense.
        reach: optional, per parameter (all ``p``) the last joint its terms
            touch: ``M_b`` is zero outside rows and columns ``0..reach_b`` and
            ``h_b`` outside entries ``0..reach_b`` (a serial chain: a body's
            inertia loads the joints inboard of it). The search then factors
            ``M`` from the tip, sharing each joint's elimination among the corners
            that agree on the parameters reaching it. None: no such promise.
        terms_tracks_last: optional, ``terms`` for ``T`` states at once with the
            tracks last: ``(q (n, T), qd (n, T)) -> (M0 (n, n, T), M_b (p, n, n, T),
            h0 (n, T), h_b (p, n, T))``, equal to ``vmap(terms)`` with its batch
            axis moved last. The coupled search calls it once per window step
            (a spatial chain's terms run several times faster this way on CPU).
            None: ``vmap(terms)``.
        layout: optional, the serial chain the terms come from (a
            :class:`rmijax.robots.spatial.ChainLayout`, as :func:`rmijax.load_robot`
            sets): methods that evaluate the dynamics on their own number types read
            it (``method="certified"`` on interval and affine jets). None: no chain.
    """

    affine: tuple[int, ...]
    terms: Callable
    affine_joints: tuple[int, ...] | None = None
    reach: tuple[int, ...] | None = None
    terms_tracks_last: Callable | None = None
    layout: object = None

    def __post_init__(self):
        object.__setattr__(self, "affine", _indices("affine", self.affine))
        if self.affine_joints is not None:
            joints = tuple(int(k) for k in self.affine_joints)
            if len(joints) != len(self.affine) or any(k < 0 for k in joints):
                raise ValueError(
                    f"affine_joints must give one joint index >= 0 per affine parameter "
                    f"({len(self.affine)}), got {self.affine_joints!r}"
                )
            object.__setattr__(self, "affine_joints", joints)
        if self.reach is not None:
            reach = tuple(int(k) for k in self.reach)
            if any(k < 0 for k in reach):
                raise ValueError(f"reach must give joint indices >= 0, got {self.reach!r}")
            object.__setattr__(self, "reach", reach)


@dataclasses.dataclass(frozen=True)
class PlanarPointMass:
    """The planar point-mass arm of SPEC section 1: ``th = (m_1..m_n, l_1..l_n)``."""


def affine_indices(structure) -> tuple[int, ...]:
    """Indices of the ``h``-only affine parameters a declaration names (none for others)."""
    return tuple(getattr(structure, "affine", ()))
