"""``certified_bounds(..., splits="auto")``: adaptive bisection of the box, and the
checker's tiling test for pieces that are not a product grid."""

from __future__ import annotations

import dataclasses
import types

import jax.numpy as jnp
import numpy as np
import pytest

import rmijax
from rmijax import _checks
from rmijax.methods.base import DivergedError
from rmijax.methods.certificate_check import _tiling_error, check_certificate
from rmijax.methods.certified import KERNEL_STEPS, _certify, _in_chunks, certified_bounds

TOL = 1e-12  # rounding level: the simulator's own float64 error on |y| ~ 1


@pytest.fixture(scope="module")
def wide_pendulum():
    """The paper pendulum on a box six times as wide (mass 4-16 kg): the computed-torque
    loop's gain varies 2.5x over it and one Taylor model about the nominal diverges."""
    params = rmijax.paper_pendulum()
    nominal, lo, hi = (np.asarray(a) for a in (params.nominal, params.lo, params.hi))
    params = params.with_box(lo=nominal - 6 * (nominal - lo), hi=nominal + 6 * (hi - nominal))
    traj = rmijax.trajectory(["sine"], duration=0.5)
    bounds, cert = certified_bounds(traj, params, splits="auto", max_pieces=3)
    return traj, params, bounds, cert


def _states(traj, params, count=300, seed=0):
    lo, hi = np.asarray(params.lo), np.asarray(params.hi)
    draws = lo + (hi - lo) * np.random.default_rng(seed).uniform(size=(count, lo.size))
    samples = np.concatenate([np.asarray(params.corners), draws])
    states, _ = rmijax.simulate(traj, params, samples)
    return np.asarray(states)


def _escape(bounds, states):
    upper, lower = np.asarray(bounds.upper), np.asarray(bounds.lower)
    return float(max(np.max(states - upper), np.max(lower - states)))


def test_auto_cuts_a_box_whose_single_model_diverges(wide_pendulum):
    traj, params, bounds, cert = wide_pendulum
    with pytest.raises(DivergedError):
        certified_bounds(traj, params, splits=1)
    assert cert.lo.shape[0] == 3
    assert np.all(np.isfinite(np.asarray(bounds.upper) - np.asarray(bounds.lower)))
    assert _tiling_error(cert, params) == ""
    # the cuts follow the loop: the light end (where the gain is largest) cut finer
    widths = np.sort(np.asarray(cert.hi - cert.lo)[:, 0])
    assert widths[0] < widths[-1]
    assert _escape(bounds, _states(traj, params)) <= TOL


def test_auto_without_remainder_lets_samples_escape(wide_pendulum):
    traj, params, _, _ = wide_pendulum
    mutant, _ = certified_bounds(traj, params, splits="auto", max_pieces=3, remainder_scale=0.0)
    assert _escape(mutant, _states(traj, params)) > 1e-6


def test_checker_accepts_the_bisected_certificate(wide_pendulum):
    traj, params, _, cert = wide_pendulum
    assert check_certificate(cert, traj, params, steps=4).ok
    tampered = dataclasses.replace(cert, injected=cert.injected.at[:, 2].multiply(0.5))
    assert not check_certificate(tampered, traj, params, steps=4).ok


def test_auto_refuses_past_max_pieces(wide_pendulum):
    traj, params, _, _ = wide_pendulum
    with pytest.raises(DivergedError, match="max_pieces=1"):
        certified_bounds(traj, params, splits="auto", max_pieces=1)
    with pytest.raises(ValueError, match="splits must be"):
        certified_bounds(traj, params, splits="grid")
    with pytest.raises(ValueError, match="refine"):
        certified_bounds(traj, params, splits="auto", refine=0.0)
    with pytest.raises(ValueError, match="max_pieces"):
        certified_bounds(traj, params, splits="auto", max_pieces=0)


def _cert(lo, hi, center=None):
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    return types.SimpleNamespace(lo=lo, hi=hi, center=0.5 * (lo + hi) if center is None else center)


