"""Worst case of the true plant: an inner estimate of the reachable range of an output.

The physical robot has *constant* parameters somewhere in the box ``[lo, hi]``.
For one output ``y = x_j,s(t; th)`` (joint ``j``, sensor ``s``) of the
fault-free closed loop run from ``x(0) = x_d(0)`` by :func:`rmijax.simulate`,
projected gradient ascent over ``th`` searches ``max_th y`` and ``min_th y``.
Every value reported is the output of an actual :func:`rmijax.simulate` run
with parameters in the box, so ``[low, high]`` lies inside the true reachable
range: a band that misses ``[low, high]`` misses a robot that can exist, and
``high - low`` is the least width a band needs there.

Search, for each output, extreme and start (given rows, all ``2^p`` corners
when ``p <= 6``, the nominal, and seeded uniform draws): ``iterations`` steps
``th <- clip(th + eta_i (hi - lo) sign(dy/dth), lo, hi)`` (descent for the
minimum), ``eta_i`` falling geometrically from 0.25 to 0.002 of the box,
keeping the best value seen. All outputs, extremes, starts and times are one
``vmap`` in one jitted program; gradients are ``jax.grad`` through the
``lax.scan`` of the closed loop (its step rematerialised, so memory holds one
state per step and track).

The search differentiates the last ``H`` steps before ``t`` only, run from the
nominal state ``x_n(t - H)`` as RMI's windows are: the closed loop forgets
older parameter effects like ``h rho^h`` (``rho`` the largest spectral radius
of the joints' ``A_i``), and ``H`` is the first ``h`` with ``(h + 1) rho^h <=
1e-7`` (204 steps for the default gains and ``dt``; the whole run when that is
shorter). On the preset arms (2 and 6 links, random parameters in the box)
this windowed output differs from the whole run by at most 1e-7 and 3e-7
(rad, rad/s), against ranges of 1e-2. It guides the search only, at ``O(H)``
instead of ``O(t / dt)`` steps per gradient: the starts and each search's
final pick are then run by :func:`rmijax.simulate` over the whole run, and
the reported values come from those runs.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from rmijax import _checks
from rmijax.methods.base import check_types
from rmijax.methods.linearized import differentiable_model, window_output
from rmijax.plant import simulate
from rmijax.robots.box import UncertainRobot
from rmijax.robots.check import check_model
from rmijax.trajectory import Trajectory

__all__ = [
    "CLOSED_FORM_MAX_JOINTS",
    "MAX_CORNER_PARAMS",
    "WorstCase",
    "forget_steps",
    "worst_case",
    "worst_case_table",
]

MAX_CORNER_PARAMS = 6
"""All ``2^p`` corners are starts only when ``p`` is at most this (64 corners)."""

CLOSED_FORM_MAX_JOINTS = 3
"""Largest robot whose closed-form ``forward_dynamics`` the search differentiates in
reverse mode; bigger ones solve ``M qdd = tau - h`` (4 links: 2.5x faster, 6 links: 50x)."""

FORGET_TOLERANCE = 1e-7
"""``(h + 1) rho^h`` below which the search's window forgets older steps."""

_STEP_FIRST, _STEP_LAST = 0.25, 0.002
"""Ascent step as a fraction of the box width, at the first and the last iteration."""


class WorstCase(NamedTuple):
    """Extremes of one output over constant parameters in the box, found by search.

    Attributes:
        low, high: the smallest and largest output reached (rad for an encoder,
            rad/s for a tachometer); an inner estimate of the reachable range.
        th_low, th_high: (p,) parameters in the box whose runs give them.
    """

    low: float
    high: float
    th_low: jax.Array
    th_high: jax.Array


