"""platoon-opt: platoons of tricycle-drive robots controlled as one redundant system.

This package is the model: vehicles, tasks, limits, avoidance, the allocation problem, the
controller, simulation, scenarios and metrics. It imports no allocator, file writer or plotting
library. The allocators live one floor up, the study (harness, statistics, report, figures,
command line) above them (docs/architecture.md).
"""

from platoon_opt.allocation import Allocation, Allocator
from platoon_opt.avoidance import AvoidanceParams, CircularObstacles
from platoon_opt.controller import PlatoonController
from platoon_opt.errors import AllocationError, OptionError, PlatoonOptError, ScenarioError
from platoon_opt.limits import AchievableSets
from platoon_opt.metrics import integrated_errors
from platoon_opt.problem import AllocationProblem
from platoon_opt.scenarios import Scenario, load_scenario
from platoon_opt.simulation import simulate, simulate_batch
from platoon_opt.tasks import CovarianceTask, MeanVarianceTask, Task, TaskJacobian
from platoon_opt.trajectory import Trajectory
from platoon_opt.vehicle import PlatoonState, VehicleLimits

__version__ = "0.2.0"

__all__ = [
    "AchievableSets",
    "Allocation",
    "AllocationError",
    "AllocationProblem",
    "Allocator",
    "AvoidanceParams",
    "CircularObstacles",
    "CovarianceTask",
    "MeanVarianceTask",
    "OptionError",
    "PlatoonController",
    "PlatoonOptError",
    "PlatoonState",
    "Scenario",
    "ScenarioError",
    "Task",
    "TaskJacobian",
    "Trajectory",
    "VehicleLimits",
    "__version__",
    "integrated_errors",
    "load_scenario",
    "simulate",
    "simulate_batch",
]
