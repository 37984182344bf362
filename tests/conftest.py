"""Test configuration: float64 by default, and silent broadcasts are errors.

The library itself never switches x64 on; the tests choose it here and pass
float32 explicitly where float32 is under test.
"""

import pathlib

import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")

DATA = pathlib.Path(__file__).parent / "data"


@pytest.fixture
def rng():
    return np.random.default_rng(20261124)


def load_case(name):
    """A reference case from tests/data (copied from ../shared/cases)."""
    with np.load(DATA / f"{name}.npz") as case:
        return {key: case[key] for key in case.files}
