"""RMI with the extreme corner searched instead of enumerated: gradient sign, then bit flips.

Exact RMI (SPEC section 5) picks, at every window step and for every track,
the corner of the parameter box that maximises the score ``sigma * gv_i(th)``
(``sigma`` the sign times the costate weight) among all ``K = 2^p`` corners;
at 16 links that is ``2^32`` corners per track and step. This method keeps
everything else of RMI (the engine's windows, costate and tracks) and finds
the corner by a local search:

1. start at the sign of the score's gradient at the nominal parameters
   (``hi_b`` where ``d score / d th_b > 0``, ``lo_b`` otherwise). A gradient
   whose linearised gain ``d score / d th_b (hi_b - lo_b)`` is within the tie
   tolerance below counts as zero: in exact arithmetic the score does not
   depend on that parameter (e.g. a distal mass at ``v = 0``), all its corners
   tie, and the contract's tie rule (lowest corner index) takes ``lo_b``.
   Taking the sign of a 1e-18 roundoff gradient instead picked the other,
   equally scored corner in 0.15-0.2% of the decisions on 2-3 links, and as
   the two move the other joints differently, bounds off by up to 1.5e-4;
2. evaluate the ``p`` corners one bit flip away (one ``vmap``) and move to the
   best of them while it beats the current corner by more than the engine's
   tie tolerance (``eps^(2/3)`` relative to ``max|score| + |sigma v_i|``), for
   at most ``max_rounds`` rounds (default ``p``).

That is at most ``1 + p * max_rounds`` evaluations (plus one gradient) per
track and step instead of ``2^p``, and no array grows with ``2^p``. The result
is a local maximum of the score over the corners: it equals exact RMI wherever
the searched corners equal the enumerated ones (always when the score is
monotone in every parameter), and :func:`corner_agreement` measures how often
they do. Because a track follows its own choices, one different decision
changes the rest of that window; the bounds are then neither inside nor
outside exact RMI's by construction.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import threading

import jax
import jax.numpy as jnp
import numpy as np

from rmijax.methods import rmi as engine
from rmijax.methods.base import Bounds
from rmijax.methods.choosers import enumerate_corners, tie_tolerance
from rmijax.methods.linearized import differentiable_model
from rmijax.methods.rmi import DEFAULT_MEMORY_BUDGET
from rmijax.robots.box import UncertainRobot, corner_tensor
from rmijax.trajectory import Trajectory

__all__ = [
    "CLOSED_FORM_MAX_LINKS",
    "LocalSearch",
    "corner_agreement",
    "corner_search_bounds",
    "corner_search_step",
    "search_robot",
]


def _check_max_rounds(max_rounds):
    """``max_rounds`` as None or an int >= 0, or a ValueError naming it."""
    if max_rounds is None:
        return None
    if isinstance(max_rounds, bool) or not isinstance(max_rounds, (int, np.integer)):
        raise ValueError(
            f"max_rounds must be None (one round per parameter) or an integer >= 0, "
            f"got {max_rounds!r}"
        )
    if max_rounds < 0:
        raise ValueError(
            f"max_rounds must be >= 0 (0 keeps the gradient-sign start), got {max_rounds!r}"
        )
    return int(max_rounds)


def _tie_tolerance(scores, offset):
    """The engine's tie tolerance (:func:`rmijax.methods.choosers.pick_corner`) for the
    scores seen so far."""
    return tie_tolerance(jnp.max(jnp.abs(scores)), offset)


@dataclasses.dataclass(frozen=True)
class LocalSearch:
    """A chooser for :func:`rmijax.methods.rmi.rmi`: gradient-sign start, then single-bit flips.

    Hashable (a static ``jit`` argument). Called by the engine once per track
    and window step as ``choose(perturbation, weight, offset, consts)``.

    Attributes:
        max_rounds: flip rounds per decision (>= 0); None means ``p``. 0 keeps
            the gradient-sign corner.
    """

    max_rounds: int | None = None

    def __post_init__(self):
        _check_max_rounds(self.max_rounds)

    def rounds(self, n_params: int) -> int:
        """Flip rounds used for ``n_params`` parameters."""
        return n_params if self.max_rounds is None else int(self.max_rounds)

    def __call__(self, perturbation, weight, offset, consts):
        """The searched corner maximising ``weight * perturbation(th)``.

        Args:
            perturbation: ``th (p,) -> gv_i`` (rad/s^2), the track's own perturbation.
            weight: ``sigma``, sign times costate weight (scalar).
            offset: ``sigma v_i`` (scalar), the cancellation scale of the tie tolerance.
            consts: the window constants; ``nominal``, ``lo``, ``hi`` (p,) are
                used (``corners`` never: it is not built for a chooser).

        Returns:
            The chosen corner (p,): ``hi_b`` or ``lo_b`` in every entry.
        """
        return self.search(perturbation, weight, offset, consts)[0]

    def search(self, perturbation, weight, offset, consts):
        """The searched corner and its score.

        Args: as :meth:`__call__`.

        Returns:
            ``(corner, score)``: the corner (p,) and ``weight * perturbation(corner)``.
        """
        nominal, lo, hi = consts["nominal"], consts["lo"], consts["hi"]
        p = lo.shape[0]

        def score(th):
            return weight * perturbation(th)

        if p == 0:
            return lo, score(lo)
        nominal_score, gradient = jax.value_and_grad(score)(nominal)
        gain = gradient * (hi - lo)  # linearised gain of hi_b over lo_b
        scale = jnp.sum(jnp.abs(gain)) + jnp.abs(nominal_score)
        upward = gain > _tie_tolerance(scale[None], offset)  # roundoff gradients are ties: lo
        start = jnp.where(upward, hi, lo)
        rounds = self.rounds(p)
        if rounds == 0:
            return start, score(start)
        flip = jnp.eye(p, dtype=bool)

        def body(carry):
            bits, current, done, count = carry
            flipped = bits[None, :] != flip  # (p, p): row b flips bit b
            scores = jax.vmap(score)(jnp.where(flipped, hi[None, :], lo[None, :]))
            best = jnp.argmax(scores)
            tol = _tie_tolerance(jnp.append(scores, current), offset)
            better = scores[best] > current + tol
            bits = jnp.where(better, flipped[best], bits)
            current = jnp.where(better, scores[best], current)
            return bits, current, ~better, count + 1

        def keep_going(carry):
            _, _, done, count = carry
            return ~done & (count < rounds)

        init = (upward, score(start), jnp.asarray(False), jnp.asarray(0, jnp.int32))
        bits, best_score, _, _ = jax.lax.while_loop(keep_going, body, init)
        return jnp.where(bits, hi, lo), best_score

    def estimate_memory(self, params: UncertainRobot, *, mode: str, itemsize: int) -> int:
        """Estimated peak bytes of the working set of one end step's window.

        One window step evaluates ``p + 2`` corners (the flips, the current
        one, the gradient) on each of the ``4n`` tracks, so every intermediate
        holds ``4n (p + 2)`` values; nothing grows with ``2^p``. XLA's buffer
        analysis (float64, one and four end steps per batch) measured, in units
        of ``4n (p + 2)`` values: 42-70 for the planar arm's closed-form
        dynamics in ``coupled`` mode (n = 1..6), and about ``3 n^2`` (52 at
        n = 2, 771 at n = 16, 3068 at n = 32) for a general linear solve or in
        ``per_joint`` mode. The estimate uses ``2n^2 + 8n + 96`` and
        ``4n^2 + 8n + 96`` units plus 64 KiB for the window's own data: it errs
        high by 1.3-4x.

        Args:
            params: the robot and its box (as passed to the engine).
            mode: ``"coupled"`` or ``"per_joint"``.
            itemsize: bytes per float (8 for float64).

        Returns:
            Bytes, an int.
        """
        n, p = params.n_joints, params.n_params
        if mode == "coupled" and params.model.forward_dynamics is not None:
            per_value = 2 * n * n + 8 * n + 96
        else:
            per_value = 4 * n * n + 8 * n + 96
        return _WINDOW_DATA_BYTES + 4 * n * (p + 2) * per_value * int(itemsize)


_WINDOW_DATA_BYTES = 64 * 2**10
"""Allowance for the window's own arrays and XLA's small buffers, per end step."""

CLOSED_FORM_MAX_LINKS = 6
"""Above this many links the search evaluates a model by a general linear solve.

