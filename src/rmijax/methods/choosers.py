"""Corner choosers: how exact RMI finds the extreme parameter corner of one track step.

RMI's corner at a track step maximises ``sigma * gv_i(th)`` over the ``2^p``
corners, near-ties going to the lowest corner index (SPEC section 2). How that
corner is found is taken from what the model declares
(:mod:`rmijax.robots.structure`), never from its type:

- nothing declared: :func:`enumerate_corners` evaluates every corner;
- :class:`~rmijax.robots.structure.AffineBias`: for each corner of the other
  parameters the score is affine in the declared ones, so they are chosen by
  the sign of their coefficient (:class:`StructuredChooser`);
- :class:`~rmijax.robots.structure.LinearDynamics`: the same choice, with every
  corner's ``M`` and ``h`` contracted from terms computed once per state, and in
  ``coupled`` mode whole window steps of every track at once
  (:mod:`rmijax.methods.linear_search`, :class:`LinearChooser`);
- :class:`~rmijax.robots.structure.PlanarPointMass`: the planar arm's factored
  search (:data:`rmijax.methods.planar_search.SEARCH`).

All of them return the corner enumeration returns, tie rule included
(the tests hold them equal).

A *chooser* is a callable ``(perturbation, weight, offset, consts) -> th``:
``perturbation`` maps a parameter vector ``(p,)`` to the track's own ``gv_i``,
``weight`` is ``sigma`` (sign times costate weight), ``offset`` is
``sigma v_i`` (for the tie tolerance) and ``consts`` the window constants
(``nominal``, ``lo``, ``hi`` and, for enumeration, ``corners``). A chooser may
also offer ``coupled(q, qd, tau, v, onehot, weight, offset, consts) -> th`` for
``coupled`` mode when it can use the state directly, or ``coupled_step(states, u,
weights, onehots, nominal, lo, hi, kp, kd, dt) -> states`` to run a whole
``coupled`` window step of every track (as the planar arm's factored search does).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from rmijax.methods import linear_search, planar_search
from rmijax.methods._keys import tie_tolerance
from rmijax.robots.structure import AffineBias, LinearDynamics, PlanarPointMass

__all__ = [
    "StructuredChooser",
    "enumerate_corners",
    "pick_corner",
    "resolve",
    "structured_pick",
]


def pick_corner(scores, offset):
    """Index of the best (largest) score; near-ties go to the lowest corner index.

    Corners whose scores agree to roundoff are ties in exact arithmetic (e.g.
    at ``v = 0`` the first joint's ``gv`` does not depend on the last mass),
    yet they move the other joints differently. So a corner within
    ``eps^(2/3)`` (4e-11 in float64, 2e-5 in float32) of the best, relative to the
    score's cancellation scale ``max|score| + |offset|``, counts as tied, and
    the lowest index wins, as the contract says.

    Args:
        scores: (K,) costate-weighted perturbations ``sigma * gv_i``.
        offset: ``sigma * v_i``, the part cancelled in ``gv = qdd - v``.
    """
    tol = tie_tolerance(jnp.max(jnp.abs(scores)), offset)
    return jnp.argmax(scores >= jnp.max(scores) - tol)


def enumerate_corners(perturbation, weight, offset, consts):
    """The exhaustive chooser: the corner maximising ``weight * perturbation(th)``.

    Args:
        perturbation: ``th (p,) -> gv_i``, the track's own perturbation.
        weight: ``sigma``, sign times the costate weight.
        offset: ``sigma v_i``, for the tie tolerance (:func:`pick_corner`).
        consts: the window constants; ``corners`` (K, p) is used.

    Returns:
        The chosen corner (p,).
    """
    corners = consts["corners"]
    scores = jax.vmap(lambda th: weight * perturbation(th))(corners)
    return corners[pick_corner(scores, offset)]


enumerate_corners.needs_corners = True


# --------------------------------------------------------------------------
# Parameters chosen by sign: the exact arg-max of a score affine in some of them
# --------------------------------------------------------------------------


def structured_pick(base, span, offset, enumerated, affine):
    """The lowest-index corner within the tie tolerance of the best, for an affine score.

    The score of the corner made of enumerated corner ``e`` and affine bits
    ``a`` is ``base[e] + sum_j a_j span[e, j]`` with ``span = coef (hi - lo)``.
    The best corner and the score scale ``max|score|`` follow from the signs of
    ``span``. The lowest index among the corners scoring at least ``best - tol``
    is then found bit by bit from the most significant parameter down: a bit
    stays clear when some completion of the remaining bits still reaches the
    threshold (the best completion of the affine bits is known in closed form),
    exactly the corner :func:`pick_corner` picks among all ``2^p``.

    Args:
        base: (E,) scores of the enumerated corners with every affine parameter at ``lo``.
        span: (E, A) score gained by moving affine parameter ``j`` from lo to hi.
        offset: ``sigma v_i`` of the tie tolerance.
        enumerated, affine: the parameter indices of the enumerated bits (E = 2^len)
            and of the affine ones, each ascending.

    Returns:
        ``(e, a_bits)``: the enumerated corner's index and (A,) bools (True: hi).
    """
    gain = jnp.maximum(span, 0.0)
    loss = jnp.minimum(span, 0.0)
    remaining = jnp.sum(gain, axis=1)
    best = base + remaining
    worst = base + jnp.sum(loss, axis=1)
    scale = jnp.maximum(jnp.max(jnp.abs(best)), jnp.max(jnp.abs(worst)))
    threshold = jnp.max(best) - tie_tolerance(scale, offset)
    n_enum = len(enumerated)
    e_bits = (np.arange(2**n_enum)[:, None] >> np.arange(n_enum)[None, :]) & 1  # (E, p_e)
    fixed = base
    alive = jnp.ones(base.shape, bool)
    a_bits = [None] * len(affine)
    order = [(b, "e", k) for k, b in enumerate(enumerated)]
    order += [(b, "a", j) for j, b in enumerate(affine)]
    for _, kind, index in sorted(order, reverse=True):
        if kind == "a":
            rest = remaining - gain[:, index]
            clear_ok = jnp.any(alive & (fixed + rest >= threshold))
            a_bits[index] = ~clear_ok
            fixed = fixed + jnp.where(clear_ok, 0.0, span[:, index])
            remaining = rest
        else:
            clear = jnp.asarray(e_bits[:, index] == 0)
            clear_ok = jnp.any(alive & clear & (fixed + remaining >= threshold))
            alive = alive & jnp.where(clear_ok, clear, ~clear)
    bits = jnp.stack(a_bits) if a_bits else jnp.zeros((0,), bool)
    return jnp.argmax(alive), bits


@dataclasses.dataclass(frozen=True)
class StructuredChooser:
    """Exact chooser for a model declaring :class:`AffineBias` or :class:`LinearDynamics`.

    The ``2^(p - a)`` corners of the other parameters are evaluated with every
    affine parameter at ``lo``; the affine ones are chosen by the sign of their
    coefficient, which for a black-box model is the derivative (exact, the
    score being affine in them) and for :class:`LinearDynamics` a contraction.

    Attributes:
        n_params: ``p``.
        affine: indices of the sign-chosen parameters.
        terms: the :class:`LinearDynamics` terms, or None.
    """

    n_params: int
    affine: tuple[int, ...]
    terms: Callable | None = None

    needs_corners = False

    @property
    def enumerated(self) -> tuple[int, ...]:
        return tuple(b for b in range(self.n_params) if b not in set(self.affine))

    @property
    def n_evaluated(self) -> int:
        """Corners evaluated per track step (``2^(p - a)``)."""
        return 2 ** len(self.enumerated)

    def _corners(self, consts):
        """(E, p): every enumerated corner, affine parameters at ``lo``."""
        lo, hi = consts["lo"], consts["hi"]
        enum = np.asarray(self.enumerated, int)
        bits = (np.arange(2**enum.size)[:, None] >> np.arange(enum.size)[None, :]) & 1
        chosen = jnp.where(jnp.asarray(bits == 1), hi[enum][None, :], lo[enum][None, :])
        return jnp.broadcast_to(lo[None, :], (bits.shape[0], lo.shape[0])).at[:, enum].set(chosen)

    def _assemble(self, corners, e, a_bits, consts):
        affine = np.asarray(self.affine, int)
        th = corners[e]
        if affine.size:
            th = th.at[affine].set(jnp.where(a_bits, consts["hi"][affine], consts["lo"][affine]))
        return th

    def __call__(self, perturbation, weight, offset, consts):
        corners = self._corners(consts)
        affine = np.asarray(self.affine, int)

        def score_and_slope(th):
            def along(values):
                return weight * perturbation(th.at[affine].set(values))

            return along(th[affine]), jax.jacfwd(along)(th[affine])

        base, coef = jax.vmap(score_and_slope)(corners)
        span = coef * (consts["hi"][affine] - consts["lo"][affine])[None, :]
        e, a_bits = structured_pick(base, span, offset, self.enumerated, self.affine)
        return self._assemble(corners, e, a_bits, consts)

    def estimate_memory(self, params, *, mode, itemsize):
        """Bytes of one end step: ``4n`` tracks x ``E`` corners x ``(1 + a)`` values per
        intermediate, with the engine's ``3n^2 + 4n + 8`` intermediates per value."""
        n = params.n_joints
        values = 4 * n * self.n_evaluated * (1 + len(self.affine))
        return 64 * 2**10 + values * itemsize * (3 * n * n + 4 * n + 8)


@dataclasses.dataclass(frozen=True)
class LinearChooser(StructuredChooser):
    """:class:`StructuredChooser` whose ``coupled`` mode runs whole window steps.

    ``coupled_step`` (:func:`rmijax.methods.linear_search.coupled_window_step`)
    takes every track of a window step at once: the terms once per track, then per
    (track, enumerated corner) the row of ``M^-1`` and the score, with the
    factorisation shared along a serial chain when ``reach`` is declared; the
    engine calls it in place of a per-track chooser.

    Attributes:
        affine_joints: for each affine parameter the joint whose bias it alone
            enters, or None (see :class:`LinearDynamics`).
        reach: per parameter the last joint its terms touch, or None.
        terms_tracks_last: the terms of many states, tracks last, or None.
    """

    affine_joints: tuple[int, ...] | None = None
    reach: tuple[int, ...] | None = None
    terms_tracks_last: Callable | None = None
    shared_start = True  # coupled_step takes (1, n, 2) states shared by every track

    def coupled_step(self, states, u, weights, onehots, nominal, lo, hi, kp, kd, dt):
        return linear_search.coupled_window_step(
            self.terms_tracks_last or _tracks_last(self.terms),
            self.enumerated,
            self.affine,
            self.affine_joints,
            self.reach,
            states,
            u,
            weights,
            onehots,
            nominal,
            lo,
            hi,
            kp,
            kd,
            dt,
        )


def _tracks_last(terms):
    """``terms`` of one state as a function of ``T`` states, tracks last (by ``vmap``)."""

    def batched(q, qd):
        return jax.vmap(terms, in_axes=1, out_axes=-1)(q, qd)

    return batched


def resolve(model, search):
    """The corner search exact RMI uses for ``model`` under the ``search`` option.

    Args:
        model: the :class:`~rmijax.robots.model.RobotModel`.
        search: ``"auto"`` (from the model's declared structure),
            ``"enumerate"`` (every corner) or a chooser callable.

    Returns:
        A chooser (see the module docstring) or
        :data:`rmijax.methods.planar_search.SEARCH` (a whole window step).
    """
    if callable(search):
        return search
    if search == "enumerate":
        return enumerate_corners
    structure = model.structure
    bad = [b for b in getattr(structure, "affine", ()) if b >= model.n_params]
    if bad:
        raise ValueError(
            f"the model's structure declares affine parameter index {bad[0]} but the model "
            f"has n_params={model.n_params}; declare indices in [0, {model.n_params})"
        )
    if isinstance(structure, PlanarPointMass):
        return planar_search.SEARCH
    if isinstance(structure, LinearDynamics):
        return LinearChooser(
            model.n_params,
            structure.affine,
            structure.terms,
            structure.affine_joints,
            structure.reach,
            structure.terms_tracks_last,
        )
    if isinstance(structure, AffineBias):
        return StructuredChooser(model.n_params, structure.affine)
    return enumerate_corners