def forget_steps(kp, kd, dt, n_steps, tolerance=FORGET_TOLERANCE) -> int:
    """Steps after which the closed loop has forgotten a perturbation: the search window ``H``.

    Args:
        kp, kd: (n,) gains; dt: the step in s; n_steps: ``T``, the cap.
        tolerance: the bound on ``(h + 1) rho^h`` (``rho``: largest spectral
            radius of the joints' ``A_i``).

    Returns:
        The first ``h >= 1`` with ``(h + 1) rho^h <= tolerance``, at most ``n_steps``.
    """
    rho = float(np.max(_checks.closed_loop_radius(kp, kd, dt)))
    h = np.arange(1, int(n_steps) + 1)
    below = np.flatnonzero((h + 1) * rho**h <= tolerance)
    return int(h[below[0]]) if below.size else int(n_steps)


def _ascend(th, objective, lo, hi, iterations):
    """Projected sign-gradient ascent of ``objective`` from ``th``: best value and its th (p,)."""
    value_and_grad = jax.value_and_grad(objective)
    decay = (_STEP_LAST / _STEP_FIRST) ** (1.0 / max(iterations - 1, 1))

    def body(i, carry):
        th, best, best_th = carry
        value, grad = value_and_grad(th)
        better = value > best
        best, best_th = jnp.where(better, value, best), jnp.where(better, th, best_th)
        th = jnp.clip(th + (_STEP_FIRST * decay**i) * (hi - lo) * jnp.sign(grad), lo, hi)
        return th, best, best_th

    init = (th, jnp.asarray(-jnp.inf, th.dtype), th)
    th, best, best_th = jax.lax.fori_loop(0, iterations, body, init)
    value = objective(th)
    better = value > best
    return jnp.where(better, value, best), jnp.where(better, th, best_th)


@functools.partial(jax.jit, static_argnames=("window", "iterations"))
def _search(traj, params, starts, steps, joints, sensors, signs, *, window, iterations):
    """The search for every objective (M,) from every start (S, p): best th (M, p).

    Objective ``m`` is ``signs[m] * x[joints[m], sensors[m]]`` at step
    ``steps[m]``, run over the window of ``window`` steps before it.
    """
    model = differentiable_model(params.model, CLOSED_FORM_MAX_JOINTS)
    u_pad = jnp.concatenate([jnp.zeros((window, traj.n_joints), traj.dtype), traj.u_d], axis=0)
    run = functools.partial(
        window_output,
        model=model,
        nominal=params.nominal,
        kp=traj.kp,
        kd=traj.kd,
        dt=traj.dt,
        remat=True,
    )

    def one_objective(step, joint, sensor, sign):
        u_win = jax.lax.dynamic_slice_in_dim(u_pad, step, window, 0)
        active = (step - window + jnp.arange(window)) >= 0
        x0 = traj.x_n[jnp.maximum(step - window, 0)]

        def objective(th):
            return sign * run(th, u_win, active, x0)[joint, sensor]

        def search(th):
            return _ascend(th, objective, params.lo, params.hi, iterations)

        values, thetas = jax.vmap(search)(starts)
        return thetas[jnp.argmax(values)]

    return jax.vmap(one_objective)(steps, joints, sensors, signs)


def _validate(traj, params):
    check_types(traj, params)
    check_model(params, traj)
    if params.n_joints != traj.n_joints:
        raise ValueError(
            f"traj has {traj.n_joints} joints but params describes a "
            f"{params.n_joints}-joint robot; give one path per joint of the robot"
        )
    dtype = jnp.result_type(traj.dtype, params.dtype)
    return _checks.cast_tree(traj, dtype), _checks.cast_tree(params, dtype)


def _step_of(name, t, traj):
    """The grid step ``round(t / dt)`` of a time ``t`` in s, inside the run."""
    original = t
    try:
        t = float(t) if not isinstance(t, bool) and np.ndim(t) == 0 else None
    except (TypeError, ValueError):
        t = None
    if t is None or not np.isfinite(t):
        raise ValueError(f"{name} must be a finite time in s, got {original!r}")
    step = int(round(t / traj.dt))
    if not 0 <= step <= traj.n_steps:
        raise ValueError(
            f"{name}={t!r} s is outside the run [0, {traj.n_steps * traj.dt:g}] s "
            f"(dt = {traj.dt:g} s)"
        )
    return step