The arm's closed-form forward dynamics is written out element by element
(``O(n^3)`` scalar operations, fast for ``vmap`` over many corners), and XLA's
compile time grows steeply with it: about 37 s for the engine's single
evaluation at 16 links, and over 10 minutes once the search's gradient and
flips are added. ``solve(M, tau - h)`` is the same function (the model's
contract) to roundoff, compiles in seconds at any size, and at 8 links and
above also runs faster per end step.
"""


def search_robot(params: UncertainRobot) -> UncertainRobot:
    """The robot the search evaluates: ``params``, minus the closed form above
    :data:`CLOSED_FORM_MAX_LINKS` links.

    Args:
        params: the robot and its box.

    Returns:
        ``params`` itself, or for a model with a closed form and more than
        :data:`CLOSED_FORM_MAX_LINKS` links a copy whose model has no
        ``forward_dynamics`` (the engine then solves ``M qdd = tau - h``).
    """
    model = differentiable_model(params.model, CLOSED_FORM_MAX_LINKS)
    return params if model is params.model else dataclasses.replace(params, model=model)


def corner_search_bounds(
    traj: Trajectory,
    params: UncertainRobot,
    *,
    mode: str = "coupled",
    window: int = 100,
    noise_lo=0.0,
    noise_hi=0.0,
    max_rounds: int | None = None,
    memory_budget: int = DEFAULT_MEMORY_BUDGET,
    chunk_size: int | None = None,
    progress: bool = False,
) -> Bounds:
    """RMI bounds with the extreme corner searched (gradient sign, then single-bit flips).

    Everything but the corner choice is :func:`rmijax.rmi` (same windows,
    costate, tracks, batching, checks); see the module docstring.

    Args:
        traj: the desired motion and its nominal response.
        params: any robot and its parameter box (``p`` parameters).
        mode: ``"coupled"`` (default) or ``"per_joint"``.
        window: ``N``, steps per window (>= 1).
        noise_lo, noise_hi: sensor noise bounds, scalar, ``(2,)`` (encoder rad,
            tachometer rad/s) or ``(n, 2)``; added as ``lower + noise_lo``,
            ``upper + noise_hi``.
        max_rounds: flip rounds per decision (int >= 0); default ``p``; 0 keeps
            the gradient-sign corner.
        memory_budget: bytes allowed for one batch of end steps.
        chunk_size: end steps per batch; default from ``memory_budget``.
        progress: show a progress bar over batches (eager calls only).

    Returns:
        :class:`~rmijax.methods.base.Bounds`, each field (T+1, n, 2).

    Raises:
        ValueError, TypeError: invalid inputs (the message names the argument),
            e.g. ``max_rounds`` negative or not an integer.
        ProblemTooLargeError: one end step does not fit ``memory_budget``.
        DivergedError: the bounds are not finite.
    """
    return engine.rmi(
        traj,
        search_robot(params),
        mode=mode,
        window=window,
        noise_lo=noise_lo,
        noise_hi=noise_hi,
        memory_budget=memory_budget,
        chunk_size=chunk_size,
        progress=progress,
        search=LocalSearch(_check_max_rounds(max_rounds)),
    )


def corner_search_step(
    traj: Trajectory,
    params: UncertainRobot,
    t_f,
    *,
    mode: str = "coupled",
    window: int = 100,
    noise_lo=0.0,
    noise_hi=0.0,
    max_rounds: int | None = None,
) -> Bounds:
    """Corner-search bounds of one end step ``t_f`` (the online form, as :func:`rmijax.rmi_step`).

    Returns:
        :class:`~rmijax.methods.base.Bounds`, each field (n, 2).
    """
    return engine.rmi_step(
        traj,
        search_robot(params),
        t_f,
        mode=mode,
        window=window,
        noise_lo=noise_lo,
        noise_hi=noise_hi,
        search=LocalSearch(_check_max_rounds(max_rounds)),
    )


# --------------------------------------------------------------------------
# Agreement with the exhaustive choice (a diagnostic for the comparison)
# --------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class _AgreementProbe:
    """Chooser that returns the exhaustive corner and reports whether the search agrees.

    Per decision, whether the searched corner equals the enumerated one and
    whether its score is within the tie tolerance of the enumerated one's go to
    :data:`_COUNTS` through ``jax.debug.callback`` (batched arrays under
    ``vmap``). The tracks therefore follow exact RMI.
    """

    search: LocalSearch

    def __call__(self, perturbation, weight, offset, consts):
        corners = corner_tensor(consts["lo"], consts["hi"])
        exact = enumerate_corners(perturbation, weight, offset, {"corners": corners})
        found, found_score = self.search.search(perturbation, weight, offset, consts)
        exact_score = weight * perturbation(exact)
        tol = _tie_tolerance(jnp.stack([exact_score, found_score]), offset)
        agree = jnp.all(found == exact)
        tied = found_score >= exact_score - tol
        jax.debug.callback(_report, agree, tied)
        return exact


_COUNTS = collections.Counter()
"""Decisions seen by :class:`_AgreementProbe` since :func:`corner_agreement` reset it."""


_COUNTS_LOCK = threading.Lock()


def _report(agree, tied):
    """Count decisions; XLA may run callbacks on several threads at once."""
    with _COUNTS_LOCK:
        _COUNTS["decisions"] += int(np.size(agree))
        _COUNTS["agree"] += int(np.sum(agree))
        _COUNTS["tied"] += int(np.sum(tied))


@functools.partial(jax.jit, static_argnames=("mode", "width", "search", "model", "dt"))
def _windows(u, x_n, qdd_n, starts, consts, *, mode, width, search, model, dt):
    """Window extremes (E, 2, n, 2) of end steps ``starts + width`` (all steps active)."""

    def one(start):
        u_win = jax.lax.dynamic_slice_in_dim(u, start, width, 0)
        xn_win = jax.lax.dynamic_slice_in_dim(x_n, start, width, 0)
        qddn_win = jax.lax.dynamic_slice_in_dim(qdd_n, start, width, 0)
        active = jnp.ones((width,), bool)
        return engine.window_extremes(
            u_win,
            xn_win,
            qddn_win,
            active,
            x_n[start],
            consts,
            model=model,
            mode=mode,
            dt=dt,
            search=search,
        )

    return jax.vmap(one)(starts)


def _check_end_steps(end_steps, n_steps):
    steps = np.asarray(end_steps)
    if steps.ndim != 1 or steps.size == 0 or not np.issubdtype(steps.dtype, np.integer):
        raise ValueError(
            f"end_steps must be a non-empty 1-D sequence of integer end steps, got {end_steps!r}"
        )
    bad = steps[(steps < 0) | (steps > n_steps)]
    if bad.size:
        raise ValueError(
            f"end_steps holds {int(bad[0])}, outside the trajectory's end steps [0, {n_steps}]"
        )
    return steps.astype(np.int64)


def corner_agreement(
    traj: Trajectory,
    params: UncertainRobot,
    end_steps,
    *,
    mode: str = "coupled",
    window: int = 100,
    max_rounds: int | None = None,
) -> dict:
    """How often the corner search picks the exhaustive corner, and what a miss costs.

    Along the exact RMI tracks of the given end steps (enumerating all ``2^p``
    corners, so keep ``p`` small), every decision (end step, track, active
    window step) is made both ways and compared. Then the corner-search bounds
    of the same end steps are compared with the exact ones.

    Args:
        traj: the desired motion and its nominal response.
        params: the robot and its box (enumerated: the engine's memory check applies).
        end_steps: (E,) integer end steps in ``[0, T]``.
        mode: ``"coupled"`` or ``"per_joint"``.
        window: ``N``, steps per window.
        max_rounds: as :func:`corner_search_bounds`.

    Returns:
        dict with
        ``decisions``: int, the number of decisions compared
        (``4n * sum(min(t_f, N))``);
        ``agree``: fraction of them where the searched corner vector equals
        the exhaustive one (1.0 when there are none);
        ``agree_score``: fraction where the searched corner's score is within
        the tie tolerance of the exhaustive one (a tie or an agreement);
        ``max_abs_error``: largest ``|searched - exact|`` over the lower and
        upper bounds of the end steps (rad, rad/s);
        ``max_rel_error``: the same relative to the exact band width, where
        the width is > 0 (0.0 if nowhere);
        ``end_steps`` (E,), ``exact`` and ``searched``: :class:`Bounds` with
        fields (E, n, 2) (no noise).

    Raises:
        ValueError, TypeError: invalid inputs, naming the argument.
        ProblemTooLargeError: the enumeration does not fit the default memory budget.
    """
    search = LocalSearch(_check_max_rounds(max_rounds))
    dtype, _, _ = engine._validate(traj, params, mode, window, 0.0, 0.0, search)
    params = search_robot(params)
    traj, params = engine._cast(traj, params, dtype)
    engine.check_memory(params, mode=mode, window=window, dtype=dtype, search="enumerate")
    steps = _check_end_steps(end_steps, traj.n_steps)
    n = traj.n_joints
    probe = _AgreementProbe(search)
    jax.effects_barrier()  # no callback of an earlier call may land in this count
    _COUNTS.clear()
    widths = np.minimum(steps, window)
    exact = np.empty((steps.size, 2, n, 2))
    searched = np.empty((steps.size, 2, n, 2))
    x_n = np.asarray(traj.x_n)
    for width in np.unique(widths):
        rows = np.flatnonzero(widths == width)
        if width == 0:  # t_f = 0: the bounds are the nominal
            exact[rows] = searched[rows] = x_n[0][None, None]
            continue
        starts = jnp.asarray(steps[rows] - width)
        for chooser, out in ((probe, exact), (search, searched)):
            consts = engine.window_constants(
                params, traj.kp, traj.kd, traj.dt, int(width), search=chooser
            )
            extremes = _windows(
                traj.u_d,
                traj.x_n,
                traj.qdd_n,
                starts,
                consts,
                mode=mode,
                width=int(width),
                search=chooser,
                model=params.model,
                dt=traj.dt,
            )
            out[rows] = np.asarray(extremes)
    jax.effects_barrier()
    nominal = x_n[steps]
    exact_bounds, searched_bounds = (
        Bounds(lower=e[:, 1], upper=e[:, 0], nominal=nominal, crossed=e[:, 0] < e[:, 1], dt=traj.dt)
        for e in (exact, searched)
    )
    error = np.abs(searched - exact)  # (E, 2, n, 2)
    width = (exact[:, 0] - exact[:, 1])[:, None]  # (E, 1, n, 2)
    width = np.broadcast_to(width, error.shape)
    positive = width > 0
    relative = np.divide(error, width, out=np.zeros_like(error), where=positive)
    decisions = int(_COUNTS["decisions"])
    expected = 4 * n * int(np.sum(widths))
    if decisions != expected:  # a callback lost or doubled: never report a wrong fraction
        raise RuntimeError(f"counted {decisions} decisions, expected {expected}")
    return dict(
        decisions=decisions,
        agree=_COUNTS["agree"] / decisions if decisions else 1.0,
        agree_score=_COUNTS["tied"] / decisions if decisions else 1.0,
        max_abs_error=float(np.max(error)),
        max_rel_error=float(np.max(relative)),
        end_steps=steps,
        exact=exact_bounds,
        searched=searched_bounds,
    )
