"""The RMI engine: exact Reachable Measurement Interval bounds (SPEC sections 4-5).

For every output (joint ``i``, sensor encoder/tachometer) and end step ``t_f``
RMI runs two tracks (max and min) through the window ``k0 = max(0, t_f - N)
.. t_f``, choosing at every step the parameter corner that maximises (or
minimises) the costate-weighted perturbation ``L(k+1)' e2 gv``.

Shape of the computation: the ``K`` corners are one stacked array; one window
step is a ``vmap`` over the ``4n`` tracks (extreme x joint x sensor) and over
corners; the window is a ``lax.scan``; end steps are independent windows,
batched in chunks sized from a memory budget (``lax.map`` with a batch size);
the whole is ``jit``-compiled. Windows are aligned at their end: step ``s`` of
the scan is time ``k = t_f - N + s``, inactive while ``k < 0``, so every end
step has the same shape and the costate weights depend on ``s`` alone.
"""

from __future__ import annotations

import functools
import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from rmijax import _checks
from rmijax.control import closed_loop_step, computed_torque, servo_command
from rmijax.methods.base import Bounds, DivergedError, ProblemTooLargeError, check_types
from rmijax.methods.choosers import LinearChooser, StructuredChooser, enumerate_corners, resolve
from rmijax.methods.planar_search import FactoredSearch
from rmijax.robots.box import UncertainRobot, corner_tensor, uncertain_indices
from rmijax.robots.check import check_model
from rmijax.trajectory import Trajectory

__all__ = [
    "DEFAULT_MEMORY_BUDGET",
    "MODES",
    "SEARCHES",
    "Bounds",
    "DivergedError",
    "ProblemTooLargeError",
    "check_memory",
    "costate_weights",
    "enumerate_corners",
    "estimate_memory",
    "estimate_seconds",
    "rmi",
    "rmi_step",
    "window_constants",
    "window_extremes",
]

MODES = ("coupled", "per_joint")
"""RMI modes: ``coupled`` (exact, the default) and ``per_joint`` (the paper's)."""

SEARCHES = ("auto", "enumerate")
"""How the extreme corner is found: ``auto`` takes the search the model's declared
structure allows (:mod:`rmijax.methods.choosers`: the planar arm's factored search,
parameters chosen by sign, or enumeration when nothing is declared);
``enumerate`` always evaluates all ``2^p`` corners (the definition). Both return
the same corner."""

DEFAULT_MEMORY_BUDGET = 4 * 2**30
"""Default bytes allowed for the working set of one batch of end steps (4 GiB)."""

_MAX_BATCH = 256


# --------------------------------------------------------------------------
# Validation and set-up
# --------------------------------------------------------------------------


def _validate(traj, params, mode, window, noise_lo, noise_hi, search="auto"):
    check_types(traj, params)
    if mode not in MODES:
        raise ValueError(f"unknown mode {mode!r}; choose one of {MODES}")
    check_search(search, params.model)
    _checks.positive_int("window", window, "steps")
    n = traj.n_joints
    if params.n_joints != n:
        raise ValueError(
            f"traj has {n} joints but params describes a {params.n_joints}-joint robot; "
            "give one path per joint of the robot"
        )
    dtype = jnp.result_type(traj.dtype, params.dtype)
    for name in ("u_d", "x_n", "qdd_n", "kp", "kd"):
        _checks.check_finite(f"traj.{name}", getattr(traj, name))
    _checks.check_stable(traj.kp, traj.kd, traj.dt)
    lo, hi = _checks.noise_interval(noise_lo, noise_hi, n, dtype)
    check_model(params, traj)
    return dtype, lo, hi


def check_search(search, model):
    """Validate the ``search`` option (see :data:`SEARCHES`) for ``model``.

    A callable is also accepted (library-internal): a *chooser*
    ``(perturbation, weight, offset, consts) -> th`` used in place of
    enumeration (see :func:`enumerate_corners`); ``rmijax.bounds`` uses it
    for methods that search the box differently.
    """
    if callable(search):
        return
    if search not in SEARCHES:
        raise ValueError(f"unknown search {search!r}; choose one of {SEARCHES}")
    found = resolve(model, search)
    if isinstance(found, FactoredSearch) and model.n_joints > found.max_links:
        raise ValueError(
            f"exact RMI takes at most {found.max_links} links "
            f"(the arm has {model.n_joints}); its 2^n mass corners per track and step are "
            "out of reach beyond that. Use a method that scales (rmijax.bounds)."
        )


