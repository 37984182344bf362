"""Tests of rmijax.corner_search: RMI with the extreme corner searched, not enumerated."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import rmijax
from rmijax.methods import corner_search, rmi as engine
from rmijax.methods.corner_search import LocalSearch, corner_agreement, corner_search_bounds

from helpers import random_arm

ARM_PATHS = ["slow_sine", "sine", "composite", "slow_sine"]


# --------------------------------------------------------------------------
# The chooser on its own, against a plainly written search
# --------------------------------------------------------------------------


def plain_local_search(score, gradient, nominal, lo, hi, rounds):
    """The search written plainly in NumPy: gradient-sign start, best single flip per round."""
    rtol = np.finfo(np.float64).eps ** (2.0 / 3.0)
    gain = gradient * (hi - lo)
    bits = gain > rtol * (np.sum(np.abs(gain)) + abs(score(nominal)))
    current = score(np.where(bits, hi, lo))
    for _ in range(rounds):
        candidates = []
        for b in range(lo.size):
            flipped = bits.copy()
            flipped[b] = not flipped[b]
            candidates.append((score(np.where(flipped, hi, lo)), flipped))
        scores = np.array([c[0] for c in candidates])
        best = int(np.argmax(scores))
        tol = rtol * max(np.max(np.abs(scores)), abs(current))
        if not scores[best] > current + tol:
            break
        current, bits = scores[best], candidates[best][1]
    return np.where(bits, hi, lo), current


def random_score(rng, p):
    """A smooth non-separable score: linear plus quadratic plus a product term."""
    linear = rng.normal(size=p)
    quadratic = rng.normal(size=(p, p)) * 2.0

    def score_np(th):
        return float(linear @ th + th @ quadratic @ th + 0.5 * np.prod(th))

    def score_jax(th):
        return jnp.dot(linear, th) + jnp.dot(th, quadratic @ th) + 0.5 * jnp.prod(th)

    def gradient_np(th):
        others = np.array([np.prod(np.delete(th, b)) for b in range(p)])
        return linear + (quadratic + quadratic.T) @ th + 0.5 * others

    return score_np, score_jax, gradient_np


@pytest.mark.parametrize("max_rounds", [None, 0, 2])
@pytest.mark.parametrize("seed", range(6))
def test_local_search_matches_plain_reference(seed, max_rounds):
    rng = np.random.default_rng(seed)
    p = 7
    nominal = rng.uniform(-1.0, 1.0, p)
    lo, hi = nominal - rng.uniform(0.1, 1.0, p), nominal + rng.uniform(0.1, 1.0, p)
    score_np, score_jax, gradient_np = random_score(rng, p)
    consts = dict(nominal=jnp.asarray(nominal), lo=jnp.asarray(lo), hi=jnp.asarray(hi))
    search = LocalSearch(max_rounds)
    found, found_score = jax.jit(lambda c: search.search(score_jax, 1.0, 0.0, c))(consts)
    rounds = p if max_rounds is None else max_rounds
    expected, expected_score = plain_local_search(
        score_np, gradient_np(nominal), nominal, lo, hi, rounds
    )
    np.testing.assert_array_equal(found, expected)
    np.testing.assert_allclose(found_score, expected_score, rtol=1e-12)
    # the result is a corner and its score is the score of that corner
    assert np.all((np.asarray(found) == lo) | (np.asarray(found) == hi))
    np.testing.assert_allclose(found_score, score_np(np.asarray(found)), rtol=1e-12)
    if max_rounds is None:  # converged: no single flip beats it (p rounds never ran out here)
        bits = np.asarray(found) == hi
        for b in range(p):
            flipped = bits.copy()
            flipped[b] = not flipped[b]
            assert score_np(np.where(flipped, hi, lo)) <= expected_score + 1e-9


def test_local_search_finds_the_maximum_of_a_separable_score():
    # A separable monotone score: the gradient sign alone is the exhaustive argmax.
    rng = np.random.default_rng(3)
    p = 9
    slopes = rng.normal(size=p)
    nominal = rng.uniform(1.0, 2.0, p)
    lo, hi = nominal - 0.3, nominal + 0.4
    corners = np.asarray(rmijax.corner_tensor(jnp.asarray(lo), jnp.asarray(hi)))
    best = corners[np.argmax(corners @ slopes)]
    consts = dict(nominal=jnp.asarray(nominal), lo=jnp.asarray(lo), hi=jnp.asarray(hi))
    for search in (LocalSearch(), LocalSearch(0)):
        found = search(lambda th: jnp.dot(slopes, th), 1.0, 0.0, consts)
        np.testing.assert_array_equal(found, best)
        # the weight's sign turns the max into the min
        found = search(lambda th: jnp.dot(slopes, th), -2.0, 0.0, consts)
        np.testing.assert_array_equal(found, corners[np.argmin(corners @ slopes)])


def test_zero_weight_picks_the_lowest_corner():
    consts = dict(nominal=jnp.ones(3), lo=jnp.zeros(3), hi=jnp.full(3, 2.0))
    found = LocalSearch()(lambda th: jnp.sum(th**2), 0.0, 0.0, consts)
    np.testing.assert_array_equal(found, np.zeros(3))  # all scores tie: contract's corner 0


# --------------------------------------------------------------------------
# Equality with exact RMI where the decisions agree
# --------------------------------------------------------------------------


@pytest.mark.parametrize("path", ["sine", "ramp", "composite"])
def test_pendulum_equals_rmi(path):
    traj = rmijax.trajectory(path, duration=3.0)
    params = rmijax.paper_pendulum()
    searched = corner_search_bounds(traj, params)
    exact = rmijax.rmi(traj, params)
    np.testing.assert_allclose(searched.lower, exact.lower, rtol=0, atol=1e-10)
    np.testing.assert_allclose(searched.upper, exact.upper, rtol=0, atol=1e-10)
    np.testing.assert_array_equal(searched.nominal, exact.nominal)
    assert searched.dt == exact.dt
    assert float(jnp.max(exact.width)) > 1e-3


def linear_bias(q, qd, th):
    """Bias forces linear in the parameters: gv is monotone in every one of them."""
    g = rmijax.GRAVITY
    return jnp.stack(
        [th[0] * g * jnp.cos(q[0]) + th[1] * qd[0], th[2] * g * jnp.sin(q[1]) + th[3] * qd[1] ** 3]
    )


def unit_mass_matrix(q, th):
    del th
    return jnp.eye(2, dtype=q.dtype)


MONOTONE_MODEL = rmijax.RobotModel(2, 4, unit_mass_matrix, linear_bias, name="linear_toy")


@pytest.mark.parametrize("max_rounds", [None, 0])
@pytest.mark.parametrize("mode", rmijax.MODES)
def test_monotone_model_equals_rmi(mode, max_rounds):
    params = rmijax.uncertain_robot(
        MONOTONE_MODEL, [1.0, 0.5, 2.0, 0.2], [0.8, 0.3, 1.5, 0.1], [1.3, 0.6, 2.2, 0.4]
    )
    traj = rmijax.trajectory(["sine", "composite"], duration=1.0)
    searched = corner_search_bounds(traj, params, mode=mode, window=40, max_rounds=max_rounds)
    exact = rmijax.rmi(traj, params, mode=mode, window=40)
    np.testing.assert_allclose(searched.lower, exact.lower, rtol=0, atol=1e-10)
    np.testing.assert_allclose(searched.upper, exact.upper, rtol=0, atol=1e-10)
    assert float(jnp.max(exact.width)) > 1e-3


def toy_mass_matrix(q, th):
    """A revolute-prismatic toy (as in tests/test_engine.py): th = (m1, c1, m2)."""
    m1, c1, m2 = th[0], th[1], th[2]
    return jnp.array([[m1 * c1**2 + m2 * q[1] ** 2, 0.0], [0.0, m2]])


def toy_bias(q, qd, th):
    m1, c1, m2 = th[0], th[1], th[2]
    g = rmijax.GRAVITY
    return jnp.array(
        [
            2.0 * m2 * q[1] * qd[0] * qd[1] + (m1 * c1 + m2 * q[1]) * g * jnp.cos(q[0]),
            -m2 * q[1] * qd[0] ** 2 + m2 * g * jnp.sin(q[0]),
        ]
    )


def toy_robot():
    model = rmijax.RobotModel(2, 3, toy_mass_matrix, toy_bias, name="rp_toy")
    return rmijax.uncertain_robot(model, [4.0, 0.5, 2.0], [3.5, 0.45, 1.6], [4.8, 0.52, 2.3])


def check_agreement(result, traj, params, *, mode, window, max_rounds=None):
    """Invariants of a corner_agreement result, with both bound sets recomputed independently."""
    steps = result["end_steps"]
    n = traj.n_joints
    assert result["decisions"] == 4 * n * int(np.sum(np.minimum(steps, window)))
    assert 0.0 <= result["agree"] <= result["agree_score"] <= 1.0
    assert result["max_abs_error"] >= 0.0 and result["max_rel_error"] >= 0.0
    exact = rmijax.rmi(traj, params, mode=mode, window=window)
    searched = corner_search_bounds(traj, params, mode=mode, window=window, max_rounds=max_rounds)
    for mine, full in ((result["exact"], exact), (result["searched"], searched)):
        np.testing.assert_allclose(mine.lower, full.lower[steps], rtol=0, atol=1e-12)
        np.testing.assert_allclose(mine.upper, full.upper[steps], rtol=0, atol=1e-12)
    error = max(
        float(np.max(np.abs(searched.lower[steps] - exact.lower[steps]))),
        float(np.max(np.abs(searched.upper[steps] - exact.upper[steps]))),
    )
    np.testing.assert_allclose(result["max_abs_error"], error, rtol=0, atol=1e-12)
    if result["agree"] == 1.0:  # same decisions, same tracks: same bounds up to roundoff
        assert result["max_abs_error"] <= 1e-12
    return exact, searched


@pytest.mark.parametrize("mode", rmijax.MODES)
def test_agreement_is_total_where_the_score_is_affine(mode):
    """With a unit mass matrix and a bias linear in the parameters every score is affine
    in them, so the gradient-sign start is the exhaustive corner at every decision:
    agreement must be exactly 1 (a property, not a measurement)."""
    params = rmijax.uncertain_robot(
        MONOTONE_MODEL, [1.0, 0.5, 2.0, 0.2], [0.8, 0.3, 1.5, 0.1], [1.3, 0.6, 2.2, 0.4]
    )
    traj = rmijax.trajectory(["sine", "composite"], duration=0.6)
    for rounds in (None, 0):
        result = corner_agreement(traj, params, [0, 7, 30, 60], mode=mode, window=30,
                                  max_rounds=rounds)  # fmt: skip
        check_agreement(result, traj, params, mode=mode, window=30, max_rounds=rounds)
        assert result["agree"] == 1.0 and result["max_abs_error"] <= 1e-12


@pytest.mark.parametrize("mode", rmijax.MODES)
def test_user_model_agreement_is_measured_right(mode):
    params = toy_robot()
    traj = rmijax.trajectory(["sine", lambda t: 1.0 + 0.2 * jnp.sin(2.0 * t)], duration=0.6)
    result = corner_agreement(traj, params, [0, 7, 30, 60], mode=mode, window=30)
    check_agreement(result, traj, params, mode=mode, window=30)


@pytest.mark.parametrize(
    "n, mode",
    [
        (2, "coupled"),
        pytest.param(4, "coupled", marks=pytest.mark.slow),
        (2, "per_joint"),
        pytest.param(4, "per_joint", marks=pytest.mark.slow),
    ],
)
def test_flips_never_lose_agreement_on_small_arms(n, mode):
    """Decisions are taken along exact RMI's tracks, so both searches see the same
    states; the flips only accept a strictly better corner, so wherever the gradient
    start is the exhaustive corner the full search is too: its agreement can only be
    higher. (How high it is on these arms is a measurement: the agreement table of
    ``notebooks/method_comparison_conclusions.md``, not a test.) Two and four links: the
    three-link cases (90 s of CI time) checked the same property between them."""
    params = rmijax.preset_arm(n)
    traj = rmijax.trajectory(ARM_PATHS[:n], duration=0.3)
    full = corner_agreement(traj, params, [15, 22, 30], mode=mode, window=15)
    start = corner_agreement(traj, params, [15, 22, 30], mode=mode, window=15, max_rounds=0)
    check_agreement(full, traj, params, mode=mode, window=15)
    check_agreement(start, traj, params, mode=mode, window=15, max_rounds=0)
    assert full["decisions"] == start["decisions"]
    assert full["agree"] >= start["agree"]
    assert full["agree_score"] >= start["agree_score"]


def test_flips_fix_what_the_gradient_start_gets_wrong():
    rng = np.random.default_rng(20261124)
    params = random_arm(rng, 3)
    traj = rmijax.trajectory(ARM_PATHS[:3], duration=0.6)
    full = corner_agreement(traj, params, [30, 60], window=30)
    start_only = corner_agreement(traj, params, [30, 60], window=30, max_rounds=0)
    check_agreement(start_only, traj, params, mode="coupled", window=30, max_rounds=0)
    assert start_only["agree"] < 1.0  # not vacuous: the start alone misses some corners
    assert full["agree"] >= start_only["agree"]  # and the flips never lose one


# --------------------------------------------------------------------------
# Interface: noise, online form, options, no recompilation
# --------------------------------------------------------------------------


def test_noise_is_added_to_the_bounds():
    traj = rmijax.trajectory("sine", duration=0.5)
    params = rmijax.paper_pendulum()
    plain = corner_search_bounds(traj, params, window=20)
    noise_lo, noise_hi = np.array([-1e-3, -2e-2]), np.array([2e-3, 1e-2])
    noisy = corner_search_bounds(traj, params, window=20, noise_lo=noise_lo, noise_hi=noise_hi)
    np.testing.assert_array_equal(noisy.lower, plain.lower + noise_lo[None, None, :])
    np.testing.assert_array_equal(noisy.upper, plain.upper + noise_hi[None, None, :])


@pytest.mark.parametrize("mode", rmijax.MODES)
def test_online_step_equals_offline(mode):
    traj = rmijax.trajectory(["slow_sine", "composite"], duration=0.5)
    params = rmijax.paper_arm2()
    offline = corner_search_bounds(traj, params, mode=mode, window=20)
    for t_f in (0, 7, 33, 50):
        online = corner_search.corner_search_step(traj, params, t_f, mode=mode, window=20)
        np.testing.assert_allclose(online.lower, offline.lower[t_f], rtol=0, atol=1e-13)
        np.testing.assert_allclose(online.upper, offline.upper[t_f], rtol=0, atol=1e-13)


def test_equal_choosers_do_not_recompile():
    traj = rmijax.trajectory("composite", duration=0.3)
    params = rmijax.paper_pendulum()
    corner_search_bounds(traj, params, window=11, max_rounds=3)
    size = engine._rmi_all._cache_size()
    corner_search_bounds(traj, params, window=11, max_rounds=3)
    assert engine._rmi_all._cache_size() == size
    assert LocalSearch(3) == LocalSearch(3) and hash(LocalSearch(3)) == hash(LocalSearch(3))


@pytest.mark.parametrize("bad", [-1, 1.5, True, "2", np.float64(2.0)])
def test_bad_max_rounds(bad):
    traj = rmijax.trajectory("sine", duration=0.1)
    params = rmijax.paper_pendulum()
    with pytest.raises(ValueError, match="max_rounds"):
        corner_search_bounds(traj, params, max_rounds=bad)
    with pytest.raises(ValueError, match="max_rounds"):
        LocalSearch(bad)
    with pytest.raises(ValueError, match="max_rounds"):
        corner_agreement(traj, params, [5], max_rounds=bad)


@pytest.mark.parametrize(
    "end_steps, message",
    [([], "non-empty"), ([[1, 2]], "1-D"), ([1.5], "integer"), ([11], r"outside .*\[0, 10\]")],
)
def test_bad_end_steps(end_steps, message):
    traj = rmijax.trajectory("sine", duration=0.1)
    with pytest.raises(ValueError, match=message):
        corner_agreement(traj, rmijax.paper_pendulum(), end_steps)


def test_bad_noise_and_mode_are_refused():
    traj = rmijax.trajectory("sine", duration=0.1)
    params = rmijax.paper_pendulum()
    with pytest.raises(ValueError, match="noise_lo > noise_hi"):
        corner_search_bounds(traj, params, noise_lo=0.1, noise_hi=0.0)
    with pytest.raises(ValueError, match="unknown mode"):
        corner_search_bounds(traj, params, mode="exact")
    with pytest.raises(ValueError, match="window"):
        corner_search_bounds(traj, params, window=0)


# --------------------------------------------------------------------------
# Scaling: no 2^p arrays, memory estimate, 16 links
# --------------------------------------------------------------------------


def test_no_corner_tensor_for_the_chooser():
    params = rmijax.preset_arm(16)
    gains = jnp.full(16, 100.0), jnp.full(16, 20.0)
    consts = engine.window_constants(params, *gains, 0.01, 5, search=LocalSearch())
    assert "corners" not in consts


def largest_intermediate(jaxpr):
    """Elements of the largest array any equation of ``jaxpr`` (and its sub-jaxprs) makes."""
    largest = 0
    for eqn in jaxpr.eqns:
        for var in eqn.outvars:
            largest = max(largest, int(np.prod(getattr(var.aval, "shape", ()))))
        for param in eqn.params.values():
            for sub in param if isinstance(param, (tuple, list)) else (param,):
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    largest = max(largest, largest_intermediate(inner))
    return largest


@pytest.mark.parametrize("mode", rmijax.MODES)
def test_nothing_grows_with_two_to_the_p(mode):
    n = 16
    params = corner_search.search_robot(rmijax.preset_arm(n))
    traj = rmijax.trajectory(["sine"] * n, duration=0.05)
    noise = jnp.zeros((n, 2))
    fn = functools.partial(engine._rmi_all, mode=mode, window=10, batch=2, search=LocalSearch())
    jaxpr = jax.make_jaxpr(fn)(traj, params, noise, noise).jaxpr
    p = params.n_params
    largest = largest_intermediate(jaxpr)
    # the flips' mass matrices (2 end steps x 4n tracks x p flips x n x n) are the largest
    assert 2 * 4 * n * p * n * n <= largest <= 2 * 4 * n * (p + 2) * n * n < 2**p


def test_search_robot_drops_the_closed_form_only_for_big_arms():
    small = rmijax.preset_arm(corner_search.CLOSED_FORM_MAX_LINKS)
    assert corner_search.search_robot(small) is small
    big = corner_search.search_robot(rmijax.preset_arm(corner_search.CLOSED_FORM_MAX_LINKS + 1))
    assert big.model.forward_dynamics is None
    # the general solve is the same function: equal bounds on a small arm
    params = rmijax.preset_arm(3)
    solved = dataclasses.replace(
        params, model=dataclasses.replace(params.model, forward_dynamics=None)
    )
    traj = rmijax.trajectory(ARM_PATHS[:3], duration=0.3)
    closed = engine.rmi(traj, params, window=15, search=LocalSearch())
    general = engine.rmi(traj, solved, window=15, search=LocalSearch())
    np.testing.assert_allclose(general.lower, closed.lower, rtol=0, atol=1e-10)
    np.testing.assert_allclose(general.upper, closed.upper, rtol=0, atol=1e-10)


@pytest.mark.parametrize(
    "n, mode, batch",
    [(1, "coupled", 1), (3, "coupled", 4), (3, "per_joint", 1), (8, "coupled", 1)],
)
def test_memory_estimate_bounds_xla_buffers(n, mode, batch):
    params = corner_search.search_robot(rmijax.preset_arm(n))
    traj = rmijax.trajectory(["sine"] * n, duration=0.1)
    noise = jnp.zeros((n, 2))
    compiled = engine._rmi_all.lower(
        traj, params, noise, noise, mode=mode, window=100, batch=batch, search=LocalSearch()
    ).compile()
    temp = compiled.memory_analysis().temp_size_in_bytes
    estimate = rmijax.estimate_memory(params, mode=mode, search=LocalSearch())
    assert temp <= batch * estimate


def test_memory_estimate_user_model():
    params = toy_robot()
    traj = rmijax.trajectory(["sine", "sine"], duration=0.1)
    noise = jnp.zeros((2, 2))
    for mode in rmijax.MODES:
        compiled = engine._rmi_all.lower(
            traj, params, noise, noise, mode=mode, window=100, batch=2, search=LocalSearch()
        ).compile()
        temp = compiled.memory_analysis().temp_size_in_bytes
        assert temp <= 2 * rmijax.estimate_memory(params, mode=mode, search=LocalSearch())


@functools.cache  # one model object per size: a fresh closure would recompile every call
def coupled_affine_model(n):
    """n joints, unit mass matrix, a bias linear in all 2n parameters that couples every
    joint to every parameter: each track's score is affine in all of them."""
    g = rmijax.GRAVITY
    phase = jnp.arange(2 * n) * 0.37

    def bias(q, qd, th):
        mix = g * jnp.cos(q[:, None] + phase[None, :]) + 0.1 * qd[:, None] * jnp.sin(phase)[None, :]
        return mix @ th

    def mass(q, th):
        del th
        return jnp.eye(n, dtype=q.dtype)

    return rmijax.RobotModel(n, 2 * n, mass, bias, name=f"coupled_affine_{n}")


