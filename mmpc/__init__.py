"""mmpc: multi-modal model predictive control by batch non-holonomic trajectory optimization."""

from mmpc.basis import Basis, bernstein_basis
from mmpc.config import OptimizerConfig
from mmpc.optimizer import BatchOptimizer
from mmpc.problem import EGO_FIELDS, ProblemBatch, ego_state, predict_constant_velocity
from mmpc.result import SolveResult, Status, Trajectories

__version__ = "0.1.0"

__all__ = [
    "Basis",
    "BatchOptimizer",
    "EGO_FIELDS",
    "OptimizerConfig",
    "ProblemBatch",
    "SolveResult",
    "Status",
    "Trajectories",
    "bernstein_basis",
    "ego_state",
    "predict_constant_velocity",
]
