"""platoon-opt: platoons of tricycle-drive robots controlled as one redundant system.

The model lives here (vehicles, tasks, limits, avoidance, the allocation problem, the
controller, simulation, scenarios, metrics); allocators live in the ``solvers`` package.
"""

from platoon_opt.avoidance import AvoidanceParams, CircularObstacles
from platoon_opt.controller import AllocationError, PlatoonController
from platoon_opt.limits import AchievableSets
from platoon_opt.metrics import integrated_errors
from platoon_opt.problem import Allocation, AllocationProblem, Allocator
from platoon_opt.scenarios import Scenario, ScenarioError, load_scenario
from platoon_opt.simulation import Trajectory, simulate
from platoon_opt.tasks import MeanVarianceTask, Task, TaskJacobian
from platoon_opt.vehicle import PlatoonState, VehicleLimits

__all__ = [
    "AchievableSets",
    "Allocation",
    "AllocationError",
    "AllocationProblem",
    "Allocator",
    "AvoidanceParams",
    "CircularObstacles",
    "MeanVarianceTask",
    "PlatoonController",
    "PlatoonState",
    "Scenario",
    "ScenarioError",
    "Task",
    "TaskJacobian",
    "Trajectory",
    "VehicleLimits",
    "integrated_errors",
    "load_scenario",
    "simulate",
]
