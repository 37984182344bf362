"""The paper's experiments (sections 3.3-3.4) as functions: bands, fault runs, tables.

Used by the command line (``rmijax``) and by ``notebooks/paper_reproduction.ipynb``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from rmijax.detection.detect import containment, detect
from rmijax.detection.suite import BIAS_VALUE, DRIFT_VALUE, default_fault_suite
from rmijax.methods.empirical import empirical_thresholds
from rmijax.methods.rmi import rmi
from rmijax.plant import Fault, simulate
from rmijax.robots.box import UncertainRobot, monte_carlo_parameters
from rmijax.robots.planar import paper_arm2, paper_pendulum
from rmijax.trajectory import trajectory

__all__ = [
    "BIAS_VALUE",
    "DRIFT_VALUE",
    "PAPER_RUNS",
    "containment_table",
    "default_fault_suite",
    "fault_table",
    "paper_true_parameters",
]

PAPER_RUNS = {
    # name: (robot builder, paths, paper figures)
    "pendulum_sine": (paper_pendulum, ["sine"], "3, 5"),
    "pendulum_ramp": (paper_pendulum, ["ramp"], "7, 8"),
    "pendulum_composite": (paper_pendulum, ["composite"], "-"),
    "arm2_hold_sine": (paper_arm2, ["hold", "sine"], "4, 6"),
    "arm2_hold_ramp": (paper_arm2, ["hold", "ramp"], "-"),
    "arm2_hold_composite": (paper_arm2, ["hold", "composite"], "9, 10"),
    "arm2_slow_sine_composite": (paper_arm2, ["slow_sine", "composite"], "11-14"),
}
"""The paper's trajectories (SPEC section 6) and the figures that show them."""


def paper_true_parameters(params: UncertainRobot) -> np.ndarray:
    """The paper's true robot for figures 15-20: every mass x1.08, every length -0.005 m."""
    n = params.n_joints
    nominal = np.asarray(params.nominal, np.float64)
    return np.concatenate([nominal[:n] * 1.08, nominal[n:] - 0.005])


@dataclasses.dataclass(frozen=True)
class FaultRow:
    """One fault against every method: latency (s or None), false alarms, alarming output."""

    fault: Fault
    results: dict


def fault_table(
    traj,
    params,
    th_true,
    bands: dict,
    faults,
    *,
    persistence=1,
    noise_lo=0.0,
    noise_hi=0.0,
    seed=0,
    progress=None,
):
    """Detection latency and false alarms of each set of bands over a list of faults.

    Args:
        traj, params: the run and the robot.
        th_true: (p,) the true robot.
        bands: ``{method name: Bounds}``.
        faults: list of :class:`~rmijax.simulate.Fault`, one run each.
        progress: optional callable ``(done, total)``.

    Returns:
        A list of :class:`FaultRow`, one per fault, whose ``results[name]`` is the
        :class:`~rmijax.detection.detect.Detection` of that method.
    """
    rows = []
    for index, fault in enumerate(faults):
        x_true, y_meas = simulate(
            traj, params, th_true, faults=[fault], noise_lo=noise_lo, noise_hi=noise_hi, seed=seed
        )
        results = {
            name: detect(y_meas, bounds, onset=fault.onset, persistence=persistence, x_true=x_true)
            for name, bounds in bands.items()
        }
        rows.append(FaultRow(fault, results))
        if progress is not None:
            progress(index + 1, len(faults))
    return rows


def containment_table(traj, params, bands: dict, *, draws=100, seed=0):
    """Containment of all corners plus ``draws`` uniform true robots, per set of bands."""
    th = monte_carlo_parameters(params, draws, seed=seed)
    states, _ = simulate(traj, params, th)
    return {name: containment(states, bounds) for name, bounds in bands.items()}


def method_bands(traj, params, *, runs=20, safety=1.2, seed=0):
    """The three thresholds the paper compares: RMI coupled, RMI per_joint, constant."""
    return {
        "rmi_coupled": rmi(traj, params, mode="coupled"),
        "rmi_per_joint": rmi(traj, params, mode="per_joint"),
        "constant": empirical_thresholds(traj, params, runs=runs, safety=safety, seed=seed),
    }


def paper_run(name: str, *, duration: float = 15.0):
    """The robot and trajectory of one of :data:`PAPER_RUNS`."""
    builder, paths, _ = PAPER_RUNS[name]
    return builder(), trajectory(paths, duration=duration)
