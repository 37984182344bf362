"""benchmarks/certified_enclosure.py: the Hessian-free bounds on the mass remainder hold
over the sampled masses, and are close enough that halving them would not."""

import numpy as np

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
