"""benchmarks/certified_enclosure.py: the Hessian-free bounds on the mass remainder hold
over the sampled masses, and are close enough that halving them would not."""

import numpy as np

import rmijax
from rmijax.methods.certified import certified_bounds

from helpers import load_benchmark

enclosure = load_benchmark("certified_enclosure")


def test_mass_remainder_bounds_contain_the_samples_with_teeth():
    row = enclosure.neumann_row(2, states=4, seed=0)
    ratios = {}
    for key in ("bound_joint", "bound_energy", "bound_min"):
        bound, sampled = np.asarray(row[key]), np.asarray(row["sampled"])  # (states, n)
        assert bound.shape == sampled.shape == (4, 2)
        assert np.all(sampled > 1e-4)  # the remainder is there to be bounded
        ratios[key] = bound / sampled
        # every sampled remainder is inside (the joint-coordinate bound is attained on
        # joint 1 at a corner, so allow rounding)
        assert np.all(ratios[key] >= 1.0 - 1e-9), key
    # Teeth: a bound at half its size would be broken by some sample, for each form.
    for key, ratio in ratios.items():
        assert np.min(ratio) < 2.0, key
    # The energy bound does not use the joint coordinates' entries: where those lose
    # (joint 2 at the start state, 4x), it is the tighter of the two.
    assert ratios["bound_energy"][0, 1] < ratios["bound_joint"][0, 1]
    assert np.allclose(row["bound_min"], np.minimum(row["bound_joint"], row["bound_energy"]))


def test_remainder_input_blocks_add_up_to_the_certified_input():
    row = enclosure.blocks_row(2, 2, 0.05)
    steps = row["steps"]
    assert len(steps) == 5  # no divergence in 0.05 s
    params = rmijax.preset_arm(2)
    traj = rmijax.trajectory(["sine"] * 2, duration=0.05)
    _, cert = certified_bounds(traj, params, splits=2)
    # the certificate's input to the last joint's velocity: dt w (1 + a few eps) plus the
    # centre's rounding, in the piece where it is largest
    injected = np.max(np.asarray(cert.injected)[:, :, -1, 1], axis=0)
    for k, step in enumerate(steps):
        shares = np.array([step[b] for b in enclosure.BLOCKS])
        assert np.all(shares >= 0.0) and abs(shares.sum() - 1.0) < 1e-12
        assert np.isclose(traj.dt * step["w"], injected[k], rtol=1e-6), k
    assert steps[0]["mx"] == 0.0 and steps[-1]["mx"] > 0.0  # the state enters after step 0


def test_sampled_hessian_over_the_tube_stays_inside_the_interval_enclosure():
    # The quadratic part of certified's remainder input against the same quantity from
    # sampled Hessians over the certificate's own tube (the --tube measurement): every
    # block's enclosure must hold the samples' spread, or the certificate is unsound.
    row = enclosure.tube_row(2, 2, (0, 1, 3), duration=0.05, samples=100)
    assert [step["step"] for step in row["steps"]] == [0, 1, 3]
    for step in row["steps"]:
        for block in enclosure.BLOCKS[1:]:
            sampled, interval = step["sampled"][block], step["interval"][block]
            assert sampled <= interval * (1.0 + 1e-9), (step["step"], block)
        assert step["sampled_total"] > 0.0
        # the affine prototype (rounding not bounded, so up to rounding) holds them too,
        # and is the tighter of the two enclosures in total
        for block in enclosure.BLOCKS[1:]:
            sampled, affine = step["sampled"][block], step["affine"][block]
            assert sampled <= affine * (1.0 + 1e-9) + 1e-15, (step["step"], block)
        assert step["affine_total"] < step["interval_total"]
    first, last = row["steps"][0], row["steps"][-1]
    # at step 0 the state is known: no remainder, so nothing in its blocks
    assert first["remainder_max"] == 0.0 and first["sampled"]["xx"] == 0.0
    assert last["remainder_max"] > 0.0 and last["sampled"]["mx"] > 0.0


def test_induction_replay_equals_the_certificate_and_affine_is_smaller():
    # The numpy replay of certified's induction (the --induction measurement) with the
    # certificate's own interval enclosure gives the certificate's remainder; only then
    # does swapping in the affine enclosure say what that enclosure would change.
    interval = enclosure.induction_row(2, 2, 8, "interval")
    check = enclosure._certificate_remainder(interval, 8)
    assert check["max_rel_difference"] < 1e-6
    steps = interval["steps"]
    assert len(steps) == 8 and steps[-1]["remainder_max"] > 0.0
    affine = enclosure.induction_row(2, 2, 8, "affine", piece=interval["piece"])
    for a, b in zip(affine["steps"], steps, strict=True):
        assert 0.0 < a["remainder_max"] < b["remainder_max"]
    # the zonotope propagation takes the linear feedback out of the input
    centre = enclosure.induction_row(2, 2, 8, "affine", piece=interval["piece"], propagate="centre")
    assert all(r["remainder_max"] > 0.0 for r in centre["steps"])
    assert centre["steps"][0]["remainder_max"] == affine["steps"][0]["remainder_max"]


def test_carried_replay_bounds_every_sampled_run_of_its_piece():
    # The 'carried' replay (remainder's first-order dependence on the parameters kept)
    # is the variant that stays bounded at 4 links; its algebra is checked here against
    # constant-parameter runs of the closed loop at the piece's corners and draws.
    row = enclosure.induction_row(2, 2, 20, "affine", propagate="carried", keep=True)
    assert len(row["steps"]) == 20
    check = enclosure.replay_containment(row, draws=100)
    assert check["runs"] == 2**4 + 100 and check["steps"] == 20
    assert check["outside"] == 0
    # the bound is not vacuous: sampled remainders reach a visible part of it
    assert 0.01 < check["largest_ratio"] <= 1.0
    # and it is below what the certificate's own propagation gives for the same piece
    nominal = enclosure.induction_row(2, 2, 20, "affine", piece=row["piece"])
    assert row["steps"][-1]["remainder_max"] < nominal["steps"][-1]["remainder_max"]


def test_union_of_carried_replays_holds_every_sampled_run():
    # The --union measurement: every piece's carried replay, united, against
    # constant-parameter runs over the whole box (corners and draws).
    row = enclosure.union_row(2, 2, 30, draws=100)
    assert row["pieces"] == 4 and row["diverged_pieces"] == []
    assert row["runs"] == 2**4 + 100 and row["runs_outside"] == 0
    # a band holding the runs is at least their range; close to it at two links
    for ratio in row["width_over_seen_min"]:
        assert ratio >= 1.0 - 1e-9
    for ratio in row["width_over_seen_median"]:
        assert ratio < 1.2
