"""The tape replay (rmijax._intervals.replay) keeps only live values in its buffers: every
read finds the value the tape means, the outputs survive, the rows are reused, and the
replayed values equal a plain evaluation of the same operations."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rmijax
from rmijax._intervals import _CODE, Tape, _slots, replay
from rmijax.methods.certified import _perturbation_tape, _tape_leaves


def _random_tape(rng, n_leaves=5, n_ops=300):
    """A tape of random operations on random earlier values (mostly recent ones, as the jet
    formulas read), and a few outputs."""
    tape = Tape(n_leaves)
    nodes = tape.leaves()
    for _ in range(n_ops):
        kind = rng.choice(["const", "add", "sub", "mul", "neg", "sin", "cos", "tanh", "sqr"])
        pick = lambda: nodes[max(0, len(nodes) - 1 - int(rng.geometric(0.2)))]  # noqa: E731
        a, b = pick(), pick()
        if kind == "const":
            node = tape._push("const", lit=float(rng.normal()))
        elif kind in ("add", "sub", "mul"):
            node = {"add": a + b, "sub": a - b, "mul": a * b}[kind]
        elif kind == "neg":
            node = -a
        else:
            node = getattr(a, {"sqr": "square"}.get(kind, kind))()
        nodes.append(node)
    outputs = sorted({nodes[-1].index, nodes[len(nodes) // 2].index, 1})
    return tape, outputs


def _occupants(ops, args, n_leaves, outputs):
    """Replays :func:`_slots`' plan on labels: which value each row holds after each op."""
    dest, rows, out, size = _slots(ops, args, n_leaves, outputs)
    holder = list(range(n_leaves)) + [None] * (size - n_leaves)
    for i in range(ops.shape[0]):
        if ops[i] != _CODE["const"]:
            for k in range(2):
                assert holder[rows[i, k]] == args[i, k], f"op {i} reads a reused row"
        holder[dest[i]] = n_leaves + i
    assert [holder[r] for r in out] == list(outputs)
    return size


def test_slots_never_overwrite_a_value_that_is_read_later():
    rng = np.random.default_rng(0)
    for _ in range(5):
        tape, outputs = _random_tape(rng)
        ops, args, _ = tape.arrays()
        size = _occupants(ops, args, tape.n_leaves, outputs)
        assert size < tape.n_leaves + ops.shape[0]


@pytest.mark.parametrize("precond, ranged", [(False, False), (True, "auto")])
def test_the_chain_tapes_fit_in_a_tenth_of_the_rows(precond, ranged):
    """The 6-joint chain's tape (the UR5e's shape): 2661 operations held in under 300 rows."""
    params = rmijax.load_robot("ur5e", mass=0.1)
    layout = params.model.structure.layout
    p = params.n_params
    (ops, args, _), rows = _perturbation_tape(layout, 6, p, False, precond, ranged)
    n_leaves = _tape_leaves(6, p, False, precond, ranged)
    size = _occupants(ops, args, n_leaves, rows)
    assert size * 10 < n_leaves + ops.shape[0]


def test_replay_equals_the_plain_evaluation():
    rng = np.random.default_rng(1)
    tape, outputs = _random_tape(rng, n_ops=200)
    ops, args, lits = tape.arrays()
    leaves = rng.uniform(-1.0, 1.0, size=tape.n_leaves)
    fns = {
        "add": jnp.add,
        "sub": jnp.subtract,
        "mul": jnp.multiply,
        "neg": lambda a, b: -a,
        "sqr": lambda a, b: a * a,
        "sin": lambda a, b: jnp.sin(a),
        "cos": lambda a, b: jnp.cos(a),
        "tanh": lambda a, b: jnp.tanh(a),
        "recip": lambda a, b: 1.0 / a,
    }
    branches = [lambda a, b, lit: (lit,)] + [
        (lambda fn: lambda a, b, lit: (fn(a[0], b[0]),))(fns[name])
        for name in ("add", "sub", "mul", "neg", "recip", "sqr", "sin", "cos", "tanh")
    ]
    with jax.enable_x64(True):
        (got,) = jax.jit(lambda x: replay((ops, args, lits), (x,), branches, outputs))(
            jnp.asarray(leaves)
        )
        values = [float(v) for v in leaves]
        names = {code: name for name, code in _CODE.items()}
        for i, op in enumerate(ops):
            a, b = values[args[i, 0]], values[args[i, 1]]
            name = names[int(op)]
            values.append(lits[i] if name == "const" else float(fns[name](a, b)))
        np.testing.assert_allclose(np.asarray(got), [values[r] for r in outputs], rtol=1e-13)
