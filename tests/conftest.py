"""Test configuration: float64 by default, and silent broadcasts are errors.

The library itself never switches x64 on; the tests choose it here and pass
float32 explicitly where float32 is under test.
"""

import gc
import pathlib

import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")

DATA = pathlib.Path(__file__).parent / "data"


_MAPS = pathlib.Path("/proc/self/maps")
_MAX_MAPPINGS = 20000
"""Clear JAX's caches once the process holds this many memory mappings (a third of the
kernel's default ``vm.max_map_count``, 65530)."""


def _mappings():
    try:
        with _MAPS.open("rb") as maps:
            return sum(1 for _ in maps)
    except OSError:  # not Linux: no count, so clear every module as before
        return _MAX_MAPPINGS


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop the compiled programs after a test module once they hold many mappings.

    The suite compiles thousands of XLA programs in one process; each keeps its own
    memory mappings, and near the kernel's ``vm.max_map_count`` (65530 here) the next
    compilation crashed with SIGSEGV inside XLA. Clearing JAX's caches when the count
    passes a third of that limit keeps the process far below it, while modules that
    follow each other still reuse each other's programs (clearing after every module
    recompiled them).
    """
    yield
    if _mappings() >= _MAX_MAPPINGS:
        jax.clear_caches()
        gc.collect()


@pytest.fixture
def rng():
    return np.random.default_rng(20261124)


def load_case(name):
    """A reference case from tests/data (copied from ../shared/cases)."""
    with np.load(DATA / f"{name}.npz") as case:
        return {key: case[key] for key in case.files}


_MEASURED_SLOW = {
    line.strip()
    for line in (pathlib.Path(__file__).parent / "slow_tests.txt").read_text().splitlines()
    if line.strip() and not line.startswith("#")
}


def pytest_collection_modifyitems(config, items):
    """Mark the tests listed in ``slow_tests.txt`` (measured >= 6 s) as ``slow``."""
    for item in items:
        if item.nodeid in _MEASURED_SLOW:
            item.add_marker(pytest.mark.slow)
