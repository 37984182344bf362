"""Plant simulation with sensor and motor faults (SPEC section 7).

The true robot has constant parameters ``th`` (anywhere, usually inside the
box); the computed-torque controller uses the nominal parameters and the
*measured* state, so a sensor fault feeds back into the motion. A batch of
true-parameter draws is one ``vmap``, time one ``lax.scan``, all ``jit``-ed.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from rmijax import _checks
from rmijax._linalg import spd_solve
from rmijax.control import computed_torque, servo_command
from rmijax.robots.box import UncertainRobot
from rmijax.robots.check import check_model
from rmijax.trajectory import Trajectory

__all__ = ["FAULT_KINDS", "DIVERGENCE_LIMIT", "Fault", "simulate"]

FAULT_KINDS = (
    "stuck_encoder",
    "stuck_tach",
    "stuck_sensors",
    "bias",
    "drift",
    "free_swinging",
    "locked",
)
"""Fault kinds: sensor faults change readings, motor faults change the plant."""

MEMORY_BUDGET = 4 * 2**30
"""Bytes a batch of runs may hold (noise, states, readings and their masked copies)."""

_ARRAYS_PER_RUN = 6

DIVERGENCE_LIMIT = 1e4
"""|q| (rad) or |qd| (rad/s) beyond which a faulty plant counts as diverged."""

_NEVER = np.iinfo(np.int32).max

_SENSOR_OFFSETS = ("bias", "drift")
_MOTOR_FAULTS = ("free_swinging", "locked")


@dataclasses.dataclass(frozen=True)
class Fault:
    """One fault of one joint, active from ``onset`` on.

    Attributes:
        kind: one of :data:`FAULT_KINDS`:
            ``stuck_encoder`` / ``stuck_tach`` (the reading holds its value at
            onset), ``stuck_sensors`` (the paper's case: the encoder holds, the
            tachometer reads 0), ``bias`` (constant offset ``value`` on
            ``sensor``), ``drift`` (offset ``value * (t - onset)``),
            ``free_swinging`` (the joint's torque is zero), ``locked`` (the
            joint stops at onset and stays; the others follow the reduced
            dynamics).
        joint: 0-based joint index.
        onset: time in s; the onset step is ``round(onset / dt)``.
        value: offset (rad or rad/s) for ``bias``, rate (rad/s or rad/s^2)
            for ``drift`` (default 0); refused for the other kinds.
        sensor: 0 encoder, 1 tachometer for ``bias`` and ``drift`` (default
            0); refused for the other kinds, whose outputs the kind names.
    """

    kind: str
    joint: int
    onset: float
    value: float | None = None
    sensor: int | None = None

    def __post_init__(self):
        if self.kind not in FAULT_KINDS:
            raise ValueError(f"unknown fault kind {self.kind!r}; choose one of {FAULT_KINDS}")
        _checks.integer("Fault joint", self.joint, minimum=0)
        _checks.real("Fault onset", self.onset, minimum=0, unit="s")
        if self.kind in _SENSOR_OFFSETS:
            value = 0.0 if self.value is None else _checks.real("Fault value", self.value)
            sensor = 0 if self.sensor is None else self.sensor
            if isinstance(sensor, bool) or sensor not in (0, 1):
                raise ValueError(
                    f"Fault sensor must be 0 (encoder) or 1 (tachometer), got {self.sensor!r}"
                )
            object.__setattr__(self, "value", value)
            object.__setattr__(self, "sensor", int(sensor))
            return
        if self.sensor is not None:
            which = {
                "stuck_encoder": "acts on the encoder (use stuck_tach for the tachometer)",
                "stuck_tach": "acts on the tachometer (use stuck_encoder for the encoder)",
                "stuck_sensors": "acts on both sensors",
            }.get(self.kind, "is a motor fault and changes no reading")
            raise ValueError(
                f"Fault sensor means nothing for kind {self.kind!r}, which {which}; "
                "leave sensor out (it is for bias and drift)"
            )
        if self.value is not None:
            raise ValueError(
                f"Fault value means nothing for kind {self.kind!r} (it is the offset of bias "
                "and the rate of drift); leave value out"
            )

    @property
    def outputs(self) -> tuple[tuple[int, int], ...]:
        """The readings ``(joint, sensor)`` this fault changes; () for a motor fault."""
        sensors = {
            "stuck_encoder": (0,),
            "stuck_tach": (1,),
            "stuck_sensors": (0, 1),
            "bias": (self.sensor,),
            "drift": (self.sensor,),
        }.get(self.kind, ())
        return tuple((self.joint, s) for s in sensors)

    @property
    def label(self) -> str:
        """A short name such as ``stuck_sensors j2 @3.0s`` (joints 1-based, as in the paper)."""
        extra = ""
        if self.kind in ("bias", "drift"):
            extra = f" {('enc', 'tach')[self.sensor]} {self.value:g}"
        return f"{self.kind}{extra} j{self.joint + 1} @{self.onset:g}s"


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class _FaultTables:
    """Faults as per-output onset steps and values, so the scan needs no Python branches."""

    hold_onset: jax.Array  # (n, 2) step from which the reading holds its onset value
    zero_onset: jax.Array  # (n, 2) step from which the reading is 0
    bias_onset: jax.Array  # (n, 2)
    bias_value: jax.Array  # (n, 2)
    drift_onset: jax.Array  # (n, 2)
    drift_rate: jax.Array  # (n, 2)
    free_onset: jax.Array  # (n,) step from which the joint's torque is zero
    lock_onset: jax.Array  # (n,) step at which the joint locks


def _fault_tables(faults, n, n_steps, dt, dtype):
    tables = {
        "hold_onset": np.full((n, 2), _NEVER),
        "zero_onset": np.full((n, 2), _NEVER),
        "bias_onset": np.full((n, 2), _NEVER),
        "bias_value": np.zeros((n, 2)),
        "drift_onset": np.full((n, 2), _NEVER),
        "drift_rate": np.zeros((n, 2)),
        "free_onset": np.full((n,), _NEVER),
        "lock_onset": np.full((n,), _NEVER),
    }
    claimed = {}  # output (joint, sensor) or joint (motor) -> index of the fault on it
    for index, fault in enumerate(faults):
        if not isinstance(fault, Fault):
            raise TypeError(f"faults[{index}] must be a rmijax.Fault, got {fault!r}")
        targets = fault.outputs if fault.kind not in _MOTOR_FAULTS else (("motor", fault.joint),)
        for target in targets:
            if target in claimed:
                other = faults[claimed[target]]
                where = (
                    f"the motor of joint {fault.joint}"
                    if target[0] == "motor"
                    else f"joint {target[0]} {('encoder', 'tachometer')[target[1]]}"
                )
                raise ValueError(
                    f"faults[{claimed[target]}] ({other.kind}) and faults[{index}] "
                    f"({fault.kind}) both act on {where}; one would silently override the "
                    "other. Give at most one sensor fault per output and one motor fault "
                    "per joint (run the combinations as separate simulations)"
                )
            claimed[target] = index
        if not (isinstance(fault.joint, (int, np.integer)) and 0 <= fault.joint < n):
            raise ValueError(
                f"faults[{index}] ({fault.kind}) names joint {fault.joint!r}, but the robot "
                f"has joints 0..{n - 1} (0-based)"
            )
        step = int(round(fault.onset / dt))
        if not 0 <= step <= n_steps:
            raise ValueError(
                f"faults[{index}] ({fault.kind}) has onset {fault.onset!r} s, outside the "
                f"run [0, {n_steps * dt:g}] s"
            )
        i, s = fault.joint, fault.sensor
        if fault.kind == "stuck_encoder":
            tables["hold_onset"][i, 0] = step
        elif fault.kind == "stuck_tach":
            tables["hold_onset"][i, 1] = step
        elif fault.kind == "stuck_sensors":
            tables["hold_onset"][i, 0] = step
            tables["zero_onset"][i, 1] = step
        elif fault.kind == "bias":
            tables["bias_onset"][i, s] = step
            tables["bias_value"][i, s] = fault.value
        elif fault.kind == "drift":
            tables["drift_onset"][i, s] = step
            tables["drift_rate"][i, s] = fault.value
        elif fault.kind == "free_swinging":
            tables["free_onset"][i] = step
        elif fault.kind == "locked":
            tables["lock_onset"][i] = step
    return _FaultTables(
        **{
            key: jnp.asarray(value, jnp.int32 if "onset" in key else dtype)
            for key, value in tables.items()
        }
    )


def _locked_accelerations(model, q, qd, tau, th, locked):
    """``M qdd = tau - h`` with ``qdd_i = 0`` imposed on the locked joints (n,) bool."""
    mass = model.mass_matrix(q, th)
    rhs = tau - model.bias(q, qd, th)
    keep = ~locked
    both = keep[:, None] & keep[None, :]
    reduced = jnp.where(both, mass, 0.0) + jnp.diag(jnp.where(keep, 0.0, 1.0))
    return spd_solve(reduced, jnp.where(keep, rhs, 0.0))


def _read(k, t, x, held, noise_k, tables, dt):
    """The readings (n, 2) of state ``x`` at step ``k`` (time ``t``), and the held values."""
    healthy = x + noise_k
    held = jnp.where(k == tables.hold_onset, healthy, held)
    reading = jnp.where(k >= tables.hold_onset, held, healthy)
    reading = jnp.where(k >= tables.zero_onset, 0.0, reading)
    reading = reading + jnp.where(k >= tables.bias_onset, tables.bias_value, 0.0)
    drift_time = t - tables.drift_onset.astype(t.dtype) * dt
    reading = reading + jnp.where(k >= tables.drift_onset, tables.drift_rate * drift_time, 0.0)
    return reading, held


def _plant_step(carry, inputs, *, params, th, kp, kd, dt, tables, limit):
    """One explicit-Euler step of the true plant under the controller (a ``lax.scan`` body).

    Shared by :func:`simulate` and :mod:`rmijax.methods.constant_corners`, so that both
    step the plant with exactly the same arithmetic.

    Args:
        carry: ``(x, held, diverged)``: true state (n, 2), held readings
            (n, 2) of stuck sensors, int32 step of divergence (never: int32 max).
        inputs: ``(k, t, u, noise_k)``: step, time (s), feed-forward (n,),
            reading noise (n, 2).
        params: the robot (its ``nominal`` drives the controller); th: (p,)
            true parameters; kp, kd: (n,) gains; dt: step in s.
        tables: the faults as per-output onset tables (:func:`_fault_tables`).
        limit: divergence limit on ``|x|``.

    Returns:
        ``(carry at k+1, (x(k), reading(k)))``; a diverged state freezes.
    """
    x, held, diverged = carry
    k, t, u, noise_k = inputs
    model, nominal = params.model, params.nominal
    locked = k >= tables.lock_onset
    x = x.at[:, 1].set(jnp.where(locked, 0.0, x[:, 1]))  # a locked joint stands still
    reading, held = _read(k, t, x, held, noise_k, tables, dt)
    v = servo_command(reading[:, 0], reading[:, 1], u, kp, kd)
    tau = computed_torque(model, nominal, reading[:, 0], reading[:, 1], v)
    tau = jnp.where(k >= tables.free_onset, 0.0, tau)
    q, qd = x[:, 0], x[:, 1]
    qdd = jax.lax.cond(
        jnp.any(locked),
        lambda: _locked_accelerations(model, q, qd, tau, th, locked),
        lambda: model.accelerations(q, qd, tau, th),
    )
    nxt = jnp.stack([q + dt * qd, qd + dt * qdd], axis=-1)
    bad = ~jnp.all(jnp.isfinite(nxt)) | jnp.any(jnp.abs(nxt) > limit)
    diverged_now = jnp.where((diverged == _NEVER) & bad, k + 1, diverged)
    nxt = jnp.where(diverged_now == _NEVER, nxt, x)  # freeze: no overflow, no NaN
    return (nxt, held, diverged_now), (x, reading)


def _plant_start(x0):
    """The :func:`_plant_step` carry of a run starting at state ``x0`` (n, 2)."""
    return (x0, jnp.zeros_like(x0), jnp.asarray(_NEVER, jnp.int32))


def _run(traj, params, th, noise, tables, limit):
    """One plant run: true states and readings (T+1, n, 2), and the divergence step."""
    n_samples = traj.n_steps + 1
    steps = jnp.arange(n_samples, dtype=jnp.int32)
    step = functools.partial(
        _plant_step,
        params=params,
        th=th,
        kp=traj.kp,
        kd=traj.kd,
        dt=traj.dt,
        tables=tables,
        limit=limit,
    )
    init = _plant_start(traj.x_n[0])
    (_, _, diverged), (states, readings) = jax.lax.scan(
        step, init, (steps, traj.t, traj.u_d, noise)
    )
    after = (steps >= diverged)[:, None, None]
    states = jnp.where(after, jnp.nan, states)
    readings = jnp.where(after, jnp.nan, readings)
    return states, readings, diverged


@functools.partial(jax.jit, static_argnames=("limit",))
def _simulate(traj, params, th_true, noise, tables, *, limit):
    return jax.vmap(_run, in_axes=(None, None, 0, 0, None, None))(
        traj, params, th_true, noise, tables, limit
    )


def simulate(
    traj: Trajectory,
    params: UncertainRobot,
    th_true,
    *,
    faults=(),
    noise_lo=0.0,
    noise_hi=0.0,
    seed: int = 0,
    divergence_limit: float = DIVERGENCE_LIMIT,
):
    """Simulate the true robot under the nominal computed-torque controller.

    Args:
        traj: desired motion, gains and step (the same grid as the bounds).
        params: the robot; its ``nominal`` parameters drive the controller.
        th_true: true parameters, (p,) for one run or (R, p) for a batch.
            Values outside the box are allowed but warned about: RMI bounds
            make no promise for them.
        faults: :class:`Fault` objects, any number, on any joints.
        noise_lo, noise_hi: uniform sensor noise bounds (scalar, (2,) or
            (n, 2)), added to every healthy reading; seeded by ``seed``.
        divergence_limit: a run whose state leaves ``|x| <= limit`` (or turns
            non-finite) is stopped there: the samples from that step on are
            NaN and a single warning says when.

    Returns:
        ``(x_true, y_meas)``: true states and measured readings, (T+1, n, 2)
        or (R, T+1, n, 2); ``[..., 0]`` position (rad), ``[..., 1]``
        velocity (rad/s).

    Raises:
        ValueError: shape mismatches, unknown fault kinds, joints out of
            range, onsets outside the run, NaN parameters or noise bounds.
    """
    if not isinstance(traj, Trajectory):
        raise TypeError(f"traj must be a rmijax.Trajectory, got {type(traj).__name__}")
    if not isinstance(params, UncertainRobot):
        raise TypeError(f"params must be a rmijax.UncertainRobot, got {type(params).__name__}")
    n, p = traj.n_joints, params.n_params
    if params.n_joints != n:
        raise ValueError(
            f"traj has {n} joints but params describes a {params.n_joints}-joint robot"
        )
    seed = _checks.seed(seed)
    divergence_limit = _checks.real("divergence_limit", divergence_limit, positive=True)
    dtype = jnp.result_type(traj.dtype, params.dtype)
    th = _checks.numbers("th_true", th_true, dtype)
    single = th.ndim == 1
    if th.ndim not in (1, 2) or th.shape[-1] != p:
        raise ValueError(
            f"th_true must have shape ({p},) or (R, {p}) for this {n}-joint robot "
            f"(p = {p} parameters), got shape {th.shape}"
        )
    th = th[None] if single else th
    runs = th.shape[0]
    shape = (runs, traj.n_steps + 1, n, 2)
    needed = _ARRAYS_PER_RUN * math.prod(shape) * jnp.dtype(dtype).itemsize
    if needed > MEMORY_BUDGET:
        fit = max(1, MEMORY_BUDGET // (needed // runs))
        raise _checks.ProblemTooLargeError(
            f"simulating {runs} runs of {traj.n_steps + 1} steps needs about "
            f"{needed / 2**30:.1f} GiB, over the {MEMORY_BUDGET / 2**30:g} GiB budget; pass "
            f"th_true in batches of at most {fit} runs (empirical_thresholds: runs <= {fit})"
        )
    _checks.check_finite("th_true", th)
    if isinstance(faults, Fault):
        faults = (faults,)
    if not isinstance(faults, (list, tuple)):
        raise TypeError(f"faults must be a Fault or a list of Faults, got {faults!r}")
    tables = _fault_tables(tuple(faults), n, traj.n_steps, traj.dt, dtype)
    lo, hi = _checks.noise_interval(noise_lo, noise_hi, n, dtype)
    check_model(params, traj)
    if _checks.is_concrete(th):
        outside = np.asarray((th < params.lo[None]) | (th > params.hi[None]))
        if outside.any():
            run, b = (int(v) for v in np.argwhere(outside)[0])
            names = params.model.param_names or tuple(f"th[{j}]" for j in range(p))
            warnings.warn(
                f"th_true (run {run}) has {names[b]} = {float(th[run, b])!r} outside its box "
                f"[{float(params.lo[b])!r}, {float(params.hi[b])!r}]: RMI bounds make no "
                "promise for such a robot",
                UserWarning,
                stacklevel=2,
            )
    uniform = jax.random.uniform(jax.random.PRNGKey(seed), shape, dtype)
    noise = jnp.broadcast_to(lo, shape) + jnp.broadcast_to(hi - lo, shape) * uniform
    traj, params = _checks.cast_tree(traj, dtype), _checks.cast_tree(params, dtype)
    states, readings, diverged = _simulate(
        traj, params, th, noise, tables, limit=float(divergence_limit)
    )
    diverged = np.asarray(diverged)
    if (diverged != _NEVER).any():
        first = int(diverged.min())
        count = int((diverged != _NEVER).sum())
        warnings.warn(
            f"the plant diverged (|state| > {divergence_limit:g} or non-finite) in {count} "
            f"of {runs} run(s), first at t = {first * traj.dt:.2f} s; samples from there on "
            "are NaN",
            RuntimeWarning,
            stacklevel=2,
        )
    if single:
        return states[0], readings[0]
    return states, readings
