"""The standard fault suite: every fault kind on every joint, at one onset."""

from __future__ import annotations

from rmijax.plant import FAULT_KINDS, Fault

__all__ = ["BIAS_VALUE", "DRIFT_VALUE", "default_fault_suite"]

BIAS_VALUE = 0.05
"""Encoder bias (rad) in the default fault suite."""

DRIFT_VALUE = 0.05
"""Encoder drift rate (rad/s) in the default fault suite."""


def default_fault_suite(n_joints: int, onset: float = 3.0) -> list[Fault]:
    """Every fault kind on every joint at ``onset`` (bias and drift on the encoder)."""
    faults = []
    for joint in range(n_joints):
        for kind in FAULT_KINDS:
            offsets = {"bias": BIAS_VALUE, "drift": DRIFT_VALUE}
            extra = dict(value=offsets[kind], sensor=0) if kind in offsets else {}
            faults.append(Fault(kind, joint, onset, **extra))
    return faults
