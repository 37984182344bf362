"""Uncertain parameters: a robot model with a box ``[lo, hi]`` around its nominal values.

The ``2^p`` extreme combinations of the box (the *corners*) are one stacked
``(K, p)`` array; corner ``c`` takes ``hi_b`` where bit ``b`` of ``c`` is set
and ``lo_b`` otherwise (SPEC section 2). That order is part of the contract.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from rmijax import _checks
from rmijax.robots.model import RobotModel

__all__ = [
    "UncertainRobot",
    "corner_tensor",
    "monte_carlo_parameters",
    "uncertain_indices",
    "uncertain_robot",
]


def corner_tensor(lo, hi, indices=None):
    """All ``2^p`` corners of the box ``[lo, hi]``, or those of the parameters ``indices``.

    Args:
        lo, hi: bounds (p,).
        indices: None (every parameter), or a static ascending tuple of the
            parameters to enumerate (:func:`uncertain_indices`); the others
            stay at ``lo`` (certain parameters have ``lo == hi``).

    Returns:
        corners (K, p), ``K = 2^p`` (``2^len(indices)``); row ``c`` takes ``hi[b]``
        where bit ``b`` of ``c`` is set, ``lo[b]`` otherwise (with ``indices``,
        bit ``j`` of ``c`` sets parameter ``indices[j]``). Dropping certain
        parameters keeps the order of the remaining corners, so the lowest
        index of a tie is the same corner either way.
    """
    p = lo.shape[-1]
    chosen = np.arange(p) if indices is None else np.asarray(indices, int)
    index = jnp.arange(2**chosen.size, dtype=jnp.int32)
    bits = (index[:, None] >> jnp.arange(chosen.size, dtype=jnp.int32)[None, :]) & 1
    if indices is None:
        return jnp.where(bits == 1, hi[None, :], lo[None, :])
    rows = jnp.broadcast_to(lo, (index.shape[0], p))
    return rows.at[:, chosen].set(jnp.where(bits == 1, hi[chosen][None, :], lo[chosen][None, :]))


def uncertain_indices(params) -> tuple[int, ...] | None:
    """The parameters with ``lo < hi``, as a static tuple; None when the box is traced.

    Certain parameters (``lo == hi``) add no corners: every corner that differs
    from another only in them is the same parameter vector. The engine and
    ``constant_corners`` enumerate the uncertain ones only when the box is
    concrete (under a user's ``jit`` its values are unknown, so every corner
    is enumerated).
    """
    if not (_checks.is_concrete(params.lo) and _checks.is_concrete(params.hi)):
        return None
    return tuple(int(b) for b in np.flatnonzero(np.asarray(params.hi) > np.asarray(params.lo)))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class UncertainRobot:
    """A robot model whose parameters are known only within a box.

    Attributes:
        nominal: (p,) the values the controller uses (``th_n``).
        lo, hi: (p,) the box; ``lo <= nominal <= hi``. ``lo == hi`` marks a
            parameter as certain.
        model: the :class:`RobotModel` (static).
    """

    nominal: jax.Array
    lo: jax.Array
    hi: jax.Array
    model: RobotModel = dataclasses.field(metadata=dict(static=True))

    @property
    def n_joints(self) -> int:
        """Number of joints ``n``."""
        return self.model.n_joints

    @property
    def n_params(self) -> int:
        """Number of uncertain parameters ``p``."""
        return self.model.n_params

    @property
    def n_corners(self) -> int:
        """Number of corners ``K = 2^p``."""
        return 2**self.model.n_params

    @property
    def corners(self) -> jax.Array:
        """The corner tensor (K, p) in the contract's bit order."""
        return corner_tensor(self.lo, self.hi)

    @property
    def dtype(self):
        return self.nominal.dtype

    def with_box(self, lo=None, hi=None, nominal=None) -> UncertainRobot:
        """A copy with some of ``nominal``, ``lo``, ``hi`` replaced (validated)."""
        return uncertain_robot(
            self.model,
            self.nominal if nominal is None else nominal,
            self.lo if lo is None else lo,
            self.hi if hi is None else hi,
            dtype=self.dtype,
        )


def uncertain_robot(model: RobotModel, nominal, lo, hi, *, dtype=None) -> UncertainRobot:
    """Wrap any :class:`RobotModel` with a parameter box.

    Args:
        model: the robot's ``M(q, th)`` and ``h(q, qd, th)``.
        nominal, lo, hi: (p,) nominal values and bounds.
        dtype: float dtype of the arrays; default follows the inputs
            (float64 arrays stay float64 only when x64 is enabled).

    Raises:
        ValueError: on shape mismatches, NaN/inf, ``lo > hi`` or a nominal
            outside its box; the message names the argument and the fix.
    """
    if not isinstance(model, RobotModel):
        raise TypeError(
            f"model must be a rmijax.RobotModel (its mass_matrix and bias functions), got "
            f"{type(model).__name__}"
        )
    names = model.param_names or tuple(f"th[{b}]" for b in range(model.n_params))
    arrays = {}
    for label, value in (("nominal", nominal), ("lo", lo), ("hi", hi)):
        arrays[label] = _checks.float_array(label, value, (model.n_params,), dtype=dtype)
    common = jnp.result_type(*arrays.values())
    arrays = {k: v.astype(common) for k, v in arrays.items()}
    if all(_checks.is_concrete(v) for v in arrays.values()):
        nom, low, high = (np.asarray(arrays[k]) for k in ("nominal", "lo", "hi"))
        bad = np.flatnonzero(low > high)
        if bad.size:
            b = int(bad[0])
            raise ValueError(
                f"lo > hi for parameter {names[b]} (index {b}): lo={low[b]!r}, "
                f"hi={high[b]!r}. Swap them: each interval must satisfy lo <= hi."
            )
        bad = np.flatnonzero((nom < low) | (nom > high))
        if bad.size:
            b = int(bad[0])
            raise ValueError(
                f"nominal value of parameter {names[b]} (index {b}) is {nom[b]!r}, "
                f"outside its box [{low[b]!r}, {high[b]!r}]. Widen lo/hi so that "
                "lo <= nominal <= hi."
            )
    return UncertainRobot(arrays["nominal"], arrays["lo"], arrays["hi"], model)


def monte_carlo_parameters(
    params: UncertainRobot, draws: int, *, seed: int = 0, corners: bool = True
) -> np.ndarray:
    """True-parameter sets for containment checks: all corners (if asked) plus uniform draws.

    Returns:
        (K + draws, p) or (draws, p) array.
    """
    draws = _checks.integer("draws", draws, minimum=0)
    rng = np.random.default_rng(_checks.seed(seed))
    corners = _checks.boolean("corners", corners)
    lo, hi = np.asarray(params.lo, np.float64), np.asarray(params.hi, np.float64)
    uniform = lo + (hi - lo) * rng.uniform(size=(int(draws), lo.size))
    if not corners:
        return uniform
    return np.concatenate([np.asarray(params.corners, np.float64), uniform], axis=0)