def _starts(params, starts, random_starts, seed):
    """Rows of ``starts``, the corners (``p <= 6``), the nominal and uniform draws: (S, p)."""
    p, dtype = params.n_params, params.dtype
    seed = _checks.seed(seed)
    rows = []
    if starts is not None:
        given = jnp.asarray(starts, dtype)
        if given.ndim != 2 or given.shape[1] != p:
            raise ValueError(
                f"starts must have shape (S, {p}): one parameter vector per row, got shape "
                f"{given.shape}"
            )
        _checks.check_finite("starts", given)
        low, high, values = np.asarray(params.lo), np.asarray(params.hi), np.asarray(given)
        outside = np.argwhere((values < low[None, :]) | (values > high[None, :]))
        if outside.size:
            row, b = (int(v) for v in outside[0])
            raise ValueError(
                f"starts[{row}, {b}] = {float(values[row, b])!r} lies outside the box "
                f"[{float(low[b])!r}, {float(high[b])!r}]; every start must be a parameter "
                "vector in the box"
            )
        rows.append(given)
    if p <= MAX_CORNER_PARAMS:
        rows.append(params.corners)
    rows.append(params.nominal[None, :])
    if (
        isinstance(random_starts, bool)
        or not isinstance(random_starts, (int, np.integer))
        or random_starts < 0
    ):
        raise ValueError(f"random_starts must be an integer >= 0, got {random_starts!r}")
    if random_starts:
        draws = jax.random.uniform(jax.random.PRNGKey(seed), (int(random_starts), p), dtype)
        rows.append(params.lo[None, :] + (params.hi - params.lo)[None, :] * draws)
    return jnp.concatenate(rows, axis=0)


def _extremes(traj, params, starts, steps, joints, sensors, signs, iterations):
    """Best ``signs * y`` per objective (M,) over the starts and the search, from simulate runs.

    Returns:
        ``(values, thetas)``: (M,) in the objective's sign and (M, p).
    """
    window = min(forget_steps(traj.kp, traj.kd, traj.dt, traj.n_steps), max(int(steps.max()), 1))
    found = _search(
        traj,
        params,
        starts,
        jnp.asarray(steps, jnp.int32),
        jnp.asarray(joints, jnp.int32),
        jnp.asarray(sensors, jnp.int32),
        jnp.asarray(signs, params.dtype),
        window=window,
        iterations=iterations,
    )
    candidates = jnp.concatenate([starts, found], axis=0)  # (S + M, p)
    states, _ = simulate(traj, params, candidates)  # (S + M, T+1, n, 2)
    outputs = np.asarray(states)[:, steps, joints, sensors] * signs[None, :]  # (S + M, M)
    n_starts, objectives = starts.shape[0], np.arange(steps.size)
    from_start = np.argmax(outputs[:n_starts], axis=0)  # (M,): ties to the first start
    searched = outputs[n_starts + objectives, objectives]
    best_start = outputs[from_start, objectives]
    use_search = searched > best_start
    values = np.where(use_search, searched, best_start)
    pick = np.where(use_search, n_starts + objectives, from_start)
    return values, candidates[pick]


