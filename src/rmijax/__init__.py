"""rmijax: dynamic fault-detection thresholds for robot arms by Reachable Measurement Intervals.

Importing rmijax changes no JAX configuration: choose float64 yourself with
``jax.config.update("jax_enable_x64", True)`` (or pass float64 arrays).
"""

from rmijax import experiments as experiments  # noqa: E402  (the paper's runs)
from rmijax.control import (
    closed_loop_step as closed_loop_step,
)
from rmijax.control import (
    coupled_perturbation as coupled_perturbation,
)
from rmijax.detect import (
    Detection as Detection,
)
from rmijax.detect import (
    containment as containment,
)
from rmijax.detect import (
    detect as detect,
)
from rmijax.detect import (
    empirical_thresholds as empirical_thresholds,
)
from rmijax.detect import (
    monte_carlo_parameters as monte_carlo_parameters,
)
from rmijax.engine import (
    DEFAULT_MEMORY_BUDGET as DEFAULT_MEMORY_BUDGET,
)
from rmijax.engine import (
    MODES as MODES,
)
from rmijax.engine import (
    Bounds as Bounds,
)
from rmijax.engine import (
    ProblemTooLargeError as ProblemTooLargeError,
)
from rmijax.engine import (
    estimate_memory as estimate_memory,
)
from rmijax.engine import (
    rmi as rmi,
)
from rmijax.engine import (
    rmi_step as rmi_step,
)
from rmijax.model import (
    GRAVITY as GRAVITY,
)
from rmijax.model import (
    RobotModel as RobotModel,
)
from rmijax.model import (
    planar_arm_model as planar_arm_model,
)
from rmijax.params import (
    UncertainRobot as UncertainRobot,
)
from rmijax.params import (
    corner_tensor as corner_tensor,
)
from rmijax.params import (
    paper_arm2 as paper_arm2,
)
from rmijax.params import (
    paper_pendulum as paper_pendulum,
)
from rmijax.params import (
    planar_arm as planar_arm,
)
from rmijax.params import (
    preset_arm as preset_arm,
)
from rmijax.params import (
    uncertain_robot as uncertain_robot,
)
from rmijax.simulate import (
    FAULT_KINDS as FAULT_KINDS,
)
from rmijax.simulate import (
    Fault as Fault,
)
from rmijax.simulate import (
    simulate as simulate,
)
from rmijax.trajectory import (
    PATHS as PATHS,
)
from rmijax.trajectory import (
    Trajectory as Trajectory,
)
from rmijax.trajectory import (
    trajectory as trajectory,
)
from rmijax.trajectory import (
    trajectory_from_samples as trajectory_from_samples,
)

__version__ = "0.1.0"

__all__ = [
    "DEFAULT_MEMORY_BUDGET",
    "FAULT_KINDS",
    "GRAVITY",
    "MODES",
    "PATHS",
    "Bounds",
    "Detection",
    "Fault",
    "ProblemTooLargeError",
    "RobotModel",
    "Trajectory",
    "UncertainRobot",
    "closed_loop_step",
    "containment",
    "corner_tensor",
    "coupled_perturbation",
    "detect",
    "empirical_thresholds",
    "estimate_memory",
    "experiments",
    "monte_carlo_parameters",
    "paper_arm2",
    "paper_pendulum",
    "planar_arm",
    "planar_arm_model",
    "preset_arm",
    "rmi",
    "rmi_step",
    "simulate",
    "trajectory",
    "trajectory_from_samples",
    "uncertain_robot",
]
