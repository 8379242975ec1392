"""mmpc: multi-modal model predictive control by batch non-holonomic trajectory optimization."""

from mmpc.solver.basis import Basis, bernstein_basis
from mmpc.goals import CruiseGoals, GoalSampler, HighSpeedGoals, NearLaneGoals
from mmpc.meta_costs import CruiseCost, HighSpeedCost, MetaCost
from mmpc.mpc import MPC, MPCConfig, Plan
from mmpc.obstacles.prediction import predict_constant_velocity, predict_within_lanes
from mmpc.problem import EGO_FIELDS, ProblemBatch, ego_state
from mmpc.ranking import Selection, constraint_violation, select_best
from mmpc.result import SolveResult, Status, Trajectories, WarmStart
from mmpc.road import Road
from mmpc.solver.config import OptimizerConfig
from mmpc.solver.optimizer import BatchOptimizer

__version__ = "0.1.0"

__all__ = [
    "Basis",
    "CruiseCost",
    "CruiseGoals",
    "GoalSampler",
    "HighSpeedCost",
    "HighSpeedGoals",
    "MetaCost",
    "MPC",
    "MPCConfig",
    "NearLaneGoals",
    "Plan",
    "Road",
    "Selection",
    "constraint_violation",
    "select_best",
    "BatchOptimizer",
    "EGO_FIELDS",
    "OptimizerConfig",
    "ProblemBatch",
    "SolveResult",
    "Status",
    "Trajectories",
    "WarmStart",
    "bernstein_basis",
    "ego_state",
    "predict_constant_velocity",
    "predict_within_lanes",
]
