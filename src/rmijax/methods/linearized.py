"""Linearized bounds: first-order parameter sensitivity of the windowed closed loop.

For end step ``t_f`` and window start ``k0 = max(0, t_f - N)`` (SPEC section 5)
the true coupled plant with *constant* parameters ``th`` runs from
``x(k0) = x_n(k0)``:
``x(k+1) = A x(k) + B u_d(k) + dt e2 gv(x(k), u_d(k); th)``, with the coupled
``gv`` of SPEC section 4. Its outputs ``y(t_f; th) = c x(t_f)`` are linearised
at the nominal parameters ``th_n`` (where ``gv = 0``, so ``y(t_f; th_n) =
x_n(t_f)``): ``S = dy/dth`` (n, 2, p) by forward-mode autodiff, ``p`` tangent
tracks. With ``d+ = hi - th_n >= 0`` and ``d- = lo - th_n <= 0``:

    upper_lin = y_n + sum_b max(S_b d+_b, S_b d-_b)
    lower_lin = y_n + sum_b min(S_b d+_b, S_b d-_b)

These are the exact extremes of the linearised output over the box, reached
at the linearisation's extreme corner ``th*`` of each output and extreme
(``hi_b`` where its term is the larger, ``lo_b`` otherwise; terms equal to within
``eps^(2/3)`` of the output's linear range are ties and take ``lo_b``,
:func:`margin_corners`).
The *remainder margin* runs the true window once at each ``th*`` and widens the
bound outwards by ``|y(th*) - y_lin(th*)|``, where ``y_lin(th*)`` is the
bound itself: the upper bound by its own corner's remainder, the lower by its
own. Then the bound also contains the true output at ``th*``.

Not a guarantee: the true output may peak inside the box (non-monotone in a
parameter, e.g. the tachometer outputs) or at a corner other than ``th*``,
and the second-order remainder elsewhere in the box can exceed the one
measured at ``th*``. Cost per end step: one nominal track, ``p`` tangent
tracks and (with the margin) ``4n`` corner runs over the window, i.e.
``O(p + n)`` tracks of dimension ``2n`` instead of RMI's ``2^p`` corners
per step, so its cost is polynomial in the links.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from rmijax import _checks
from rmijax.control import closed_loop_step, coupled_perturbation
from rmijax.methods import rmi as engine
from rmijax.methods._keys import tie_tolerance
from rmijax.methods.base import Bounds
from rmijax.robots.box import UncertainRobot
from rmijax.trajectory import Trajectory

__all__ = [
    "CLOSED_FORM_MAX_JOINTS",
    "differentiable_model",
    "estimate_memory",
    "linearized_bounds",
    "window_output",
]

_MAX_BATCH = 256

TANGENT_BATCH = 16
"""Tangent directions pushed through one window together. With all ``p`` at once,
every step solves one matrix for ``p`` right-hand sides, and XLA's CPU
triangular solve goes multi-threaded from ``n p >= 1024`` on: on a loaded
2-core machine each such call stalled ~8 ms (a 32 x 32 solve with 64
right-hand sides: 8 ms; with 16: 0.01 ms), making 32 links 4.7x slower."""

CLOSED_FORM_MAX_JOINTS = 6
"""Largest robot whose closed-form ``forward_dynamics`` the windows differentiate;
bigger ones solve ``M qdd = tau - h`` (see :func:`differentiable_model`)."""


def window_output(th, u_win, active, x0, *, model, nominal, kp, kd, dt, remat=False):
    """The true coupled closed loop with constant parameters over one window: x(t_f) (n, 2).

    Step ``s`` of the window is time ``k = t_f - N + s``; inactive steps
    (``k < 0``) leave the state unchanged, as in :func:`rmijax.methods.rmi.window_extremes`.

    Args:
        th: (p,) constant true parameters.
        u_win: (N, n) feed-forward ``u_d(k)`` in rad/s^2.
        active: (N,) bool, False for steps before the run.
        x0: (n, 2) the window's start ``x_n(k0)``: positions (rad), velocities (rad/s).
        model: the :class:`~rmijax.robots.model.RobotModel` (static).
        nominal: (p,) the controller's parameters ``th_n``.
        kp, kd: (n,) gains; dt: the step in s.
        remat: recompute each step in reverse mode (``jax.checkpoint``), so that
            a gradient keeps one state per step instead of every intermediate.

    Returns:
        (n, 2) the state at the window's end ``t_f``.
    """

    def step(x, inputs):
        u, on = inputs
        q, qd = x[:, 0], x[:, 1]
        gv = coupled_perturbation(model, th, nominal, q, qd, u, kp, kd)
        nxt = jnp.stack(closed_loop_step(q, qd, u, gv, kp, kd, dt), axis=-1)
        return jnp.where(on, nxt, x), None

    final, _ = jax.lax.scan(jax.checkpoint(step) if remat else step, x0, (u_win, active))
    return final


def differentiable_model(model, closed_form_max_joints):
    """``model``, without its closed-form ``forward_dynamics`` above a number of joints.

    Without it ``RobotModel.accelerations`` solves ``M(q; th) qdd = tau - h``
    with the model's own ``mass_matrix`` and ``bias``. The planar arm's
    element-by-element factorisation differentiates badly: forward mode for
    ``p`` tangents took over 20 GB to compile at 16 links, and reverse mode
    at 6 links ran 50x slower than through a batched solve.
    """
    if model.forward_dynamics is not None and model.n_joints > closed_form_max_joints:
        return dataclasses.replace(model, forward_dynamics=None)
    return model


def _sensitivity(run, nominal):
    """``y(th_n)`` (n, 2) and ``S = dy/dth`` (n, 2, p): ``p`` tangent tracks.

    The tangents go :data:`TANGENT_BATCH` at a time (one primal track per batch).
    """
    p = nominal.shape[0]
    basis = jnp.eye(p, dtype=nominal.dtype)
    outputs, tangents = jax.lax.map(
        lambda e: jax.jvp(run, (nominal,), (e,)), basis, batch_size=min(TANGENT_BATCH, p)
    )
    return outputs[0], jnp.moveaxis(tangents, 0, -1)


def margin_corners(up_term, down_term, lo, hi):
    """The linearisation's extreme corner ``th*`` of every output and extreme.

    Args:
        up_term, down_term: ``S_b (hi_b - th_n_b)`` and ``S_b (lo_b - th_n_b)``, shape
            ``(n, 2, p)`` (joint, sensor, parameter).
        lo, hi: the box, shape ``(p,)``.

    Returns:
        ``(2, n, 2, p)``: ``[max, min]`` corners; the maximum's takes ``hi_b`` where
        ``up_term`` is the larger, the minimum's where it is the smaller, by more than
        the tie tolerance ``eps^(2/3)`` times the output's linear range ``sum_b |up_b -
        down_b|`` (SPEC section 2's relative tolerance); ties take ``lo_b``. Without the
        tolerance, terms that are equal in exact arithmetic (a parameter the output does
        not depend on, such as the friction of a joint at rest: ``S_b`` of 1e-18 relative)
        let roundoff choose the corner, and the remainder margin moved with any change
        of the solve's rounding.
    """
    gap = up_term - down_term
    tol = tie_tolerance(jnp.sum(jnp.abs(gap), axis=-1, keepdims=True), 0.0)
    hi_b, lo_b = jnp.broadcast_to(hi, gap.shape), jnp.broadcast_to(lo, gap.shape)
    return jnp.stack([jnp.where(gap > tol, hi_b, lo_b), jnp.where(gap < -tol, hi_b, lo_b)])


def _end_step(t_f, data, model, window, dt, margin):
    """Linearised (and margin-widened) extremes of one end step: (2, n, 2).

    Axes: [max/min, joint, sensor].
    """
    nominal, lo, hi = data["nominal"], data["lo"], data["hi"]
    u_win = jax.lax.dynamic_slice_in_dim(data["u"], t_f, window, 0)
    active = (t_f - window + jnp.arange(window)) >= 0
    x0 = data["x_n"][jnp.maximum(t_f - window, 0)]
    run = functools.partial(
        window_output,
        u_win=u_win,
        active=active,
        x0=x0,
        model=model,
        nominal=nominal,
        kp=data["kp"],
        kd=data["kd"],
        dt=dt,
    )
    y_n, sens = _sensitivity(run, nominal)  # (n, 2), (n, 2, p)
    up_term = sens * (hi - nominal)[None, None, :]
    down_term = sens * (lo - nominal)[None, None, :]
    upper = y_n + jnp.sum(jnp.maximum(up_term, down_term), axis=-1)
    lower = y_n + jnp.sum(jnp.minimum(up_term, down_term), axis=-1)
    if margin:
        n, p = y_n.shape[0], nominal.shape[0]
        corners = margin_corners(up_term, down_term, lo, hi)  # (2, n, 2, p)
        runs = jax.vmap(run)(corners.reshape(4 * n, p)).reshape(2, n, 2, n, 2)
        joint, sensor = np.meshgrid(np.arange(n), np.arange(2), indexing="ij")
        own = runs[:, joint, sensor, joint, sensor]  # (2, n, 2): each run's own output
        upper = upper + jnp.abs(own[0] - upper)
        lower = lower - jnp.abs(own[1] - lower)
    return jnp.stack([upper, lower])


def _window_data(traj, params, window):
    """The arrays every window needs; ``u`` padded in front so any end step slices ``N`` rows.

    (``engine._window_data`` would build the ``(2^p, p)`` corner tensor here.)
    """
    pad = jnp.zeros((window, traj.n_joints), traj.u_d.dtype)
    return dict(
        u=jnp.concatenate([pad, traj.u_d], axis=0),
        x_n=traj.x_n,
        nominal=params.nominal,
        lo=params.lo,
        hi=params.hi,
        kp=traj.kp,
        kd=traj.kd,
    )


def _end_step_fn(traj, params, window, margin):
    data = _window_data(traj, params, window)
    model = differentiable_model(params.model, CLOSED_FORM_MAX_JOINTS)
    return functools.partial(
        _end_step, data=data, model=model, window=window, dt=traj.dt, margin=margin
    )


@functools.partial(jax.jit, static_argnames=("window", "batch", "margin"))
def _linearized_all(traj, params, noise_lo, noise_hi, *, window, batch, margin):
    fn = _end_step_fn(traj, params, window, margin)
    extremes = jax.lax.map(fn, jnp.arange(traj.n_steps + 1), batch_size=batch)
    return engine._assemble(extremes, traj.x_n, noise_lo, noise_hi, traj.dt)


@functools.partial(jax.jit, static_argnames=("window", "margin"))
def _linearized_chunk(traj, params, end_steps, *, window, margin):
    return jax.vmap(_end_step_fn(traj, params, window, margin))(end_steps)


def estimate_memory(params: UncertainRobot, *, margin=True, dtype=None) -> int:
    """Estimated peak bytes of one end step's working set.

    ``1 + p`` (nominal and tangent) tracks plus ``4n`` corner runs with the
    margin, each holding ``O(n^2)`` intermediates of the dynamics (mass
    matrices, their factor and tangents) at a time: counted as
    ``5 n^2 + 8 n + 16`` values per track plus 64 KiB. XLA's buffer analysis
    (float64, preset arm, margin on) measured 0.04, 0.96 and 6.3 MiB per end
    step at n = 6, 16 and 32; the estimate gives 0.13, 1.1 and 8.0 MiB.
    """
    n, p = params.n_joints, params.n_params
    itemsize = jnp.dtype(dtype or params.dtype).itemsize
    tracks = 1 + p + (4 * n if margin else 0)
    return 64 * 2**10 + tracks * (5 * n * n + 8 * n + 16) * itemsize


def _batch(params, margin, dtype, n_end, chunk_size):
    chunk_size = _checks.chunk_size(chunk_size, "end steps")
    if chunk_size is not None:
        return min(chunk_size, n_end)
    per_end_step = estimate_memory(params, margin=margin, dtype=dtype)
    return int(max(1, min(engine.DEFAULT_MEMORY_BUDGET // per_end_step, _MAX_BATCH, n_end)))


def _check_finite(bounds):
    where = _checks.first_non_finite(bounds.upper, bounds.lower)
    if where is not None:
        step, joint, sensor = where
        raise engine.DivergedError.at(
            where,
            f"linearized bounds are not finite (end step {step}, joint {joint} "
            f"{engine.DivergedError.SENSORS[sensor]}): the constant-parameter window diverged. "
            "Narrow the parameter box (lo, hi), shorten the window or use stiffer gains.",
        )


def linearized_bounds(
    traj: Trajectory,
    params: UncertainRobot,
    *,
    mode: str = "coupled",
    window: int = 100,
    noise_lo=0.0,
    noise_hi=0.0,
    margin: bool = True,
    chunk_size: int | None = None,
    progress: bool = False,
) -> Bounds:
    """Bounds from the first-order parameter sensitivity of every end step's window.

    See the module docstring for the definition. This is **not** a guarantee:
    the true output may peak inside the box (non-monotone outputs such as the
    tachometers) or at a corner other than the linearisation's, and the
    remainder margin is measured at one corner only. Cost: ``O(p + n)``
    window tracks per end step (``1 + p + 4n``; ``1 + p`` without margin).

    Args:
        traj: the desired motion and its nominal response.
        params: the robot and its parameter box (any :class:`~rmijax.robots.model.RobotModel`).
        mode: must be ``"coupled"``: the method describes the true plant.
        window: ``N``, steps per window (>= 1).
        noise_lo, noise_hi: sensor noise bounds, scalar, ``(2,)`` (encoder rad,
            tachometer rad/s) or ``(n, 2)``; added as ``upper + noise_hi``,
            ``lower + noise_lo``.
        margin: widen each bound by the remainder ``|y(th*) - y_lin(th*)|`` at its
            extreme corner (``4n`` nonlinear runs); False gives the pure
            first-order band.
        chunk_size: end steps per batch; default from a 4 GiB working-set budget
            (at most 256).
        progress: show a progress bar over batches (eager calls only).

    Returns:
        :class:`~rmijax.methods.base.Bounds` with ``lower``, ``upper``, ``nominal``,
        ``crossed`` of shape (T+1, n, 2); ``[..., 0]`` encoder (rad),
        ``[..., 1]`` tachometer (rad/s).

    Raises:
        TypeError, ValueError: invalid inputs, ``mode="per_joint"`` included
            (the message names the argument).
        DivergedError: the bounds are not finite (only checked outside ``jit``).
    """
    if mode != "coupled":
        raise ValueError(
            f"linearized_bounds needs mode='coupled', got mode={mode!r}: it linearises the "
            "true coupled plant with constant parameters, in which every joint moves its "
            "neighbours; per_joint (the paper's RMI simplification) takes the other joints "
            "from the nominal trajectory and describes no physical plant"
        )
    # search="enumerate" only selects the engine's checks that apply to any model size.
    dtype, lo, hi = engine._validate(
        traj, params, mode, window, noise_lo, noise_hi, search="enumerate"
    )
    margin = _checks.boolean("margin", margin)
    progress = _checks.boolean("progress", progress)
    traj, params = engine._cast(traj, params, dtype)
    n_end = traj.n_steps + 1
    batch = _batch(params, margin, dtype, n_end, chunk_size)
    window = min(int(window), traj.n_steps)  # a longer window gives the same windows
    concrete = all(_checks.is_concrete(a) for a in jax.tree_util.tree_leaves((traj, params)))
    if progress and concrete:
        bounds = _with_progress(traj, params, lo, hi, window, batch, margin)
    else:
        bounds = _linearized_all(traj, params, lo, hi, window=window, batch=batch, margin=margin)
    _check_finite(bounds)
    return bounds


def _with_progress(traj, params, lo, hi, window, batch, margin):
    from tqdm.auto import tqdm

    n_end = traj.n_steps + 1
    pieces = []
    with tqdm(total=n_end, desc=f"linearized n={traj.n_joints}", unit="step") as bar:
        for chunk in range(math.ceil(n_end / batch)):
            ends = np.minimum(np.arange(chunk * batch, (chunk + 1) * batch), n_end - 1)
            extremes = _linearized_chunk(
                traj, params, jnp.asarray(ends), window=window, margin=margin
            )
            extremes.block_until_ready()
            pieces.append(extremes)
            bar.update(min(batch, n_end - chunk * batch))
    extremes = jnp.concatenate(pieces, axis=0)[:n_end]
    return engine._assemble(extremes, traj.x_n, lo, hi, traj.dt)
