"""A cheap sanity check of a user's robot model before any band is computed.

A mass matrix that is singular, indefinite or asymmetric somewhere in the box,
a bias that returns NaN, or a ``forward_dynamics`` that disagrees with
``solve(M, tau - h)`` all give finite, plausible-looking bounds. So the public
entry points (:func:`rmijax.rmi`, :func:`rmijax.rmi_step`, :func:`rmijax.bounds`,
:func:`rmijax.monitor`, :func:`rmijax.simulate`) call :func:`check_model` once
per call, outside ``jit``, at a few states and parameter sets, evaluating the
model with NumPy rather than compiling it; the result is cached by model, box
and states, so repeated calls cost a dictionary look-up.
"""

from __future__ import annotations

import functools

import jax
import numpy as np

from rmijax import _checks
from rmijax.robots import _numpy_eval

__all__ = ["ModelCheckError", "check_model"]

_CACHE: dict = {}
_CACHE_SIZE = 64


class ModelCheckError(ValueError):
    """The robot model failed a sanity check (what failed, where, and the fix)."""


def _parameter_sets(lo, hi, nominal, corners, rng):
    """(S, p): nominal, all-lo, all-hi and the uncertain corners (all, or a seeded sample)."""
    uncertain = np.flatnonzero(hi > lo)
    u = uncertain.size
    if u and 2**u <= corners:
        bits = ((np.arange(2**u)[:, None] >> np.arange(u)[None, :]) & 1).astype(bool)
    else:
        bits = rng.integers(0, 2, size=(corners if u else 0, u)).astype(bool)
    sets = np.broadcast_to(lo, (bits.shape[0], lo.size)).copy()
    sets[:, uncertain] = np.where(bits, hi[uncertain], lo[uncertain])
    return np.concatenate([np.stack([nominal, lo, hi]), sets])


def _states(traj, n, states, rng):
    """(S, 2, n) states ``(q, qd)``: the trajectory's start and a few samples along it."""
    if traj is not None:
        x_n = np.asarray(traj.x_n)
        steps = np.unique(np.linspace(0, x_n.shape[0] - 1, states).round().astype(int))
        chosen = x_n[steps]  # (S, n, 2)
        return np.moveaxis(chosen, -1, 1)
    q = np.concatenate([np.zeros((1, n)), rng.uniform(-np.pi, np.pi, (states - 1, n))])
    qd = np.concatenate([np.zeros((1, n)), rng.uniform(-1.0, 1.0, (states - 1, n))])
    return np.stack([q, qd], axis=1)


def _shapes(model, dtype):
    """Trace the model's functions once and refuse wrong output shapes by name."""
    n, p = model.n_joints, model.n_params
    q = jax.ShapeDtypeStruct((n,), dtype)
    th = jax.ShapeDtypeStruct((p,), dtype)
    calls = [
        ("mass_matrix", model.mass_matrix, (q, th), (n, n), "(q, th)"),
        ("bias", model.bias, (q, q, th), (n,), "(q, qd, th)"),
    ]
    if model.forward_dynamics is not None:
        fd = model.forward_dynamics
        calls.append(("forward_dynamics", fd, (q, q, q, th), (n,), "(q, qd, tau, th)"))
    for name, call, inputs, shape, args in calls:
        try:
            out = jax.eval_shape(call, *inputs)
        except Exception as err:  # a user function: report any failure by name
            raise ModelCheckError(
                f"params.model.{name}{args} fails on q, qd, tau of shape ({n},) and th of "
                f"shape ({p},): {type(err).__name__}: {err}. It must be a pure JAX "
                "function of single (unbatched) arguments"
            ) from err
        if getattr(out, "shape", None) != shape:
            raise ModelCheckError(
                f"params.model.{name} returns shape {getattr(out, 'shape', out)}, expected "
                f"{shape} for a {n}-joint robot with {p} parameters; fix {name} or "
                "n_joints/n_params"
            )


_FAST_COMPILE = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}
"""The check runs once on a few dozen points: compile time is all of its cost, so skip
XLA's CPU optimisation passes (about halves it)."""


