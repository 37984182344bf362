"""The NumPy jaxpr interpreter the model check uses equals XLA's compiled program."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

import rmijax
from rmijax.robots import _numpy_eval, check


def _assert_equal_to_jit(fn, *args, rtol=1e-12):
    got = _numpy_eval.evaluate(fn, *args)
    want = jax.tree_util.tree_leaves(jax.jit(fn)(*args))
    assert len(got) == len(want)
    for g, w in zip(got, want, strict=True):
        w = np.asarray(w)
        assert g.shape == w.shape and g.dtype == w.dtype
        np.testing.assert_allclose(g, w, rtol=rtol, atol=rtol)


def _batch(params, rng, size=9):
    n = params.model.n_joints
    lo, hi = np.asarray(params.lo), np.asarray(params.hi)
    th = lo + (hi - lo) * rng.uniform(size=(size, lo.size))
    q, qd = rng.normal(size=(2, size, n))
    return q, qd, th, rng.normal(size=n)


@pytest.mark.parametrize(
    "make",
    [
        rmijax.paper_arm2,
        rmijax.paper_pendulum,
        lambda: rmijax.preset_arm(5),
        pytest.param(
            lambda: rmijax.load_robot(
                "panda",
                mass=0.1,
                payload=(0.0, 1.0),
                friction=dict(viscous=(0.0, 0.1), coulomb=(0.0, 0.2)),
            ),
            marks=pytest.mark.slow,
            id="panda",
        ),
        pytest.param(
            lambda: rmijax.load_robot("ur5e", mass=0.2), marks=pytest.mark.slow, id="ur5e"
        ),
    ],
)
def test_library_models_evaluate_as_compiled(make, rng):
    params = make()
    _assert_equal_to_jit(check._evaluator(params.model), *_batch(params, rng), rtol=1e-11)


def test_float32_stays_float32(rng):
    params = rmijax.paper_arm2(dtype=jnp.float32)
    args = [np.asarray(a, np.float32) for a in _batch(params, rng)]
    _assert_equal_to_jit(check._evaluator(params.model), *args, rtol=2e-5)


def test_control_flow_linear_algebra_and_integers(rng):
    a = rng.normal(size=(4, 4))
    spd = a @ a.T + 4 * np.eye(4)

    def fn(x, m, k):
        y = lax.fori_loop(0, 3, lambda i, c: c * 0.5 + jnp.sin(c) * i, x)
        carry, ys = lax.scan(lambda c, v: (c + v, c * v), 0.0, x)
        z = lax.cond(x[0] > 0, lambda v: v * 2.0, lambda v: v - 1.0, x)
        w = lax.while_loop(lambda c: c[0] < 10, lambda c: (c[0] + 3, c[1] * 1.5), (0, x))
        sol = jnp.linalg.solve(m, x)
        chol = jnp.linalg.cholesky(m)
        tri = jax.scipy.linalg.solve_triangular(chol, x, lower=True)
        picked = x[k] + x.at[k].add(2.0)[1:3].sum() + jnp.pad(x, (1, 2))[::2].sum()
        quotient = (
            jnp.array([-7, 7, -8]) // jnp.array([2, -2, 3]),
            lax.div(jnp.array([-7, 7]), jnp.array([2, 2])),
        )
        return y, carry, ys, z, w[1], sol, chol, tri, picked, *quotient, jnp.cumsum(x[::-1])

    x = rng.normal(size=4)
    _assert_equal_to_jit(fn, x, spd, 2)


def test_the_check_of_a_user_arm_compiles_nothing(monkeypatch):
    params = rmijax.paper_arm2()
    user = dataclasses.replace(params, model=dataclasses.replace(params.model, trusted=False))
    traj = rmijax.trajectory(["hold", "sine"], duration=1.0)

    def refuse(*args):
        raise AssertionError("the check compiled the model instead of interpreting it")

    monkeypatch.setattr(check, "_compiled", refuse)
    check._CACHE.clear()
    rmijax.check_model(user, traj)
    broken = dataclasses.replace(
        user, model=dataclasses.replace(user.model, forward_dynamics=lambda q, qd, tau, th: tau)
    )
    with pytest.raises(rmijax.ModelCheckError, match="forward_dynamics disagrees"):
        rmijax.check_model(broken, traj)


def test_a_function_the_interpreter_cannot_run_falls_back_to_xla(monkeypatch):
    def fn(x):
        return (jnp.fft.fft(x).real,)

    x = np.linspace(0.0, 1.0, 8)
    _assert_equal_to_jit(fn, x)