def estimate_memory(
    params: UncertainRobot, *, mode="coupled", window=100, dtype=None, search="auto"
) -> int:
    """Estimated peak bytes of the working set of one end step's window.

    The search taken from the model's structure (or a chooser passed as
    ``search``) may bring its own ``estimate_memory(params, mode=, itemsize=)``:
    the planar arm's factored search is ``O(n^3 2^n)`` coupled and ``O(n 4^n)``
    per_joint (:func:`rmijax.methods.planar_search.estimate_memory`). When corners are
    enumerated, the inner step evaluates every corner on every track: ``4n x K`` values
    per intermediate, and XLA keeps ``O(n^2)`` of them alive at once. Measured
    with XLA's own buffer analysis for the planar arm (``n = 5..7``, float64,
    one end step): about ``0.7 n^2`` such arrays in ``coupled`` mode (closed-form
    dynamics) and ``2.3 n^2`` in ``per_joint`` mode (full ``M`` and ``h`` per
    corner). The estimate uses ``n^2 + 2n + 8`` and ``3n^2 + 4n + 8`` (models
    without a closed form: the latter in both modes) plus 64 KiB, so it
    errs high by about 2x; it grows linearly with the number of end steps per batch.
    """
    del window  # the scan keeps one step's intermediates alive at a time
    if mode not in MODES:
        raise ValueError(f"unknown mode {mode!r}; choose one of {MODES}")
    if not callable(search) and search not in SEARCHES:
        raise ValueError(f"unknown search {search!r}; choose one of {SEARCHES}")
    n, k = params.n_joints, _enumerated_corners(params)
    itemsize = jnp.dtype(dtype or params.dtype).itemsize
    tracks = 4 * n
    found = resolve(params.model, search)
    if hasattr(found, "estimate_memory"):
        return int(found.estimate_memory(params, mode=mode, itemsize=itemsize))
    if mode == "coupled" and params.model.forward_dynamics is not None:
        per_value = n * n + 2 * n + 8
    else:
        per_value = 3 * n * n + 4 * n + 8
    return _WINDOW_DATA_BYTES + tracks * k * itemsize * per_value


def _enumerated_corners(params):
    """Corners enumeration evaluates: ``2^u`` over the ``u`` uncertain parameters
    (certain ones, ``lo == hi``, add none), ``2^p`` when the box is traced."""
    uncertain = uncertain_indices(params)
    return params.n_corners if uncertain is None else 2 ** len(uncertain)


def _evaluated_corners(params, search):
    """Corners the search evaluates per track step (for messages)."""
    found = resolve(params.model, search)
    if isinstance(found, StructuredChooser):
        return found.n_evaluated
    return _enumerated_corners(params)


EVALUATIONS_PER_SECOND = 1e8
"""Dynamics evaluations per second, weighted by ``n^2``, that the time estimate assumes:
a fast machine (a 2-core CPU measured about 1e7), so a refusal means hopeless, not slow."""


def estimate_seconds(params, n_steps, *, mode="coupled", window=100, search="auto"):
    """Optimistic run time (s) of :func:`rmi` over ``n_steps`` steps, or None if not estimated.

    Counted for the searches that evaluate corners: enumeration (``2^u`` corners
    of the ``u`` uncertain parameters) and the structured choosers
    (``2^(p-a) (1 + a)`` values); ``(T+1) min(N, T) 4n`` track steps each, an
    evaluation costing ``n^2`` at :data:`EVALUATIONS_PER_SECOND`. The contracted
    corners of :class:`~rmijax.methods.choosers.LinearChooser` cost 1 each. The planar
    arm's factored search and the corner search scale polynomially: None.
    """
    del mode
    found = resolve(params.model, search)
    n = params.n_joints
    weight = n * n
    if found is enumerate_corners:
        per_step = _enumerated_corners(params)
    elif isinstance(found, LinearChooser):
        # contracted corners: a handful of fused operations each, not a dynamics evaluation
        # (measured on the Panda, p = 22: about 1.5e7 corner-steps/s on the 2-core CPU)
        per_step, weight = found.n_evaluated, 1
    elif isinstance(found, StructuredChooser):
        per_step = found.n_evaluated * (1 + len(found.affine))
    else:
        return None
    evaluations = (n_steps + 1) * min(int(window), n_steps) * 4 * n * per_step
    return evaluations * weight / EVALUATIONS_PER_SECOND