@functools.lru_cache(maxsize=32)
def _evaluator(model):
    """``(q, qd, th, accel) -> M, h, qdd_fd`` over a flat batch of (state, parameters) pairs."""

    def one(q, qd, th, accel):
        mass = model.mass_matrix(q, th)
        bias = model.bias(q, qd, th)
        if model.forward_dynamics is None:
            return mass, bias, accel
        tau = mass @ accel + bias  # then solve(M, tau - h) == accel exactly
        return mass, bias, model.forward_dynamics(q, qd, tau, th)

    return jax.vmap(one, in_axes=(0, 0, 0, None))


def _evaluate(model, q, qd, th, accel):
    """M, h and forward dynamics over the batch: NumPy first (no compilation), else XLA."""
    n, batch = model.n_joints, q.shape[0]
    expected = ((batch, n, n), (batch, n), (batch, n))
    try:
        with np.errstate(all="ignore"):  # NaN and inf are judged afterwards, by name
            out = _numpy_eval.evaluate(_evaluator(model), q, qd, th, accel)
        if tuple(o.shape for o in out) == expected:
            return out
    except Exception:  # anything the interpreter cannot do: XLA names the failure
        pass
    return _compiled(model, q, qd, th, accel, expected)


def _compiled(model, q, qd, th, accel, expected):
    fn = jax.jit(_evaluator(model))
    try:
        lowered = fn.lower(q, qd, th, accel)
    except Exception:
        _shapes(model, q.dtype)  # names the function that failed, or its wrong shape
        raise
    if tuple(o.shape for o in lowered.out_info) != expected:
        _shapes(model, q.dtype)
    try:
        options = _FAST_COMPILE if jax.default_backend() == "cpu" else None
        compiled = lowered.compile(compiler_options=options)
    except Exception:  # an XLA without these options: its default passes
        compiled = lowered.compile()
    return tuple(np.asarray(a) for a in compiled(q, qd, th, accel))


def _where(q, qd, th, names):
    fmt = np.array2string
    pairs = ", ".join(f"{label}={value:.6g}" for label, value in zip(names, th, strict=True))
    return f"q={fmt(q, precision=4)}, qd={fmt(qd, precision=4)}, parameters ({pairs})"


def check_model(params, traj=None, *, states: int = 4, corners: int = 16, seed: int = 0):
    """Refuse a robot model that is not a rigid-body model somewhere it will be used.

    Evaluated at ``states`` states (the trajectory's start and samples along
    its nominal, or the zero state and random ones when ``traj`` is None) and
    at the nominal parameters, the box's all-lo and all-hi ends and its
    uncertain corners (all of them up to ``corners``, else a seeded sample):

    - ``M(q, th)`` finite, symmetric (relative tolerance ``sqrt(eps)``) and
      positive definite, with a condition number below ``1 / (n eps)``;
    - ``h(q, qd, th)`` finite;
    - ``forward_dynamics`` (if given) equal to ``solve(M, tau - h)``.

    Runs outside ``jit`` only (on tracers it returns at once); cached by model,
    box and states. The model's functions are traced once and evaluated by
    NumPy, primitive by primitive (``robots/_numpy_eval.py``), not compiled:
    a trace and a few milliseconds (a compiled fallback, for what the
    interpreter cannot run, costs one small XLA compilation). A model with
    ``trusted=True`` (the library's own, held to the SPEC's oracles by the
    test suite) is not checked.

    Args:
        params: the :class:`~rmijax.robots.box.UncertainRobot`.
        traj: the :class:`~rmijax.trajectory.Trajectory` whose states to test,
            or None.
        states: number of states (>= 1); corners: uncertain corners at most.
        seed: for the sampled corners and states.

    Raises:
        ModelCheckError (a ValueError): what failed, at which state and
            parameters, and what to fix.
    """
    model = params.model
    if model.trusted:
        return
    leaves = [params.nominal, params.lo, params.hi]
    if traj is not None:
        leaves.append(traj.x_n)
    if not all(_checks.is_concrete(a) for a in leaves):
        return
    dtype = params.dtype
    rng = np.random.default_rng(seed)
    nominal, lo, hi = (np.asarray(a) for a in (params.nominal, params.lo, params.hi))
    x = _states(traj, model.n_joints, states, rng).astype(dtype)
    key = (model, np.dtype(dtype).str, nominal.tobytes(), lo.tobytes(), hi.tobytes(), x.tobytes())
    if key in _CACHE:
        return
    sets = _parameter_sets(lo, hi, nominal, corners, rng).astype(dtype)
    accel = rng.uniform(-1.0, 1.0, model.n_joints).astype(dtype)
    n_states, n_sets = x.shape[0], sets.shape[0]
    q = np.repeat(x[:, 0], n_sets, axis=0)
    qd = np.repeat(x[:, 1], n_sets, axis=0)
    th = np.tile(sets, (n_states, 1))
    flat = _evaluate(model, q, qd, th, accel)
    mass, bias, qdd = (a.reshape((n_states, n_sets) + a.shape[1:]) for a in flat)
    names = model.param_names or tuple(f"th[{b}]" for b in range(model.n_params))
    _judge(model, mass, bias, qdd, accel, x, sets, names, np.finfo(dtype).eps)
    if len(_CACHE) >= _CACHE_SIZE:
        _CACHE.clear()
    _CACHE[key] = True