def test_tiling_of_pieces_that_are_not_a_grid():
    """An adaptive tiling of [0, 1] x [0, 2] (third parameter certain) passes; an overlap,
    a gap, a piece outside the box and a centre outside its piece are refused."""
    box = types.SimpleNamespace(lo=np.array([0.0, 0.0, 5.0]), hi=np.array([1.0, 2.0, 5.0]))
    lo = [[0.0, 0.0, 5.0], [0.5, 0.0, 5.0], [0.5, 1.0, 5.0], [0.75, 1.0, 5.0]]
    hi = [[0.5, 2.0, 5.0], [1.0, 1.0, 5.0], [0.75, 2.0, 5.0], [1.0, 2.0, 5.0]]
    assert _tiling_error(_cert(lo, hi), box) == ""
    overlap = [row[:] for row in hi]
    overlap[0][0] = 0.6  # also covers part of pieces 1 and 2
    assert "overlap" in _tiling_error(_cert(lo, overlap), box)
    gap = [row[:] for row in hi]
    gap[3][1] = 1.9
    assert "no tiling" in _tiling_error(_cert(lo, gap), box)
    assert "no tiling" in _tiling_error(_cert(lo[:3], hi[:3]), box)
    outside = [row[:] for row in hi]
    outside[3][0] = 1.25
    assert "inside the parameter box" in _tiling_error(_cert(lo, outside), box)
    centers = 0.5 * (np.asarray(lo) + np.asarray(hi))
    centers[2, 0] = 0.9
    assert "centre" in _tiling_error(_cert(lo, hi, centers), box)


def test_rounds_are_evaluated_in_chunks_of_one_size():
    """Every call gets ``chunk`` boxes (one compilation for all rounds), the last chunk
    padded with copies, and the pieces come back in order with the padding dropped."""
    shapes = []

    def certify(boxes):
        shapes.append(tuple(a.shape for a in boxes))
        centers = boxes[0]
        return {"upper": centers + 1.0, "lower": centers - 1.0}

    pending = [(np.full(2, float(i)), np.full(2, i - 0.5), np.full(2, i + 0.5)) for i in range(7)]
    pieces = _in_chunks(certify, pending, 3)
    assert shapes == [((3, 2),) * 3] * 3
    np.testing.assert_array_equal(pieces["upper"][:, 0], np.arange(7) + 1.0)
    np.testing.assert_array_equal(pieces["lower"][:, 1], np.arange(7) - 1.0)


def test_diverged_pieces_skip_their_remaining_steps(wide_pendulum):
    """A piece whose remainder stopped being finite skips the rest of the run (its
    outputs ``inf`` from the next step) once every piece certified with it has diverged;
    next to a finite piece it runs on, and neither changes the other's result."""
    traj, params, _, cert = wide_pendulum
    whole = (np.asarray(params.nominal), np.asarray(params.lo), np.asarray(params.hi))
    piece = tuple(np.asarray(a)[0] for a in (cert.center, cert.lo, cert.hi))
    noise = jnp.zeros((1, 2))

    def run(*boxes):
        arrays = (jnp.asarray(np.stack([box[i] for box in boxes])) for i in range(3))
        pieces, _, _ = _certify(
            traj, params, *arrays, noise, noise, jnp.asarray(1.0),
            noisy=False, kernel_steps=KERNEL_STEPS, segments=3,
        )  # fmt: skip
        return {key: np.asarray(value) for key, value in pieces.items()}

    alone, finite, both = run(whole), run(piece), run(whole, piece)
    first = _checks.first_non_finite(alone["upper"][0], alone["lower"][0])[0]
    assert 0 < first < traj.n_steps
    assert np.all(alone["remainder"][0, first + 1 :] == np.inf)  # skipped, not computed
    assert np.all(np.isfinite(alone["remainder"][0, :first]))
    assert _checks.first_non_finite(both["upper"][0], both["lower"][0])[0] == first
    assert not np.all(both["remainder"][0, first + 1 :] == np.inf)  # ran on beside piece
    for key in ("upper", "lower", "remainder"):
        assert np.all(np.isfinite(both[key][1]))
        np.testing.assert_allclose(both[key][1], finite[key][0], rtol=1e-12, atol=1e-300)
