"""Evaluate a traced JAX function with NumPy, to check a model without compiling it.

:func:`rmijax.check_model` evaluates a user's ``M``, ``h`` and ``forward_dynamics`` at a
few dozen points once. Compiling them with XLA for that costs a few tenths of a second
(as much as 6% of a first two-joint ``rmi`` call), while the program runs in
microseconds; evaluating the function's jaxpr primitive by primitive with NumPy costs a
trace and a few milliseconds. Primitives not in the table below (rare in a rigid-body
model: gathers with batching dimensions, scatters, FFTs, ...) are handed to JAX itself
(``primitive.bind``: one small eager compilation each, cached by JAX), so every function
evaluates; the table only makes the common ones cheap. Loops (``while``, ``scan``,
``cond``) and nested ``jit``/``custom_jvp`` calls are interpreted recursively.

The results are float64/float32 NumPy arrays equal to the compiled program's up to
roundoff (NumPy and XLA may order sums differently); the check's tolerances are far
above that. Tested against ``jax.jit`` on the library's models and on random programs.
"""

from __future__ import annotations

import jax
import numpy as np
from jax.extend import core as _jax_core

__all__ = ["eval_jaxpr"]


def _convert(x, *, new_dtype, **_):
    return np.asarray(x).astype(new_dtype)


def _broadcast_in_dim(x, *, shape, broadcast_dimensions, **_):
    x = np.asarray(x)
    expanded = [1] * len(shape)
    for axis, dim in zip(broadcast_dimensions, x.shape, strict=True):
        expanded[int(axis)] = dim
    return np.broadcast_to(x.reshape(expanded), shape)


def _dot_general(lhs, rhs, *, dimension_numbers, preferred_element_type=None, **_):
    (lc, rc), (lb, rb) = dimension_numbers
    lc, rc, lb, rb = ([int(a) for a in axes] for axes in (lc, rc, lb, rb))
    letters = iter("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ")
    lhs_sub = [None] * np.ndim(lhs)
    rhs_sub = [None] * np.ndim(rhs)
    batch = []
    for a, b in zip(lb, rb, strict=True):
        lhs_sub[a] = rhs_sub[b] = next(letters)
        batch.append(lhs_sub[a])
    for a, b in zip(lc, rc, strict=True):
        lhs_sub[a] = rhs_sub[b] = next(letters)
    lhs_free = [i for i in range(len(lhs_sub)) if lhs_sub[i] is None]
    rhs_free = [i for i in range(len(rhs_sub)) if rhs_sub[i] is None]
    for i in lhs_free:
        lhs_sub[i] = next(letters)
    for i in rhs_free:
        rhs_sub[i] = next(letters)
    out = batch + [lhs_sub[i] for i in lhs_free] + [rhs_sub[i] for i in rhs_free]
    spec = f"{''.join(lhs_sub)},{''.join(rhs_sub)}->{''.join(out)}"
    result = np.einsum(spec, lhs, rhs)
    if preferred_element_type is not None:
        result = result.astype(preferred_element_type)
    return result


def _slice(x, *, start_indices, limit_indices, strides=None, **_):
    strides = strides or (1,) * len(start_indices)
    return np.asarray(x)[
        tuple(
            slice(s, e, st) for s, e, st in zip(start_indices, limit_indices, strides, strict=True)
        )
    ]


def _reduce(fn):
    def apply(x, *, axes, **_):
        return fn(np.asarray(x), axis=tuple(int(a) for a in axes))

    return apply


def _cumulative(fn):
    def apply(x, *, axis, reverse=False, **_):
        x = np.asarray(x)
        if reverse:
            return np.flip(fn(np.flip(x, axis), axis=axis), axis)
        return fn(x, axis=axis)

    return apply


def _select_n(which, *cases):
    return np.choose(np.asarray(which).astype(np.int32), np.broadcast_arrays(*cases))


