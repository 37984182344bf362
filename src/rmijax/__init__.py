"""rmijax: dynamic fault-detection thresholds for robot arms by Reachable Measurement Intervals.

Importing rmijax changes no JAX configuration: choose float64 yourself with
``jax.config.update("jax_enable_x64", True)`` (or pass float64 arrays).
"""

from rmijax import fleet as fleet
from rmijax.apps import experiments as experiments
from rmijax.control import (
    closed_loop_step as closed_loop_step,
    coupled_perturbation as coupled_perturbation,
)
from rmijax.detection.detect import (
    Detection as Detection,
    containment as containment,
    detect as detect,
)
from rmijax.detection.monitor import (
    BandMonitorState as BandMonitorState,
    Monitor as Monitor,
    MonitorOutput as MonitorOutput,
    MonitorState as MonitorState,
    monitor as monitor,
    monitor_from_bounds as monitor_from_bounds,
)
from rmijax.evaluation.worst_case import (
    WorstCase as WorstCase,
    worst_case as worst_case,
    worst_case_table as worst_case_table,
)
from rmijax.io import Log as Log, LogError as LogError, read_log as read_log
from rmijax.methods.base import (
    Bounds as Bounds,
    DivergedError as DivergedError,
    ProblemTooLargeError as ProblemTooLargeError,
)
from rmijax.methods.certified import (
    Certificate as Certificate,
    certified_bounds as certified_bounds,
)
from rmijax.methods.dispatch import (
    DEFAULT_WINDOWS as DEFAULT_WINDOWS,
    METHODS as METHODS,
    SCALABLE_METHODS as SCALABLE_METHODS,
    bounds as bounds,
)
from rmijax.methods.empirical import empirical_thresholds as empirical_thresholds
from rmijax.methods.rmi import (
    DEFAULT_MEMORY_BUDGET as DEFAULT_MEMORY_BUDGET,
    MODES as MODES,
    SEARCHES as SEARCHES,
    estimate_memory as estimate_memory,
    rmi as rmi,
    rmi_step as rmi_step,
)
from rmijax.plant import FAULT_KINDS as FAULT_KINDS, Fault as Fault, simulate as simulate
from rmijax.robots.box import (
    UncertainRobot as UncertainRobot,
    corner_tensor as corner_tensor,
    monte_carlo_parameters as monte_carlo_parameters,
    uncertain_indices as uncertain_indices,
    uncertain_robot as uncertain_robot,
)
from rmijax.robots.check import ModelCheckError as ModelCheckError, check_model as check_model
from rmijax.robots.loaders import (
    SHIPPED as SHIPPED,
    default_box as default_box,
    load_robot as load_robot,
)
from rmijax.robots.model import GRAVITY as GRAVITY, RobotModel as RobotModel
from rmijax.robots.planar import (
    paper_arm2 as paper_arm2,
    paper_pendulum as paper_pendulum,
    planar_arm as planar_arm,
    planar_arm_model as planar_arm_model,
    preset_arm as preset_arm,
)
from rmijax.robots.structure import AffineBias as AffineBias, LinearDynamics as LinearDynamics
from rmijax.trajectory import (
    PATHS as PATHS,
    Trajectory as Trajectory,
    trajectory as trajectory,
    trajectory_from_samples as trajectory_from_samples,
    waypoint_trajectory as waypoint_trajectory,
)

__version__ = "0.1.0"

__all__ = [
    "AffineBias",
    "LinearDynamics",
    "ModelCheckError",
    "DEFAULT_MEMORY_BUDGET",
    "DEFAULT_WINDOWS",
    "FAULT_KINDS",
    "GRAVITY",
    "METHODS",
    "MODES",
    "PATHS",
    "SHIPPED",
    "SCALABLE_METHODS",
    "SEARCHES",
    "BandMonitorState",
    "Bounds",
    "Certificate",
    "Detection",
    "DivergedError",
    "Fault",
    "Log",
    "LogError",
    "Monitor",
    "MonitorOutput",
    "MonitorState",
    "ProblemTooLargeError",
    "RobotModel",
    "Trajectory",
    "UncertainRobot",
    "WorstCase",
    "bounds",
    "certified_bounds",
    "check_model",
    "closed_loop_step",
    "containment",
    "corner_tensor",
    "coupled_perturbation",
    "default_box",
    "detect",
    "empirical_thresholds",
    "estimate_memory",
    "experiments",
    "fleet",
    "load_robot",
    "monitor",
    "monitor_from_bounds",
    "monte_carlo_parameters",
    "paper_arm2",
    "paper_pendulum",
    "planar_arm",
    "planar_arm_model",
    "preset_arm",
    "read_log",
    "rmi",
    "rmi_step",
    "simulate",
    "trajectory",
    "trajectory_from_samples",
    "uncertain_indices",
    "uncertain_robot",
    "waypoint_trajectory",
    "worst_case",
    "worst_case_table",
]
