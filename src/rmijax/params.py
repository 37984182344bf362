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
from rmijax.model import RobotModel, planar_arm_model

__all__ = [
    "UncertainRobot",
    "corner_tensor",
    "paper_arm2",
    "paper_pendulum",
    "planar_arm",
    "preset_arm",
    "uncertain_robot",
]


def corner_tensor(lo, hi):
    """All ``2^p`` corners of the box ``[lo, hi]``.

    Args:
        lo, hi: bounds (p,).

    Returns:
        corners (K, p), ``K = 2^p``; row ``c`` takes ``hi[b]`` where bit ``b``
        of ``c`` is set, ``lo[b]`` otherwise.
    """
    p = lo.shape[-1]
    index = jnp.arange(2**p, dtype=jnp.int32)
    bits = (index[:, None] >> jnp.arange(p, dtype=jnp.int32)[None, :]) & 1
    return jnp.where(bits == 1, hi[None, :], lo[None, :])


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


def planar_arm(nominal, lo, hi, *, dtype=None) -> UncertainRobot:
    """The uncertain planar point-mass arm (SPEC sections 1-2).

    Args:
        nominal, lo, hi: (2n,) = masses (kg) then lengths (m) of links 1..n.
        dtype: float dtype; default follows the inputs.

    Returns:
        An :class:`UncertainRobot` with ``p = 2n`` parameters.

    Raises:
        ValueError: if the vectors differ in length or have odd length, if
            any bound is not positive, or as :func:`uncertain_robot`.
    """
    nominal_np = np.asarray(nominal) if _checks.is_concrete(nominal) else None
    size = np.shape(nominal)[-1] if np.ndim(nominal) == 1 else None
    if size is None or size % 2:
        raise ValueError(
            f"nominal must be a 1-D vector (m_1..m_n, l_1..l_n) of even length 2n; "
            f"got shape {np.shape(nominal)}"
        )
    for label, value in (("lo", lo), ("hi", hi)):
        if np.shape(value) != (size,):
            raise ValueError(
                f"{label} has shape {np.shape(value)} but nominal has shape ({size},): "
                "give masses then lengths for every link in all three vectors"
            )
    robot = uncertain_robot(planar_arm_model(size // 2), nominal, lo, hi, dtype=dtype)
    if nominal_np is not None and _checks.is_concrete(robot.lo):
        low = np.asarray(robot.lo)
        bad = np.flatnonzero(low <= 0)
        if bad.size:
            b = int(bad[0])
            raise ValueError(
                f"lo of parameter {robot.model.param_names[b]} is {low[b]!r}: masses and "
                "lengths must be positive (the mass matrix is singular otherwise)"
            )
    return robot


def paper_pendulum(*, dtype=None) -> UncertainRobot:
    """The paper's pendulum: ``m = 10 [9, 11]`` kg, ``l = 1 [0.99, 1.01]`` m."""
    return planar_arm([10.0, 1.0], [9.0, 0.99], [11.0, 1.01], dtype=dtype)


def preset_arm(n: int, *, dtype=None) -> UncertainRobot:
    """The ``n``-link scaling preset: link 1 as the paper's two-joint arm's link 1
    (``m = 12 [11, 13]`` kg, ``l = 1.5 [1.49, 1.51]`` m), every other link as its
    link 2 (``m = 10 [9, 11]`` kg, ``l = 1 [0.99, 1.01]`` m)."""
    n = int(n)
    if n < 1:
        raise ValueError(f"n must be >= 1 link, got {n}")
    masses = [12.0] + [10.0] * (n - 1)
    masses_lo = [11.0] + [9.0] * (n - 1)
    masses_hi = [13.0] + [11.0] * (n - 1)
    lengths = [1.5] + [1.0] * (n - 1)
    lengths_lo = [1.49] + [0.99] * (n - 1)
    lengths_hi = [1.51] + [1.01] * (n - 1)
    return planar_arm(masses + lengths, masses_lo + lengths_lo, masses_hi + lengths_hi, dtype=dtype)


def paper_arm2(*, dtype=None) -> UncertainRobot:
    """The paper's two-joint arm: link 1 ``m1 = 12 [11, 13]``, ``l1 = 1.5 [1.49, 1.51]``;
    link 2 as the pendulum."""
    return preset_arm(2, dtype=dtype)