def _div(x, y, **_):
    x, y = np.asarray(x), np.asarray(y)
    if np.issubdtype(x.dtype, np.integer):  # XLA rounds an integer quotient toward zero
        return (np.sign(x) * np.sign(y) * (np.abs(x) // np.abs(y))).astype(x.dtype)
    return x / y


def _rem(x, y, **_):
    return np.fmod(np.asarray(x), np.asarray(y))  # the sign of the dividend, as XLA


def _integer_pow(x, *, y):
    return np.asarray(x) ** y


def _iota(*, dtype, shape, dimension, **_):
    index = np.arange(shape[dimension], dtype=dtype)
    expanded = [1] * len(shape)
    expanded[dimension] = shape[dimension]
    return np.broadcast_to(index.reshape(expanded), shape)


def _mode_name(mode):
    return getattr(mode, "name", str(mode)).upper()


def _gather(operand, indices, *, dimension_numbers, slice_sizes, mode, **_):
    dn = dimension_numbers
    if dn.operand_batching_dims or "FILL" in _mode_name(mode):
        raise NotImplementedError  # handed to JAX
    operand, indices = np.asarray(operand), np.asarray(indices)
    batch_shape = indices.shape[:-1]
    starts = indices.reshape(-1, indices.shape[-1])
    collapsed = tuple(int(d) for d in dn.collapsed_slice_dims)
    pieces = []
    for row in starts:
        start = [0] * operand.ndim
        for dim, value in zip(dn.start_index_map, row, strict=True):
            dim = int(dim)  # clamped so the slice fits, as XLA does
            start[dim] = int(np.clip(value, 0, operand.shape[dim] - slice_sizes[dim]))
        window = operand[
            tuple(slice(s, s + size) for s, size in zip(start, slice_sizes, strict=True))
        ]
        pieces.append(np.squeeze(window, axis=collapsed))
    window_shape = tuple(size for dim, size in enumerate(slice_sizes) if dim not in collapsed)
    stacked = np.stack(pieces).reshape(batch_shape + window_shape)
    offset = [int(d) for d in dn.offset_dims]
    source, next_batch = [], 0
    for position in range(stacked.ndim):
        if position in offset:
            source.append(len(batch_shape) + offset.index(position))
        else:
            source.append(next_batch)
            next_batch += 1
    return np.transpose(stacked, source)


def _scatter(combine):
    def apply(operand, indices, updates, *, dimension_numbers, mode, **params):
        dn = dimension_numbers
        if dn.operand_batching_dims or params.get("update_jaxpr") is not None and combine is None:
            raise NotImplementedError
        out = np.array(operand, copy=True)
        indices, updates = np.asarray(indices), np.asarray(updates)
        window_dims = [int(d) for d in dn.update_window_dims]
        scatter_dims = [d for d in range(updates.ndim) if d not in window_dims]
        updates = np.transpose(updates, scatter_dims + window_dims)
        n_scatter = len(scatter_dims)
        updates = updates.reshape((-1,) + updates.shape[n_scatter:])
        starts = indices.reshape(-1, indices.shape[-1])
        inserted = {int(d) for d in dn.inserted_window_dims}
        sizes, window = [], iter(updates.shape[1:])
        for dim in range(out.ndim):
            sizes.append(1 if dim in inserted else next(window))
        drop = "FILL" in _mode_name(mode)
        for row, update in zip(starts, updates, strict=True):
            start = [0] * out.ndim
            for dim, value in zip(dn.scatter_dims_to_operand_dims, row, strict=True):
                start[int(dim)] = int(value)
            fits = all(0 <= s <= out.shape[d] - sizes[d] for d, s in enumerate(start))
            if not fits:
                if drop:
                    continue
                start = [int(np.clip(s, 0, out.shape[d] - sizes[d])) for d, s in enumerate(start)]
            region = tuple(slice(s, s + size) for s, size in zip(start, sizes, strict=True))
            shaped = update.reshape([sizes[d] for d in range(out.ndim)])
            out[region] = shaped if combine is None else combine(out[region], shaped)
        return out

    return apply


def _pad(x, padding_value, *, padding_config):
    x = np.asarray(x)
    if any(lo < 0 or hi < 0 or interior for lo, hi, interior in padding_config):
        raise NotImplementedError
    widths = [(lo, hi) for lo, hi, _ in padding_config]
    return np.pad(x, widths, constant_values=np.asarray(padding_value).item())


def _triangular_solve(a, b, *, left_side, lower, transpose_a, conjugate_a, unit_diagonal):
    a = np.tril(a) if lower else np.triu(a)
    if unit_diagonal:
        eye = np.eye(a.shape[-1], dtype=bool)
        a = np.where(eye, 1, a)
    if conjugate_a:
        a = np.conj(a)
    if transpose_a:
        a = np.swapaxes(a, -1, -2)
    if left_side:
        return np.linalg.solve(a, b)
    return np.swapaxes(np.linalg.solve(np.swapaxes(a, -1, -2), np.swapaxes(b, -1, -2)), -1, -2)


def _cholesky(x, **_):
    x = np.asarray(x)
    try:
        return np.linalg.cholesky(x)
    except np.linalg.LinAlgError:  # XLA answers NaN where the matrix is not positive definite
        raise NotImplementedError from None


def _unary(fn):
    return lambda x, **_: fn(np.asarray(x))


def _binary(fn):
    return lambda x, y, **_: fn(np.asarray(x), np.asarray(y))


_TABLE = {
    "add": _binary(np.add),
    "sub": _binary(np.subtract),
    "mul": _binary(np.multiply),
    "div": _div,
    "rem": _rem,
    "max": _binary(np.maximum),
    "min": _binary(np.minimum),
    "pow": _binary(np.power),
    "atan2": _binary(np.arctan2),
    "lt": _binary(np.less),
    "le": _binary(np.less_equal),
    "gt": _binary(np.greater),
    "ge": _binary(np.greater_equal),
    "eq": _binary(np.equal),
    "ne": _binary(np.not_equal),
    "and": _binary(np.logical_and),
    "or": _binary(np.logical_or),
    "neg": _unary(np.negative),
    "sin": _unary(np.sin),
    "cos": _unary(np.cos),
    "tan": _unary(np.tan),
    "tanh": _unary(np.tanh),
    "exp": _unary(np.exp),
    "log": _unary(np.log),
    "log1p": _unary(np.log1p),
    "expm1": _unary(np.expm1),
    "sqrt": _unary(np.sqrt),
    "rsqrt": _unary(lambda x: 1.0 / np.sqrt(x)),
    "abs": _unary(np.abs),
    "sign": _unary(np.sign),
    "floor": _unary(np.floor),
    "ceil": _unary(np.ceil),
    "square": _unary(np.square),
    "not": _unary(np.logical_not),
    "asin": _unary(np.arcsin),
    "acos": _unary(np.arccos),
    "atan": _unary(np.arctan),
    "logistic": _unary(lambda x: 1.0 / (1.0 + np.exp(-x))),
    "integer_pow": _integer_pow,
    "convert_element_type": _convert,
    "broadcast_in_dim": _broadcast_in_dim,
    "dot_general": _dot_general,
    "reshape": lambda x, *, new_sizes, **_: np.reshape(x, new_sizes),
    "squeeze": lambda x, *, dimensions: np.squeeze(x, axis=tuple(int(d) for d in dimensions)),
    "expand_dims": lambda x, *, dimensions: np.expand_dims(x, tuple(dimensions)),
    "transpose": lambda x, *, permutation: np.transpose(x, permutation),
    "rev": lambda x, *, dimensions: np.flip(x, axis=tuple(int(d) for d in dimensions)),
    "slice": _slice,
    "concatenate": lambda *xs, dimension: np.concatenate(xs, axis=dimension),
    "stack": lambda *xs, axis: np.stack(xs, axis=axis),
    "select_n": _select_n,
    "iota": _iota,
    "reduce_sum": _reduce(np.sum),
    "reduce_max": _reduce(np.max),
    "reduce_min": _reduce(np.min),
    "reduce_prod": _reduce(np.prod),
    "cumsum": _cumulative(np.cumsum),
    "cumprod": _cumulative(np.cumprod),
    "copy": _unary(np.copy),
    "copy_p": _unary(np.copy),
    "stop_gradient": _unary(lambda x: x),
    "gather": _gather,
    "scatter-add": _scatter(np.add),
    "scatter_add": _scatter(np.add),
    "scatter": _scatter(None),
    "pad": _pad,
    "cholesky": _cholesky,
    "triangular_solve": _triangular_solve,
}


def _sub_jaxpr(params):
    """The closed jaxpr a call-like primitive (jit, custom_jvp/vjp, remat) wraps, or None."""
    for key in ("jaxpr", "call_jaxpr", "fun_jaxpr"):
        inner = params.get(key)
        if inner is None:
            continue
        if isinstance(inner, _jax_core.ClosedJaxpr):
            return inner.jaxpr, inner.consts
        if isinstance(inner, _jax_core.Jaxpr):
            return inner, ()
    return None


def _while(args, params):
    cond, body = params["cond_jaxpr"], params["body_jaxpr"]
    nc, nb = params["cond_nconsts"], params["body_nconsts"]
    cond_consts, body_consts, carry = args[:nc], args[nc : nc + nb], list(args[nc + nb :])
    while bool(eval_jaxpr(cond.jaxpr, cond.consts, *cond_consts, *carry)[0]):
        carry = eval_jaxpr(body.jaxpr, body.consts, *body_consts, *carry)
    return carry


def _scan(args, params):
    jaxpr, length, reverse = params["jaxpr"], params["length"], params["reverse"]
    n_consts, n_carry = params["num_consts"], params["num_carry"]
    consts, carry, xs = (
        args[:n_consts],
        list(args[n_consts : n_consts + n_carry]),
        args[n_consts + n_carry :],
    )
    ys = []
    for i in reversed(range(length)) if reverse else range(length):
        out = eval_jaxpr(jaxpr.jaxpr, jaxpr.consts, *consts, *carry, *(x[i] for x in xs))
        carry, y = list(out[:n_carry]), out[n_carry:]
        ys.append(y)
    if reverse:
        ys.reverse()
    outs = jaxpr.jaxpr.outvars[n_carry:]
    if not length:
        return carry + [np.zeros((0, *v.aval.shape), v.aval.dtype) for v in outs]
    return carry + [np.stack([y[j] for y in ys]) for j in range(len(outs))]


def _cond(args, params):
    index, operands = args[0], args[1:]
    branch = params["branches"][int(np.clip(int(index), 0, len(params["branches"]) - 1))]
    return eval_jaxpr(branch.jaxpr, branch.consts, *operands)


_CONTROL = {"while": _while, "scan": _scan, "cond": _cond}
_CALLS = {"jit", "pjit", "custom_jvp_call", "custom_vjp_call", "remat", "checkpoint", "closed_call"}


def _bind(eqn, args):
    """Hand a primitive the table lacks to JAX (eager: compiled once per signature)."""
    out = eqn.primitive.bind(*args, **eqn.params)
    if eqn.primitive.multiple_results:
        return [np.asarray(o) for o in out]
    return np.asarray(out)


def eval_jaxpr(jaxpr, consts, *args):
    """Evaluate ``jaxpr`` (a ``jax.core.Jaxpr``) on NumPy arrays; a list of outputs."""
    env = {}

    def read(var):
        if isinstance(var, _jax_core.Literal):
            return np.asarray(var.val)
        return env[var]

    for var, value in zip(jaxpr.constvars, consts, strict=True):
        env[var] = np.asarray(value)
    for var, value in zip(jaxpr.invars, args, strict=True):
        env[var] = np.asarray(value)
    for eqn in jaxpr.eqns:
        inputs = [read(v) for v in eqn.invars]
        name = eqn.primitive.name
        inner = _sub_jaxpr(eqn.params)
        if name in _CONTROL:
            out = _CONTROL[name](inputs, eqn.params)
        elif name in _TABLE:
            try:
                out = _TABLE[name](*inputs, **eqn.params)
            except NotImplementedError:  # a case the table does not cover
                out = _bind(eqn, inputs)
        elif inner is not None and name in _CALLS:
            out = eval_jaxpr(inner[0], inner[1], *inputs)
        else:
            out = _bind(eqn, inputs)
        if eqn.primitive.multiple_results:
            for var, value in zip(eqn.outvars, out, strict=True):
                env[var] = np.asarray(value, dtype=var.aval.dtype)
        else:
            env[eqn.outvars[0]] = np.asarray(out, dtype=eqn.outvars[0].aval.dtype)
    return [read(v) for v in jaxpr.outvars]


def evaluate(fn, *args):
    """``fn(*args)`` (a pure JAX function of arrays) evaluated by NumPy, as a tuple."""
    closed = jax.make_jaxpr(fn)(*args)
    return tuple(eval_jaxpr(closed.jaxpr, closed.consts, *args))