def sign_chooser(perturbation, weight, offset, consts):
    """The exact corner of an affine score, written plainly: each parameter by the sign of
    its coefficient (a zero coefficient ties: lo)."""
    lo, hi, nominal = consts["lo"], consts["hi"], consts["nominal"]
    gain = jax.grad(lambda th: weight * perturbation(th))(nominal) * (hi - lo)
    return jnp.where(gain > 0, hi, lo)


def test_sixteen_links_equal_exact_rmi_where_it_is_known():
    """At 16 links (2^32 corners, beyond enumeration) the search must still find RMI's
    corner where it is known: every score affine in all 32 parameters, so exact RMI is
    the engine run with the plain sign chooser above."""
    n = 16
    rng = np.random.default_rng(16)
    nominal = rng.uniform(0.5, 2.0, 2 * n)
    lo = nominal * (1.0 - rng.uniform(0.05, 0.2, 2 * n))
    hi = nominal * (1.0 + rng.uniform(0.05, 0.2, 2 * n))
    params = rmijax.uncertain_robot(coupled_affine_model(n), nominal, lo, hi)
    traj = rmijax.trajectory((["sine", "composite", "slow_sine", "ramp"] * 4)[:n], duration=0.2)
    searched = corner_search_bounds(traj, params, window=10)
    # the engine sizes chunks for enumeration; this chooser holds no corner tensor
    exact = rmijax.rmi(
        traj, params, window=10, search=sign_chooser, memory_budget=2**60, chunk_size=4
    )
    np.testing.assert_allclose(searched.lower, exact.lower, rtol=0, atol=1e-12)
    np.testing.assert_allclose(searched.upper, exact.upper, rtol=0, atol=1e-12)
    assert float(jnp.min(exact.width[5:])) > 1e-3  # every band is open
