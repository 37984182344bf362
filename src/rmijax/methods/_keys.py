"""Exact keys for the corner searches: order-preserving integers and the contract's tie tolerance.

An integer max-reduction over an order-preserving image of the scores finds the best
score exactly in one fused loop (PERF_NOTES); the tie tolerance is SPEC section 2's.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["float_of_ordered", "ordered_int", "tie_tolerance"]


def ordered_int(x):
    """An integer image of a float array that preserves its order (exactly)."""
    itype = jnp.int64 if x.dtype == jnp.float64 else jnp.int32
    bits = jax.lax.bitcast_convert_type(x, itype)
    return jnp.where(bits < 0, bits ^ jnp.iinfo(itype).max, bits)


def float_of_ordered(k, dtype):
    """The float whose :func:`ordered_int` image is ``k``."""
    return jax.lax.bitcast_convert_type(jnp.where(k < 0, k ^ jnp.iinfo(k.dtype).max, k), dtype)


def tie_tolerance(scale, offset):
    """The contract's tie tolerance: ``eps^(2/3) * (max|score| + |offset|)``."""
    rtol = jnp.finfo(scale.dtype).eps ** (2.0 / 3.0)
    return rtol * (scale + jnp.abs(offset))
