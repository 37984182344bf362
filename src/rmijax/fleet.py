"""Fleet scale: offline RMI, bounds and plant runs over many runs, sharded across devices.

A batch of runs (trajectories and/or parameter boxes / true parameters) is
stacked along a leading ``batch`` axis, padded to a multiple of the device
count (the padding repeats the last run and is cut off again), laid out with
``NamedSharding(mesh, P("batch"))`` and computed by ``jax.shard_map`` of the
``vmap``-ed single-run function: every device runs the very program a single
device would on its share, so results equal single-device results (to
roundoff of the batched arithmetic, far below 1e-12 in float64). Runs of
different lengths are padded at the end to the longest: RMI's end step ``t_f``
and the plant's step ``k`` depend on the past alone, so the padding changes no
kept sample. :func:`rmi_sharded` shards the end steps of one long run instead.

Across hosts: start every process with ``jax.distributed.initialize()`` (the
README's "Fleet scale" section shows the launch); :func:`device_mesh` then
spans every device of every host, every process passes the same inputs and
gets the whole result back. For
folders of logs it is cheaper to let each process take its own logs
(:func:`my_share`) on its local devices, which is what ``rmijax check`` does.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from rmijax.methods import rmi as _engine
from rmijax.methods.base import Bounds
from rmijax.plant import _NEVER, DIVERGENCE_LIMIT, Fault, _fault_tables, _run
from rmijax.robots.box import UncertainRobot
from rmijax.trajectory import Trajectory

__all__ = [
    "AXIS",
    "bounds_batch",
    "certified_batch",
    "device_mesh",
    "my_share",
    "rmi_batch",
    "rmi_sharded",
    "simulate_batch",
]

AXIS = "batch"
"""Name of the mesh axis that runs (or end steps) are split along."""


def device_mesh(devices=None) -> Mesh:
    """A one-axis :class:`~jax.sharding.Mesh` named ``"batch"`` over ``devices``.

    Args:
        devices: a device list, an int (the first that many of ``jax.devices()``)
            or None (every device of every process).
    """
    if devices is None:
        devices = jax.devices()
    elif isinstance(devices, int):
        available = jax.devices()
        if not 1 <= devices <= len(available):
            raise ValueError(f"devices={devices}: there are {len(available)} devices")
        devices = available[:devices]
    return Mesh(np.asarray(list(devices)), (AXIS,))


def my_share(items):
    """The items this process handles when every process of a multi-host job gets the
    same list: every ``jax.process_count()``-th, starting at ``jax.process_index()``."""
    return list(items)[jax.process_index() :: jax.process_count()]


# --------------------------------------------------------------------------
# Batches: stack, pad, place, gather
# --------------------------------------------------------------------------


def _as_list(value, kind, name):
    if isinstance(value, kind):
        return [value]
    value = list(value)
    if not value or not all(isinstance(v, kind) for v in value):
        raise TypeError(f"{name} must be a {kind.__name__} or a non-empty sequence of them")
    return value


def _broadcast(lists, names):
    """One batch size ``B`` from sequences of length 1 or B."""
    sizes = {len(v) for v in lists if len(v) != 1}
    if len(sizes) > 1:
        detail = ", ".join(f"{n}: {len(v)}" for n, v in zip(names, lists, strict=True))
        raise ValueError(f"batch sizes differ ({detail}); give 1 or the same number of each")
    size = sizes.pop() if sizes else 1
    return size, [v * size if len(v) == 1 else v for v in lists]


def _pad_steps(traj: Trajectory, n_steps: int) -> Trajectory:
    """``traj`` extended to ``n_steps`` by repeating its last sample (the past is unchanged)."""
    extra = n_steps - traj.n_steps
    if extra == 0:
        return traj

    def pad(x):
        return jnp.concatenate([x, jnp.repeat(x[-1:], extra, axis=0)], axis=0)

    fields = {k: pad(getattr(traj, k)) for k in ("q_d", "qd_d", "qdd_d", "u_d", "x_n", "qdd_n")}
    t = traj.t[0] + traj.dt * jnp.arange(n_steps + 1, dtype=traj.t.dtype)
    return dataclasses.replace(traj, t=t, **fields)


def _same_grid(trajs):
    steps = {t.dt for t in trajs}
    if len(steps) > 1:
        raise ValueError(f"the runs have different steps dt {sorted(steps)}; batch same-dt runs")
    joints = {t.n_joints for t in trajs}
    if len(joints) > 1:
        raise ValueError(f"the runs have different joint counts {sorted(joints)}")
    n_steps = max(t.n_steps for t in trajs)
    labels = trajs[0].labels
    return [dataclasses.replace(_pad_steps(t, n_steps), labels=labels) for t in trajs]


def _stack(trees, multiple):
    """Stack pytrees along a new leading axis, padded to a multiple of ``multiple``."""
    size = len(trees)
    padded = math.ceil(size / multiple) * multiple
    trees = list(trees) + [trees[-1]] * (padded - size)
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *trees)


def _place(tree, mesh, spec):
    """Global arrays laid out by ``spec`` on ``mesh`` (each process gives its own shards)."""
    sharding = NamedSharding(mesh, spec)

    def put(x):
        host = np.asarray(x)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    return jax.tree_util.tree_map(put, tree)


def _gather(tree):
    """The whole of each array, as NumPy, on every process (gathered across hosts only
    when the mesh spans them; a mesh of local devices needs no other process)."""

    def whole(x):
        if getattr(x, "is_fully_addressable", True):
            return np.asarray(x)
        from jax.experimental import multihost_utils

        return np.asarray(multihost_utils.process_allgather(x, tiled=True))

    return jax.tree_util.tree_map(whole, tree)


@functools.lru_cache(maxsize=64)
def _program(body, mesh, batched_specs, static):
    """``jit(shard_map(vmap(body)))`` over the batch axis; ``static`` goes to ``body``."""

    def local(batched, shared):
        return jax.vmap(lambda b: body(b, shared, **dict(static)))(batched)

    mapped = jax.shard_map(
        local, mesh=mesh, in_specs=(batched_specs, P()), out_specs=P(AXIS), check_vma=False
    )
    return jax.jit(mapped)


def _run_batched(body, batched, shared, mesh, static):
    """``body(run, shared, **static)`` for every run of the stacked ``batched``."""
    placed = _place(batched, mesh, P(AXIS))
    replicated = _place(shared, mesh, P())
    program = _program(body, mesh, P(AXIS), tuple(sorted(static.items())))
    return _gather(program(placed, replicated))


# --------------------------------------------------------------------------
# RMI over a batch of runs, and over the end steps of one run
# --------------------------------------------------------------------------


def _rmi_body(run, shared, *, mode, window, batch, search):
    traj, params = run
    lo, hi = shared
    return _engine._rmi_all(
        traj, params, lo, hi, None, mode=mode, window=window, batch=batch, search=search
    )


def _per_device_batch(
    params, mode, window, dtype, budget, n_end, runs_per_device, chunk_size, search
):
    if chunk_size is not None:
        return int(chunk_size)
    single = _engine._batch_size(params, mode, window, dtype, budget, n_end, None, search=search)
    return max(1, single // max(1, runs_per_device))


def rmi_batch(
    trajs,
    params,
    *,
    mode: str = "coupled",
    window: int = 100,
    noise_lo=0.0,
    noise_hi=0.0,
    mesh: Mesh | None = None,
    memory_budget: int = _engine.DEFAULT_MEMORY_BUDGET,
    chunk_size: int | None = None,
    search: str = "auto",
) -> list[Bounds]:
    """:func:`rmijax.rmi` of many runs at once, sharded across the devices of ``mesh``.

    Args:
        trajs: a :class:`~rmijax.Trajectory` or a sequence of them (same ``dt``
            and joints; lengths may differ).
        params: an :class:`~rmijax.UncertainRobot` or a sequence (parameter
            boxes of one model); a single one serves every run.
        mode, window, noise_lo, noise_hi, search: as :func:`rmijax.rmi`.
        mesh: default :func:`device_mesh` over every device.
        memory_budget: bytes per device for one batch of end steps of all its runs.
        chunk_size: end steps per batch (per run); default from the budget.

    Returns:
        One :class:`~rmijax.Bounds` per run (NumPy arrays, (T_r+1, n, 2)),
        equal to ``rmijax.rmi(trajs[r], params[r])``.

    Raises:
        As :func:`rmijax.rmi`; ValueError for runs of different ``dt`` or joints.
    """
    trajs = _as_list(trajs, Trajectory, "trajs")
    robots = _as_list(params, UncertainRobot, "params")
    size, (trajs, robots) = _broadcast([trajs, robots], ["trajs", "params"])
    checked = [
        _engine._validate(t, r, mode, window, noise_lo, noise_hi, search)
        for t, r in zip(trajs, robots, strict=True)
    ]
    dtype = jnp.result_type(*(c[0] for c in checked))
    lo, hi = (c.astype(dtype) for c in checked[0][1:])
    lengths = [t.n_steps + 1 for t in trajs]
    trajs = _same_grid([_engine._cast(t, robots[0], dtype)[0] for t in trajs])
    robots = [_engine._cast(trajs[0], r, dtype)[1] for r in robots]
    mesh = device_mesh() if mesh is None else mesh
    per_device = math.ceil(size / mesh.size)
    batch = _per_device_batch(
        robots[0], mode, window, dtype, memory_budget, max(lengths), per_device, chunk_size, search
    )
    batched = _stack(list(zip(trajs, robots, strict=True)), mesh.size)
    static = dict(mode=mode, window=int(window), batch=batch, search=search)
    out = _run_batched(_rmi_body, batched, (lo, hi), mesh, static)
    results = []
    for r, length in enumerate(lengths):
        bounds = Bounds(
            lower=out.lower[r, :length],
            upper=out.upper[r, :length],
            nominal=out.nominal[r, :length],
            crossed=out.crossed[r, :length],
            dt=trajs[0].dt,
        )
        _engine._check_result(bounds)
        results.append(bounds)
    return results


def _end_steps_body(end_steps, shared, *, mode, window, batch, search):
    traj, params = shared
    _, fn = _engine._end_step_fn(traj, params, mode, window, search)
    return jax.lax.map(fn, end_steps, batch_size=batch)


def rmi_sharded(
    traj: Trajectory,
    params: UncertainRobot,
    *,
    mode: str = "coupled",
    window: int = 100,
    noise_lo=0.0,
    noise_hi=0.0,
    mesh: Mesh | None = None,
    memory_budget: int = _engine.DEFAULT_MEMORY_BUDGET,
    chunk_size: int | None = None,
    search: str = "auto",
    progress: bool = False,
) -> Bounds:
    """:func:`rmijax.rmi` of one long run, its end steps split across the devices of ``mesh``.

    End steps are independent windows; each device computes a contiguous share.
    Arguments as :func:`rmi_batch`; ``progress=True`` computes slices of
    ``devices x chunk`` end steps one after another under a progress bar.
    Returns :class:`~rmijax.Bounds` (T+1, n, 2), NumPy.
    """
    dtype, lo, hi = _engine._validate(traj, params, mode, window, noise_lo, noise_hi, search)
    traj, params = _engine._cast(traj, params, dtype)
    mesh = device_mesh() if mesh is None else mesh
    n_end = traj.n_steps + 1
    batch = _per_device_batch(
        params, mode, window, dtype, memory_budget, n_end, 1, chunk_size, search
    )
    # one slice: ``batch`` end steps per device; the whole run when no progress is shown
    piece = mesh.size * batch if progress else math.ceil(n_end / mesh.size) * mesh.size
    n_pieces = math.ceil(n_end / piece)
    shared = _place((traj, params), mesh, P())
    static = dict(mode=mode, window=int(window), batch=batch, search=search)
    program = _shard_end_steps(mesh, tuple(sorted(static.items())))
    pieces = []
    with _progress_bar(progress, n_end, f"RMI {mode} n={traj.n_joints}") as bar:
        for index in range(n_pieces):
            ends = np.minimum(np.arange(index * piece, (index + 1) * piece), n_end - 1)
            pieces.append(_gather(program(_place(ends.astype(np.int32), mesh, P(AXIS)), shared)))
            bar.update(min(piece, n_end - index * piece))
    extremes = np.concatenate(pieces, axis=0)[:n_end]
    bounds = _engine._assemble(jnp.asarray(extremes), traj.x_n, lo, hi, traj.dt)
    bounds = jax.tree_util.tree_map(np.asarray, bounds)
    _engine._check_result(bounds)
    return bounds


def _progress_bar(show, total, desc):
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="step", disable=not show)


@functools.lru_cache(maxsize=64)
def _shard_end_steps(mesh, static):
    def local(end_steps, shared):
        return _end_steps_body(end_steps, shared, **dict(static))

    return jax.jit(
        jax.shard_map(local, mesh=mesh, in_specs=(P(AXIS), P()), out_specs=P(AXIS), check_vma=False)
    )


# --------------------------------------------------------------------------
# Plant runs over a batch
# --------------------------------------------------------------------------


def _simulate_body(run, shared, *, limit):
    traj, params, th, noise, tables = run
    return _run(traj, params, th, noise, tables, limit)


def _fault_lists(faults, size):
    if isinstance(faults, Fault):
        return [(faults,)] * size
    faults = list(faults)
    if all(isinstance(f, Fault) for f in faults):
        return [tuple(faults)] * size
    if len(faults) != size:
        raise ValueError(
            f"faults must be Fault objects for every run or one sequence per run ({size}), "
            f"got {len(faults)} entries"
        )
    return [(f,) if isinstance(f, Fault) else tuple(f) for f in faults]


def simulate_batch(
    trajs,
    params,
    th_true,
    *,
    faults=(),
    noise_lo=0.0,
    noise_hi=0.0,
    seed: int = 0,
    divergence_limit: float = DIVERGENCE_LIMIT,
    mesh: Mesh | None = None,
):
    """:func:`rmijax.simulate` of many runs at once, sharded across the devices of ``mesh``.

    Args:
        trajs: a :class:`~rmijax.Trajectory` or a sequence (same ``dt``, lengths may differ).
        params: an :class:`~rmijax.UncertainRobot` or a sequence of them.
        th_true: true parameters (p,) for every run or (B, p).
        faults: :class:`~rmijax.Fault` objects for every run, or one sequence per run.
        noise_lo, noise_hi: as :func:`rmijax.simulate`; run ``r`` draws its
            noise with seed ``seed + r`` over the longest run's length, so a run of
            that length equals ``rmijax.simulate(trajs[r], params[r], th_true[r],
            seed=seed + r)`` (shorter runs get other draws of the same bounds).
        divergence_limit: as :func:`rmijax.simulate` (one warning for the batch).
        mesh: default :func:`device_mesh` over every device.

    Returns:
        ``(x_true, y_meas)``: lists with one (T_r+1, n, 2) NumPy array per run.
    """
    from rmijax import _checks

    trajs = _as_list(trajs, Trajectory, "trajs")
    robots = _as_list(params, UncertainRobot, "params")
    th = np.asarray(th_true, np.float64)
    p = robots[0].n_params
    if th.ndim not in (1, 2) or th.shape[-1] != p:
        raise ValueError(f"th_true must have shape ({p},) or (B, {p}), got {th.shape}")
    _checks.check_finite("th_true", th)
    rows = [th] if th.ndim == 1 else list(th)
    size, (trajs, robots, rows) = _broadcast([trajs, robots, rows], ["trajs", "params", "th_true"])
    fault_lists = _fault_lists(faults, size)
    dtype = jnp.result_type(trajs[0].dtype, robots[0].dtype)
    lengths = [t.n_steps + 1 for t in trajs]
    for t, r in zip(trajs, robots, strict=True):
        if r.n_joints != t.n_joints or r.model != robots[0].model:
            raise ValueError("every run needs the same robot model, with one path per joint")
    trajs = _same_grid([_checks.cast_tree(t, dtype) for t in trajs])
    robots = [_checks.cast_tree(r, dtype) for r in robots]
    n, n_steps = trajs[0].n_joints, trajs[0].n_steps
    lo, hi = _checks.noise_interval(noise_lo, noise_hi, n, dtype)
    runs = []
    for r in range(size):
        tables = _fault_tables(fault_lists[r], n, lengths[r] - 1, trajs[0].dt, dtype)
        shape = (1, n_steps + 1, n, 2)
        uniform = jax.random.uniform(jax.random.PRNGKey(seed + r), shape, dtype)
        noise = jnp.broadcast_to(lo, shape) + jnp.broadcast_to(hi - lo, shape) * uniform
        runs.append((trajs[r], robots[r], jnp.asarray(rows[r], dtype), noise[0], tables))
    mesh = device_mesh() if mesh is None else mesh
    batched = _stack(runs, mesh.size)
    states, readings, diverged = _run_batched(
        _simulate_body, batched, (), mesh, dict(limit=float(divergence_limit))
    )
    diverged = np.asarray(diverged)[:size]
    diverged = np.where(diverged < np.asarray(lengths), diverged, _NEVER)
    if (diverged != _NEVER).any():
        warnings.warn(
            f"the plant diverged (|state| > {divergence_limit:g} or non-finite) in "
            f"{int((diverged != _NEVER).sum())} of {size} run(s); samples from there on are NaN",
            RuntimeWarning,
            stacklevel=2,
        )
    x_true = [states[r, : lengths[r]] for r in range(size)]
    y_meas = [readings[r, : lengths[r]] for r in range(size)]
    return x_true, y_meas


def _certified_body(
    run,
    shared,
    *,
    noisy,
    kernel_steps,
    segments,
    enclosure,
    propagate,
    layout,
    free,
    solve,
    coulomb="auto",
):
    from rmijax.methods import certified

    traj, params, centers, los, his, fixed = run
    noise_lo, noise_hi, scale = shared
    pieces, _, _ = certified._certify(
        traj,
        params,
        centers,
        los,
        his,
        noise_lo,
        noise_hi,
        scale,
        noisy=noisy,
        kernel_steps=kernel_steps,
        segments=segments,
        enclosure=enclosure,
        propagate=propagate,
        layout=layout,
        free=free,
        fixed=None if free is None else fixed,
        solve=solve,
        coulomb=coulomb,
    )
    return jnp.min(pieces["lower"], axis=0), jnp.max(pieces["upper"], axis=0)


def certified_batch(
    trajs,
    params,
    *,
    noise_lo=0.0,
    noise_hi=0.0,
    splits=None,
    kernel_steps: int | None = None,
    segments: int = 3,
    enclosure: str | None = None,
    propagate: str | None = None,
    solve: str | None = None,
    coulomb: str = "auto",
    mesh: Mesh | None = None,
) -> list[Bounds]:
    """:func:`rmijax.methods.certified.certified_bounds` of many runs, sharded like
    :func:`rmi_batch` (the bands only; the certificates stay with the single-run call).

    Args:
        trajs, params: as :func:`rmi_batch`, float64: planar point-mass arms, or the
            serial chains of :func:`rmijax.load_robot` (one model for every run);
            every box split into the same number of pieces (``splits="auto"`` is for
            the single-run call). Parameters certain in every box (``lo == hi``) are
            constants of the jets, as in the single-run call.
        noise_lo, noise_hi, splits, kernel_steps, segments, enclosure, propagate, solve,
            coulomb: as ``certified_bounds``.
        mesh: default :func:`device_mesh` over every device.

    Returns:
        One :class:`~rmijax.Bounds` per run (NumPy, (T_r+1, n, 2)).
    """
    from rmijax import _checks
    from rmijax.methods import certified
    from rmijax.methods.base import DivergedError, check_types

    trajs = _as_list(trajs, Trajectory, "trajs")
    robots = _as_list(params, UncertainRobot, "params")
    size, (trajs, robots) = _broadcast([trajs, robots], ["trajs", "params"])
    layout = certified._layout(robots[0])  # refuses a model it cannot evaluate
    for r, (traj, robot) in enumerate(zip(trajs, robots, strict=True)):
        check_types(traj, robot)
        certified._layout(robot)
        if layout is not None and robot.model != robots[0].model:
            raise ValueError(
                f"params[{r}] (model {robot.model.name!r}, parameters "
                f"{robot.model.param_names}) is not the model of params[0] "
                f"({robots[0].model.name!r}, {robots[0].model.param_names}): certified_batch "
                "needs one chain and parameter layout (payload link, friction kinds) for "
                "every run; load the arm with the same layout for each, or make each run's "
                "box with params.with_box(lo=..., hi=...)"
            )
        if jnp.result_type(traj.dtype, robot.dtype) != jnp.float64:
            raise ValueError("certified bounds work in float64: enable jax_enable_x64")
        if robot.n_joints != traj.n_joints:
            raise ValueError(f"a run has {traj.n_joints} joints for a {robot.n_joints}-joint arm")
        _checks.check_stable(traj.kp, traj.kd, traj.dt)
    n = trajs[0].n_joints
    lo, hi = _checks.noise_interval(noise_lo, noise_hi, n, jnp.float64)
    lo, hi = jnp.broadcast_to(lo, (n, 2)), jnp.broadcast_to(hi, (n, 2))
    noisy = bool(np.any(np.asarray(lo) != 0) or np.any(np.asarray(hi) != 0))
    kernel_steps = certified.KERNEL_STEPS if kernel_steps is None else kernel_steps
    kernel_steps = _checks.positive_int("kernel_steps", kernel_steps, "steps")
    segments = _checks.positive_int("segments", segments)
    if isinstance(splits, str):
        raise ValueError(
            f"certified_batch splits every box into one grid, got splits={splits!r}: give "
            "counts, or call rmijax.certified_bounds(..., splits='auto') per run"
        )
    solve = certified._solve_choice(solve, robots[0])
    coulomb = certified._coulomb_choice(coulomb, robots[0])
    # fold the certain parameters where every box leaves the same ones certain; where
    # the boxes differ (or none is certain) every parameter is a variable
    frees = {certified._free_parameters(r) for r in robots}
    free = (frees.pop() or None) if len(frees) == 1 else None
    boxes = [certified._pieces(r, certified._split_counts(r, splits)) for r in robots]
    if free is not None:  # certain parameters are constants of the jets, not variables
        boxes = [tuple(a[:, list(free)] for a in box) for box in boxes]
    if len({b[0].shape for b in boxes}) > 1:
        raise ValueError("every box must split into the same number of pieces (give splits=)")
    lengths = [t.n_steps + 1 for t in trajs]
    trajs = _same_grid(trajs)
    runs = [
        (t, r, *(jnp.asarray(a, jnp.float64) for a in box), jnp.asarray(r.lo, jnp.float64))
        for t, r, box in zip(trajs, robots, boxes, strict=True)
    ]
    mesh = device_mesh() if mesh is None else mesh
    shared = (lo, hi, jnp.asarray(1.0, jnp.float64))
    enclosure = certified._choice("enclosure", enclosure, ("interval", "affine"), n)
    propagate = certified._choice("propagate", propagate, ("kernel", "carried"), n)
    static = dict(
        noisy=noisy,
        kernel_steps=kernel_steps,
        segments=segments,
        enclosure=enclosure,
        propagate=propagate,
        layout=layout,
        free=free,
        solve=solve,
        coulomb=coulomb,
    )
    lower, upper = _run_batched(_certified_body, _stack(runs, mesh.size), shared, mesh, static)
    results = []
    for r, length in enumerate(lengths):
        low, high = lower[r, :length], upper[r, :length]
        where = _checks.first_non_finite(high, low)
        if where is not None:
            step, joint, sensor = where
            raise DivergedError.at(
                where,
                f"certified bounds of run {r} are not finite (step {step}, joint {joint} "
                f"{DivergedError.SENSORS[sensor]}): the remainder bound diverged. Narrow the "
                "box, split it (splits=...) or use stiffer gains.",
            )
        nominal = np.asarray(trajs[r].x_n)[:length]
        results.append(
            Bounds(lower=low, upper=high, nominal=nominal, crossed=high < low, dt=trajs[0].dt)
        )
    return results


def bounds_batch(
    trajs, params, *, method: str = "rmi", readings=None, mesh: Mesh | None = None, **options
):
    """:func:`rmijax.bounds` of many runs; ``method="rmi"`` is sharded (:func:`rmi_batch`).

    ``method="certified"`` is sharded too (:func:`certified_batch`). The other
    methods have no batched engine yet: they run one after another
    on the default device (same results, no speed-up). ``readings``: one
    (T_r+1, n, 2) array per run, for ``short_window``. Returns one
    :class:`~rmijax.Bounds` per run.
    """
    if method == "certified" and readings is None:
        if options.get("window") is not None:
            raise ValueError("method='certified' has no window: it certifies the whole run")
        if options.pop("mode", "coupled") != "coupled":
            raise ValueError("method='certified' certifies the coupled plant: mode='coupled'")
        options.pop("window", None)
        return certified_batch(trajs, params, mesh=mesh, **options)
    if method == "rmi" and readings is None:
        if options.get("window") is None:
            options.pop("window", None)
        options.pop("progress", None)
        return rmi_batch(trajs, params, mesh=mesh, **options)
    from rmijax.methods.dispatch import bounds

    trajs = _as_list(trajs, Trajectory, "trajs")
    robots = _as_list(params, UncertainRobot, "params")
    per_run = [None] if readings is None else list(readings)
    size, (trajs, robots, per_run) = _broadcast(
        [trajs, robots, per_run], ["trajs", "params", "readings"]
    )
    return [
        bounds(t, r, method=method, readings=y, **options)
        for t, r, y in zip(trajs, robots, per_run, strict=True)
    ]