_WINDOW_DATA_BYTES = 64 * 2**10
"""Allowance for the window's own arrays and XLA's small buffers, per end step."""


def check_memory(
    params,
    *,
    mode="coupled",
    window=100,
    dtype=None,
    budget=DEFAULT_MEMORY_BUDGET,
    search="auto",
):
    """Raise :class:`ProblemTooLargeError` if one end step's window does not fit ``budget``."""
    _batch_size(params, mode, window, dtype or params.dtype, budget, 1, None, search=search)


def _size(nbytes):
    """Bytes for a message: ``1.50 GiB``, ``12.0 MiB``, ``64.0 KiB`` or ``100 bytes``."""
    for unit, scale in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if nbytes >= 0.1 * scale:
            return f"{nbytes / scale:.{2 if unit == 'GiB' else 1}f} {unit}"
    return f"{int(nbytes)} bytes"


def _batch_size(params, mode, window, dtype, budget, n_end_steps, chunk_size, *, search="auto"):
    budget = _checks.memory_budget(budget)
    chunk_size = _checks.chunk_size(chunk_size, "end steps")
    per_end_step = estimate_memory(params, mode=mode, window=window, dtype=dtype, search=search)
    if per_end_step > budget:
        raise ProblemTooLargeError(
            f"one end step of this problem needs about {_size(per_end_step)} "
            f"({params.n_joints} joints, {_enumerated_corners(params)} corners of the "
            f"uncertain parameters, mode={mode!r}) but memory_budget is "
            f"{_size(budget)} even at chunk size 1. Raise memory_budget (bytes) if "
            "the machine has the memory, make parameters certain (lo == hi: each halves "
            "the corners) or use a method that scales (rmijax.bounds, e.g. "
            "method='corner_search' or 'linearized')."
        )
    if chunk_size is not None:
        if chunk_size * per_end_step > budget:
            raise ProblemTooLargeError(
                f"chunk_size={chunk_size} needs about "
                f"{_size(chunk_size * per_end_step)}, over memory_budget "
                f"{_size(budget)}; use chunk_size <= {budget // per_end_step} "
                "or leave it None to size it from the budget"
            )
        return min(int(chunk_size), n_end_steps)
    return int(max(1, min(budget // per_end_step, _MAX_BATCH, n_end_steps)))


def costate_weights(kp, kd, dt, window):
    """Velocity part of the costate per window step: (N, n, 2) [step, joint, sensor].

    ``L(k+1) = (A_i')^(N-1-s) c`` for window step ``s``, iterated as
    ``L(k) = A' L(k+1)`` like the definition; ``c = (1, 0)`` for the encoder
    and ``(0, 1)`` for the tachometer. Only the velocity part weighs ``gv``.
    """
    n, dtype = kp.shape[0], kp.dtype
    kp_col, kd_col = kp[:, None], kd[:, None]

    def back(costate, _):
        pos, vel = costate
        prev = (pos + (-kp_col * dt) * vel, dt * pos + (1.0 - kd_col * dt) * vel)
        return prev, vel

    eye = jnp.eye(2, dtype=dtype)
    start = (jnp.broadcast_to(eye[0], (n, 2)), jnp.broadcast_to(eye[1], (n, 2)))
    _, vel_weights = jax.lax.scan(back, start, None, length=window)
    return jnp.flip(vel_weights, 0)  # step s weighs with (A')^(N-1-s) c


def window_constants(params, kp, kd, dt, window, search="auto", uncertain=None):
    """The arrays every window shares: costate weights, the box and, if enumerated, corners.

    The ``(K, p)`` corner tensor is built only when ``search`` enumerates it: a
    chooser or the factored search never needs it (at 16 links it would have
    ``2^32`` rows). ``uncertain`` (a static tuple, :func:`uncertain_indices`)
    limits it to the corners of those parameters: the same chosen corner, tie
    rule included, since corners that differ only in certain parameters are
    the same vector and the lowest index among them has those bits clear.
    """
    consts = dict(
        weights=costate_weights(kp, kd, dt, window),
        nominal=params.nominal,
        lo=params.lo,
        hi=params.hi,
        kp=kp,
        kd=kd,
    )
    if getattr(resolve(params.model, search), "needs_corners", False):
        consts["corners"] = corner_tensor(params.lo, params.hi, uncertain)
    return consts


def _window_data(traj, params, window, search="auto", starts=None, uncertain=None):
    """Arrays one window needs, padded so that any end step slices a fixed length.

    ``traj`` and ``params`` arrive cast to one dtype (:func:`_cast`). ``starts``
    (T+1, n, 2), if given, replaces ``x_n`` as the states the windows start
    from (see :func:`_rmi_from_starts`); RMI itself passes None.
    """

    def pad(x):
        return jnp.concatenate([jnp.zeros((window,) + x.shape[1:], x.dtype), x], axis=0)

    return dict(
        u=pad(traj.u_d),
        x_n=traj.x_n,
        x_start=traj.x_n if starts is None else starts,
        x_pad=pad(traj.x_n),
        qdd_pad=pad(traj.qdd_n),
        **window_constants(params, traj.kp, traj.kd, traj.dt, window, search, uncertain),
    )


def _end_step_fn(traj, params, mode, window, search, starts=None, uncertain=None):
    """The window data and ``t_f -> extremes (2, n, 2)`` of one end step."""
    data = _window_data(traj, params, window, search, starts, uncertain)
    fn = functools.partial(
        _window_extremes,
        data=data,
        model=params.model,
        mode=mode,
        window=window,
        dt=traj.dt,
        search=search,
    )
    return data, fn


def _tracks(n):
    """Track layout: index ``e * 2n + i * 2 + s`` for extreme e (max, min), joint, sensor."""
    extreme, joint, sensor = np.meshgrid(np.arange(2), np.arange(n), np.arange(2), indexing="ij")
    return extreme.ravel(), joint.ravel(), sensor.ravel()


def _window_extremes(t_f, data, model, mode, window, dt, search):
    """``c x_max(t_f)``, ``c x_min(t_f)`` of every output: (2, n, 2) [extreme, joint, sensor].

    Slices end step ``t_f``'s window out of the padded arrays of
    :func:`_window_data` and runs :func:`window_extremes` on it, from the start
    state ``x_start(k0)`` (``x_n(k0)`` for RMI).
    """
    u_win = jax.lax.dynamic_slice_in_dim(data["u"], t_f, window, 0)
    xn_win = jax.lax.dynamic_slice_in_dim(data["x_pad"], t_f, window, 0)
    qddn_win = jax.lax.dynamic_slice_in_dim(data["qdd_pad"], t_f, window, 0)
    active = (t_f - window + jnp.arange(window)) >= 0
    x0 = data["x_start"][jnp.maximum(t_f - window, 0)]  # (n, 2)
    return window_extremes(
        u_win, xn_win, qddn_win, active, x0, data, model=model, mode=mode, dt=dt, search=search
    )


def _one_step_window(found, u_win, sigma, active, x0, onehot, box):
    """A coupled window of one step: (4n,) ``c x(t_f)`` in track order, exactly as the scan.

    Two savings, exact for the outputs: every track starts from ``x0``, so the search
    takes the state once (``coupled_step`` with a ``(1, n, 2)`` state: terms and
    factorisation shared, one row of ``M^-1`` per joint); and an encoder track's output
    after the step, ``q + dt qd``, does not depend on the corner, so only the tachometer
    tracks search. This is the online monitor's cheapest tick (``short_window``, N = 1).
    """
    n = onehot.shape[1]
    dt = box[-1]
    _, joint, sensor = _tracks(n)
    enc, tach = np.flatnonzero(sensor == 0), np.flatnonzero(sensor == 1)
    new = found.coupled_step(x0[None], u_win[0], sigma[0][tach], onehot[tach], *box)
    speeds = jnp.where(active[0], new[np.arange(tach.size), joint[tach], 1], x0[joint[tach], 1])
    q, qd = x0[joint[enc], 0], x0[joint[enc], 1]
    positions = jnp.where(active[0], q + dt * qd, q)
    return jnp.concatenate([positions, speeds])[np.argsort(np.concatenate([enc, tach]))]


def window_extremes(u_win, xn_win, qddn_win, active, x0, consts, *, model, mode, dt, search="auto"):
    """RMI over one window whose inputs are given: (2, n, 2) [max/min, joint, sensor].

    Step ``s`` of the window is time ``k = t_f - N + s``.

    Args:
        u_win: (N, n) feed-forward ``u_d(k)``.
        xn_win, qddn_win: (N, n, 2) nominal states and (N, n) nominal
            accelerations at ``k`` (used by ``per_joint`` mode only).
        active: (N,) bool, False for steps before the run (``k < 0``).
        x0: (n, 2) the window's start: ``x_n(k0)`` for RMI, a measured state
            for :mod:`rmijax.methods.short_window`. In ``per_joint`` mode each track
            starts its own joint from ``x0`` and takes the others from ``xn_win``.
        consts: mapping with ``weights`` (N, n, 2) costate velocity parts,
            ``corners`` (K, p), ``nominal``, ``lo``, ``hi`` (p,), ``kp``, ``kd`` (n,).
        model: the :class:`~rmijax.robots.model.RobotModel`; mode: ``coupled`` or
            ``per_joint``; dt: step in s; search: see :data:`SEARCHES` (or a
            chooser, see :func:`check_search`).
    """
    n = model.n_joints
    extreme, joint, sensor = _tracks(n)
    dtype = u_win.dtype
    sign = jnp.asarray(1 - 2 * extreme, dtype)  # +1 max, -1 min
    onehot = jnp.asarray(np.eye(n)[joint], dtype)  # (4n, n)
    nominal, kp, kd = consts["nominal"], consts["kp"], consts["kd"]
    found = resolve(model, search)
    sigma = sign[None, :] * consts["weights"][:, joint, sensor]  # (N, 4n)
    box = (nominal, consts["lo"], consts["hi"], kp, kd, dt)

    if mode == "coupled" and hasattr(found, "coupled_step"):
        onehot = np.eye(n, dtype=dtype)[joint]  # static: a search may read the layout

        def step(states, inputs):
            u, sigma_s, on = inputs
            new = found.coupled_step(states, u, sigma_s, onehot, *box)
            return jnp.where(on, new, states), None

        if getattr(found, "shared_start", False) and u_win.shape[0] == 1:
            values = _one_step_window(found, u_win, sigma, active, x0, onehot, box)
        else:
            init = jnp.broadcast_to(x0, (4 * n, n, 2))
            final, _ = jax.lax.scan(step, init, (u_win, sigma, active))
            values = final[np.arange(4 * n), joint, sensor]
    elif mode == "coupled":

        def track_step(x, sigma_t, onehot_t, u):
            q, qd = x[:, 0], x[:, 1]
            v = servo_command(q, qd, u, kp, kd)
            tau = computed_torque(model, nominal, q, qd, v)

            def perturbation(th):
                return jnp.dot(onehot_t, model.accelerations(q, qd, tau, th) - v)

            offset = sigma_t * jnp.dot(onehot_t, v)
            if hasattr(found, "coupled"):
                th = found.coupled(q, qd, tau, v, onehot_t, sigma_t, offset, consts)
            else:
                th = found(perturbation, sigma_t, offset, consts)
            gv = model.accelerations(q, qd, tau, th) - v
            return jnp.stack(closed_loop_step(q, qd, u, gv, kp, kd, dt), axis=-1)

        def step(states, inputs):
            u, sigma_s, on = inputs
            new = jax.vmap(track_step, in_axes=(0, 0, 0, None))(states, sigma_s, onehot, u)
            return jnp.where(on, new, states), None

        init = jnp.broadcast_to(x0, (4 * n, n, 2))
        final, _ = jax.lax.scan(step, init, (u_win, sigma, active))
        values = final[np.arange(4 * n), joint, sensor]
    elif isinstance(found, FactoredSearch):

        def step(states, inputs):
            u, sigma_s, on, xn, qddn = inputs
            new = found.per_joint_step(states, u, sigma_s, joint, xn, qddn, *box)
            return jnp.where(on, new, states), None

        init = x0[joint]
        final, _ = jax.lax.scan(step, init, (u_win, sigma, active, xn_win, qddn_win))
        values = final[np.arange(4 * n), sensor]
    else:

        def track_step(x, sigma_t, onehot_t, u, xn, qddn):
            mine = onehot_t > 0
            q = jnp.where(mine, x[0], xn[:, 0])
            qd = jnp.where(mine, x[1], xn[:, 1])
            v = servo_command(q, qd, u, kp, kd)
            tau = computed_torque(model, nominal, q, qd, v)
            tau_i, v_i = jnp.dot(onehot_t, tau), jnp.dot(onehot_t, v)
            qdd_others = jnp.where(mine, 0.0, qddn)

            def perturbation(th):
                row = onehot_t @ model.mass_matrix(q, th)
                bias_i = jnp.dot(onehot_t, model.bias(q, qd, th))
                return (tau_i - jnp.dot(row, qdd_others) - bias_i) / jnp.dot(row, onehot_t) - v_i

            gv = perturbation(found(perturbation, sigma_t, sigma_t * v_i, consts))
            q_i, qd_i = closed_loop_step(
                x[0],
                x[1],
                jnp.dot(onehot_t, u),
                gv,
                jnp.dot(onehot_t, kp),
                jnp.dot(onehot_t, kd),
                dt,
            )
            return jnp.stack([q_i, qd_i])

        def step(states, inputs):
            u, sigma_s, on, xn, qddn = inputs
            new = jax.vmap(track_step, in_axes=(0, 0, 0, None, None, None))(
                states, sigma_s, onehot, u, xn, qddn
            )
            return jnp.where(on, new, states), None

        init = x0[joint]  # (4n, 2): each track starts from its own joint's nominal state
        final, _ = jax.lax.scan(step, init, (u_win, sigma, active, xn_win, qddn_win))
        values = final[np.arange(4 * n), sensor]
    return values.reshape(2, n, 2)


def _assemble(extremes, nominal, noise_lo, noise_hi, dt):
    shape = extremes[..., 0, :, :].shape
    upper = extremes[..., 0, :, :] + jnp.broadcast_to(noise_hi, shape)
    lower = extremes[..., 1, :, :] + jnp.broadcast_to(noise_lo, shape)
    return Bounds(lower=lower, upper=upper, nominal=nominal, crossed=upper < lower, dt=dt)


@functools.partial(jax.jit, static_argnames=("mode", "window", "batch", "search", "uncertain"))
def _rmi_all(
    traj,
    params,
    noise_lo,
    noise_hi,
    starts=None,
    *,
    mode,
    window,
    batch,
    search="auto",
    uncertain=None,
):
    data, fn = _end_step_fn(traj, params, mode, window, search, starts, uncertain)
    end_steps = jnp.arange(traj.n_steps + 1)
    extremes = jax.lax.map(fn, end_steps, batch_size=batch)  # (T+1, 2, n, 2)
    return _assemble(extremes, data["x_n"], noise_lo, noise_hi, traj.dt)


@functools.partial(jax.jit, static_argnames=("mode", "window", "search", "uncertain"))
def _rmi_chunk(traj, params, end_steps, starts=None, *, mode, window, search, uncertain=None):
    _, fn = _end_step_fn(traj, params, mode, window, search, starts, uncertain)
    return jax.vmap(fn)(end_steps)


@functools.partial(jax.jit, static_argnames=("mode", "window", "search", "uncertain"))
def _rmi_one(traj, params, t_f, noise_lo, noise_hi, *, mode, window, search, uncertain=None):
    data, fn = _end_step_fn(traj, params, mode, window, search, uncertain=uncertain)
    extremes = fn(t_f)
    return _assemble(extremes, data["x_n"][t_f], noise_lo, noise_hi, traj.dt)


def _cast(traj, params, dtype):
    return _checks.cast_tree(traj, dtype), _checks.cast_tree(params, dtype)


def _check_result(bounds):
    """Refuse non-finite bounds (a diverged window); warn about crossed ones."""
    if not _checks.is_concrete(bounds.upper):
        return
    where = _checks.first_non_finite(bounds.upper, bounds.lower)
    if where is not None:
        sensor = DivergedError.SENSORS[where[-1]]
        at = f"end step {where[0]}, " if len(where) == 3 else ""
        raise DivergedError.at(
            where,
            f"RMI bounds are not finite ({at}joint {where[-2]} {sensor}): the worst-case "
            "tracks diverged, because with the parameter chosen afresh at every step this "
            "closed loop is unstable over the window. Narrow the parameter box (lo, hi), "
            "shorten the window or use stiffer gains (kp, kd).",
        )
    _warn_crossed(bounds)


def _warn_crossed(bounds):
    if _checks.is_concrete(bounds.crossed) and bool(jnp.any(bounds.crossed)):
        count = int(jnp.sum(bounds.crossed))
        warnings.warn(
            f"RMI bounds crossed (upper < lower) at {count} output sample(s); see "
            "bounds.crossed. They are returned as computed, not swapped.",
            RuntimeWarning,
            stacklevel=4,
        )


def rmi(
    traj: Trajectory,
    params: UncertainRobot,
    *,
    mode: str = "coupled",
    window: int = 100,
    noise_lo=0.0,
    noise_hi=0.0,
    memory_budget: int = DEFAULT_MEMORY_BUDGET,
    chunk_size: int | None = None,
    progress: bool = False,
    search: str = "auto",
) -> Bounds:
    """RMI bounds for every end step of a trajectory (the offline form).

    Callable inside the user's ``jax.jit`` (value checks are then skipped;
    shapes are still checked).

    Args:
        traj: the desired motion and its nominal response.
        params: the robot and its parameter box (``K = 2^p`` corners).
        mode: ``"coupled"`` (exact, default) or ``"per_joint"`` (the paper's;
            not a safe threshold for ``n >= 2``, SPEC section 4).
        window: ``N``, steps per window (>= 1).
        noise_lo, noise_hi: sensor noise bounds ``[V_lo, V_hi]``, scalar,
            ``(2,)`` (encoder rad, tachometer rad/s) or ``(n, 2)``.
        memory_budget: bytes allowed for one batch of end steps; the batch
            size follows from it.
        chunk_size: end steps per batch; default from ``memory_budget``.
        progress: show a progress bar over batches (eager calls only).
        search: ``"auto"`` (the planar arm's exact factored search, else
            enumeration) or ``"enumerate"`` (all ``2^p`` corners; same result,
            slower). See :data:`SEARCHES`.

    Returns:
        :class:`Bounds` with ``lower``, ``upper``, ``nominal``, ``crossed``
        of shape (T+1, n, 2).

    Raises:
        TypeError, ValueError: invalid inputs (the message names the argument).
        ProblemTooLargeError: one end step cannot fit in ``memory_budget``.
        DivergedError: the bounds are not finite (a box too wide for the loop);
            only checked outside ``jit``.
    """
    dtype, lo, hi = _validate(traj, params, mode, window, noise_lo, noise_hi, search)
    traj, params = _cast(traj, params, dtype)
    bounds = _rmi_from_starts(
        traj,
        params,
        None,
        lo,
        hi,
        mode=mode,
        window=window,
        memory_budget=memory_budget,
        chunk_size=chunk_size,
        progress=progress,
        search=search,
    )
    _check_result(bounds)
    return bounds


# --------------------------------------------------------------------------
# Windows from given start states (used by rmijax.methods.short_window)
# --------------------------------------------------------------------------


def _rmi_from_starts(
    traj,
    params,
    starts,
    offset_lo,
    offset_hi,
    *,
    mode,
    window,
    memory_budget,
    chunk_size,
    progress,
    search,
):
    """RMI's windows started from ``starts`` instead of the nominal state (private entry).

    End step ``t_f``'s tracks start at ``starts[max(0, t_f - N)]`` and run the
    unchanged RMI recursion (costate weights, corner choice, both modes).
    :func:`rmi` calls it with ``starts=None`` (the nominal ``x_n``);
    :func:`rmijax.methods.short_window.short_window_bounds` with the readings.

    Args:
        traj, params: already validated and cast to one dtype (:func:`_cast`).
        starts: (T+1, n, 2) window start states, same dtype, or None for ``x_n``.
        offset_lo, offset_hi: added to the min and max tracks' outputs;
            (n, 2) or (T+1, n, 2) (rad, rad/s).
        mode, window, memory_budget, chunk_size, progress, search: as :func:`rmi`.

    Returns:
        :class:`Bounds` (T+1, n, 2), not yet checked (:func:`_check_result`).
    """
    progress = _checks.boolean("progress", progress)
    n_end = traj.n_steps + 1
    window = min(int(window), traj.n_steps)  # a longer window gives the same windows
    batch = _batch_size(
        params, mode, window, traj.dtype, memory_budget, n_end, chunk_size, search=search
    )
    seconds = estimate_seconds(params, traj.n_steps, mode=mode, window=window, search=search)
    if seconds is not None:
        _checks.check_time(
            f"RMI over {_evaluated_corners(params, search)} corners x {4 * traj.n_joints} tracks x "
            f"{n_end} end steps x {window}-step windows",
            seconds,
            progress=progress,
            fixes="Make parameters certain (lo == hi: each halves the corners), shorten the "
            "run or the window, or use a method that scales (rmijax.bounds with "
            "method='corner_search' or 'linearized').",
        )
    leaves = jax.tree_util.tree_leaves((traj, params, starts))
    concrete = all(_checks.is_concrete(a) for a in leaves)
    uncertain = uncertain_indices(params)
    if progress and concrete:
        return _rmi_with_progress(
            traj, params, offset_lo, offset_hi, mode, window, batch, search, starts, uncertain
        )
    return _rmi_all(
        traj,
        params,
        offset_lo,
        offset_hi,
        starts,
        mode=mode,
        window=int(window),
        batch=batch,
        search=search,
        uncertain=uncertain,
    )


def _rmi_with_progress(traj, params, lo, hi, mode, window, batch, search, starts, uncertain):
    from tqdm.auto import tqdm

    n_end = traj.n_steps + 1
    n_chunks = math.ceil(n_end / batch)
    pieces = []
    with tqdm(total=n_end, desc=f"RMI {mode} n={traj.n_joints}", unit="step") as bar:
        for chunk in range(n_chunks):
            ends = np.arange(chunk * batch, (chunk + 1) * batch)
            ends = np.minimum(ends, n_end - 1)  # fixed chunk shape: no retrace on the last
            extremes = _rmi_chunk(
                traj,
                params,
                jnp.asarray(ends),
                starts,
                mode=mode,
                window=int(window),
                search=search,
                uncertain=uncertain,
            )
            extremes.block_until_ready()
            pieces.append(extremes)
            bar.update(min(batch, n_end - chunk * batch))
    extremes = jnp.concatenate(pieces, axis=0)[:n_end]
    return _assemble(extremes, traj.x_n, lo, hi, traj.dt)


def _end_step(t_f, n_steps):
    """``t_f`` as an int32 scalar in ``[0, T]``: integer types only, never wrapped.

    The dtype is known even under ``jit``, so a float or bool ``t_f`` is
    refused at trace time (truncating 2.5 to 2 would silently answer for
    another step). A traced integer is clipped into ``[0, T]`` in its own
    dtype before the cast to int32, so an int64 beyond the int32 range lands
    on ``T``, not on a wrapped-around step.
    """
    dtype = getattr(t_f, "dtype", None)
    if isinstance(t_f, (bool, np.bool_)) or (dtype is not None and dtype == np.bool_):
        raise TypeError(f"t_f must be an integer end step, got the bool {t_f!r}")
    if dtype is None and not isinstance(t_f, int):
        raise TypeError(
            f"t_f must be an integer end step (0 <= t_f <= T), got {t_f!r} of type "
            f"{type(t_f).__name__}"
        )
    if dtype is not None and not jnp.issubdtype(dtype, jnp.integer):
        raise TypeError(
            f"t_f must be an integer end step, got dtype {dtype}; a float step would be "
            "truncated to another step. Pass an int (e.g. jnp.int32(k)) or round it yourself"
        )
    if np.ndim(t_f) != 0:
        raise ValueError(f"t_f must be a scalar end step, got shape {np.shape(t_f)}")
    if _checks.is_concrete(t_f):
        if not 0 <= int(t_f) <= n_steps:
            raise ValueError(f"t_f={int(t_f)} is outside the trajectory's end steps [0, {n_steps}]")
        return jnp.asarray(int(t_f), jnp.int32)
    return jnp.clip(t_f, 0, n_steps).astype(jnp.int32)


def rmi_step(
    traj: Trajectory,
    params: UncertainRobot,
    t_f,
    *,
    mode: str = "coupled",
    window: int = 100,
    noise_lo=0.0,
    noise_hi=0.0,
    search: str = "auto",
) -> Bounds:
    """RMI bounds of one end step ``t_f`` (the online form).

    ``t_f`` may be a Python int or a traced integer: under the user's
    ``jax.jit`` the same compiled step serves every ``t_f`` without retracing.
    A traced ``t_f`` outside ``[0, T]`` is clipped into it (in its own dtype,
    so a large int64 never wraps to another step); a float or bool ``t_f``
    is refused, traced or not. The other arguments are those of :func:`rmi`.

    Returns:
        :class:`Bounds` with ``lower``, ``upper``, ``nominal``, ``crossed`` of
        shape (n, 2).
    """
    dtype, lo, hi = _validate(traj, params, mode, window, noise_lo, noise_hi, search)
    traj, params = _cast(traj, params, dtype)
    t_f = _end_step(t_f, traj.n_steps)
    window = min(int(window), traj.n_steps)  # a longer window gives the same window
    check_memory(params, mode=mode, window=window, dtype=dtype, search=search)
    bounds = _rmi_one(
        traj,
        params,
        t_f,
        lo,
        hi,
        mode=mode,
        window=int(window),
        search=search,
        uncertain=uncertain_indices(params),
    )
    _check_result(bounds)
    return bounds
