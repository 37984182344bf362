"""Importing rmijax is quiet and leaves JAX's configuration alone."""

import subprocess
import sys


def test_import_is_silent_and_keeps_float32():
    code = (
        "import jax, rmijax, jax.numpy as jnp;"
        "assert not jax.config.jax_enable_x64;"
        "assert jnp.zeros(1).dtype == jnp.float32;"
        "assert rmijax.paper_pendulum().nominal.dtype == jnp.float32"
    )
    result = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=False,
        env={"PATH": "", "JAX_PLATFORMS": "cpu"},
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout == ""
    assert result.stderr == ""


def test_public_api_is_listed():
    import rmijax

    for name in rmijax.__all__:
        assert hasattr(rmijax, name), name
    for name in (
        "planar_arm",
        "paper_pendulum",
        "paper_arm2",
        "preset_arm",
        "trajectory",
        "trajectory_from_samples",
        "rmi",
        "rmi_step",
        "bounds",
        "worst_case",
        "worst_case_table",
    ):
        assert name in rmijax.__all__