def worst_case(
    traj: Trajectory,
    params: UncertainRobot,
    output,
    t,
    *,
    starts=None,
    random_starts: int = 8,
    iterations: int = 60,
    seed: int = 0,
) -> WorstCase:
    """Largest and smallest value of one output at one time over constant parameters.

    Projected gradient ascent (and descent) over the box from many starts (see
    the module docstring). An *inner* estimate: ``high`` is at least the
    output of every start, and the :func:`rmijax.simulate` run with
    ``th_high`` gives it; the true maximum may be larger.

    Args:
        traj: the desired motion (the run starts at ``x_d(0)``).
        params: the robot and its parameter box.
        output: ``(joint, sensor)``, 0-based; sensor 0 encoder (rad), 1 tachometer (rad/s).
        t: time in s; the output is taken at step ``round(t / dt)``.
        starts: optional (S, p) parameter vectors in the box to start from
            (e.g. each bound method's extreme corner).
        random_starts: number of seeded uniform draws added to the starts (>= 0).
        iterations: gradient steps per start (>= 1).
        seed: seed of the uniform draws.

    Returns:
        :class:`WorstCase` ``(low, high, th_low, th_high)``.

    Raises:
        TypeError, ValueError: an output out of range, ``t`` outside the run,
            ``starts`` of the wrong shape or outside the box, bad counts.
    """
    traj, params = _validate(traj, params)
    if (
        not isinstance(output, (tuple, list))
        or len(output) != 2
        or not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in output)
    ):
        raise ValueError(f"output must be a (joint, sensor) pair of ints, got {output!r}")
    joint, sensor = (int(v) for v in output)
    if not 0 <= joint < traj.n_joints or sensor not in (0, 1):
        raise ValueError(
            f"output={tuple(output)!r} is out of range: joint must be in "
            f"0..{traj.n_joints - 1} and sensor 0 (encoder) or 1 (tachometer)"
        )
    step = _step_of("t", t, traj)
    iterations = _checks.positive_int("iterations", iterations)
    start_rows = _starts(params, starts, random_starts, seed)
    values, thetas = _extremes(
        traj,
        params,
        start_rows,
        np.full(2, step),
        np.full(2, joint),
        np.full(2, sensor),
        np.array([1.0, -1.0]),
        iterations,
    )
    return WorstCase(
        low=-float(values[1]), high=float(values[0]), th_low=thetas[1], th_high=thetas[0]
    )


def worst_case_table(
    traj: Trajectory,
    params: UncertainRobot,
    times,
    *,
    starts=None,
    random_starts: int = 4,
    iterations: int = 40,
    seed: int = 0,
) -> dict:
    """:func:`worst_case` for every output at each of the given times, in one program.

    Args:
        traj, params: as :func:`worst_case`.
        times: (M,) times in s inside the run.
        starts, random_starts, iterations, seed: as :func:`worst_case` (the
            same starts serve every output and time).

    Returns:
        dict with ``times`` (M,) the grid times in s, ``steps`` (M,) their
        steps, ``low``, ``high`` (M, n, 2) in rad / rad/s, and ``th_low``,
        ``th_high`` (M, n, 2, p) the parameters reaching them.

    Raises:
        TypeError, ValueError: as :func:`worst_case`; ``times`` empty or not 1-D.
    """
    traj, params = _validate(traj, params)
    times = np.asarray(_checks.numbers("times", times, None), dtype=np.float64)
    if times.ndim != 1 or times.size == 0:
        raise ValueError(f"times must be a non-empty 1-D sequence of times in s, got {times!r}")
    steps = np.array([_step_of(f"times[{i}]", t, traj) for i, t in enumerate(times)])
    iterations = _checks.positive_int("iterations", iterations)
    start_rows = _starts(params, starts, random_starts, seed)
    n, m = traj.n_joints, steps.size
    grid = np.meshgrid(steps, np.arange(n), np.arange(2), np.array([1.0, -1.0]), indexing="ij")
    values, thetas = _extremes(
        traj, params, start_rows, *(g.ravel() for g in grid), iterations=iterations
    )
    values = values.reshape(m, n, 2, 2)
    thetas = thetas.reshape(m, n, 2, 2, params.n_params)
    return dict(
        times=steps * traj.dt,
        steps=steps,
        low=-values[..., 1],
        high=values[..., 0],
        th_low=thetas[..., 1, :],
        th_high=thetas[..., 0, :],
    )