def _judge(model, mass, bias, qdd, accel, x, sets, names, eps):
    """Raise on the first failure over the (S, P) grid of states and parameter sets."""
    n = model.n_joints

    def at(s, c):
        return _where(x[s, 0], x[s, 1], sets[c], names)

    def first(bad):
        return tuple(int(i) for i in np.argwhere(bad)[0])

    bad = ~np.isfinite(mass).all(axis=(-2, -1))
    if bad.any():
        s, c = first(bad)
        raise ModelCheckError(
            f"params.model.mass_matrix returns NaN/inf at {at(s, c)}; M must be finite "
            "everywhere in the box"
        )
    bad = ~np.isfinite(bias).all(axis=-1)
    if bad.any():
        s, c = first(bad)
        raise ModelCheckError(
            f"params.model.bias (h) returns NaN/inf at {at(s, c)}; h must be finite "
            "everywhere in the box"
        )
    scale = np.maximum(np.abs(mass).max(axis=(-2, -1)), np.finfo(mass.dtype).tiny)
    asym = np.abs(mass - np.swapaxes(mass, -1, -2)).max(axis=(-2, -1)) / scale
    bad = asym > np.sqrt(eps)
    if bad.any():
        s, c = first(bad)
        raise ModelCheckError(
            f"params.model.mass_matrix is not symmetric at {at(s, c)} (max |M - M'| / max|M| "
            f"= {asym[s, c]:.3g}); a mass matrix is symmetric positive definite. Fix "
            "mass_matrix"
        )
    eig = np.linalg.eigvalsh(0.5 * (mass + np.swapaxes(mass, -1, -2)))
    smallest, largest = eig[..., 0], eig[..., -1]
    cutoff = n * eps * np.abs(largest)  # below it the sign of an eigenvalue is roundoff
    bad = smallest < -cutoff
    if bad.any():
        s, c = first(bad)
        raise ModelCheckError(
            f"params.model.mass_matrix is not positive definite at {at(s, c)} (smallest "
            f"eigenvalue {smallest[s, c]:.3g}, largest {largest[s, c]:.3g}); a mass matrix "
            "is positive definite everywhere in the box (check signs, and that no "
            "parameter in [lo, hi] makes a mass or inertia <= 0)"
        )
    bad = smallest <= cutoff
    if bad.any():
        s, c = first(bad)
        raise ModelCheckError(
            f"params.model.mass_matrix is singular at {at(s, c)} (eigenvalues "
            f"{smallest[s, c]:.3g} .. {largest[s, c]:.3g}): the accelerations are not "
            "determined there. Fix mass_matrix or keep the box and the motion away from "
            "that configuration"
        )
    if model.forward_dynamics is None:
        return
    bad = ~np.isfinite(qdd).all(axis=-1)
    cond = largest / smallest
    error = np.abs(qdd - accel).max(axis=-1) / np.abs(accel).max()
    tol = np.sqrt(eps) + 1e3 * eps * cond
    bad = bad | (error > tol)
    if bad.any():
        s, c = first(bad)
        raise ModelCheckError(
            f"params.model.forward_dynamics disagrees with solve(M, tau - h) at {at(s, c)}: "
            f"relative error {error[s, c]:.3g} (allowed {tol[s, c]:.2g}). It must return "
            "M(q, th)^-1 (tau - h(q, qd, th)) for the same th; fix it or leave it None"
        )
