"""Back-off: the iterations project onto shrunk feasible sets, the checks keep the true ones."""

import pytest
import torch

import mmpc
from mmpc.config import ConfigError
from mmpc.obstacles.prediction import predict_constant_velocity


def _swerve(config: mmpc.OptimizerConfig) -> mmpc.SolveResult:
    """A car 30 m ahead (8 m/s, 0.5 m right of the ego's line); the goal lies beyond it on that line."""
    opt = mmpc.BatchOptimizer(config)
    obstacles = predict_constant_velocity(torch.tensor([[[30.0, 0.5, 8.0, 0.0]]]), opt.times)
    return opt(mmpc.ProblemBatch(mmpc.ego_state(0.0, 0.0, 0.0, 14.0), torch.tensor([[[115.0, 0.0]]]), obstacles))


def test_obstacle_backoff_makes_an_unfinished_swerve_feasible():
    # 30 iterations: without back-off the plan still grazes the ellipse (0.987 < 0.99), infeasible
    plain = _swerve(mmpc.OptimizerConfig(iterations=30))
    assert not bool(plain.feasible) and plain.status.item() & int(mmpc.Status.OBSTACLE)
    assert 0.95 < plain.min_obstacle_distance.item() < 0.99
    # converging onto the ellipse scaled by 1.05, it is outside the true one already
    backed_off = _swerve(mmpc.OptimizerConfig(iterations=30, obstacle_backoff=0.05))
    assert bool(backed_off.feasible)
    assert 1.0 < backed_off.min_obstacle_distance.item() < 1.05
    assert backed_off.residual_obstacle.item() > 0.0  # measured against the scaled ellipse it projects onto


def test_obstacle_backoff_keeps_the_margin_once_converged():
    plain = _swerve(mmpc.OptimizerConfig())
    backed_off = _swerve(mmpc.OptimizerConfig(obstacle_backoff=0.05))
    assert bool(plain.feasible) and bool(backed_off.feasible)
    assert plain.min_obstacle_distance.item() == pytest.approx(1.0, abs=0.015)
    assert backed_off.min_obstacle_distance.item() == pytest.approx(1.05, abs=0.015)


def test_acceleration_backoff_shrinks_the_disc_the_plan_uses():
    # braking from 14 m/s to end 38 m ahead after 8 s: the acceleration bound is active
    goals = torch.tensor([[[38.0, 0.0]]])
    problem = mmpc.ProblemBatch(mmpc.ego_state(0.0, 0.0, 0.0, 14.0), goals, torch.zeros(1, 0, 100, 2))
    plain = mmpc.BatchOptimizer(mmpc.OptimizerConfig())(problem)
    backed_off = mmpc.BatchOptimizer(mmpc.OptimizerConfig(acceleration_backoff=0.3))(problem)
    assert bool(plain.feasible) and bool(backed_off.feasible)
    assert plain.max_acceleration.item() > 3.8
    assert backed_off.max_acceleration.item() < 3.7 + 0.02


@pytest.mark.parametrize(
    "overrides, message",
    [
        ({"obstacle_backoff": -0.01}, "obstacle_backoff"),
        ({"obstacle_backoff": 1.0}, "obstacle_backoff"),
        ({"acceleration_backoff": -0.1}, "acceleration_backoff"),
        ({"acceleration_backoff": 4.0}, r"acceleration_backoff.*a_max=4.0"),
    ],
)
def test_backoffs_out_of_range_are_refused(overrides, message):
    with pytest.raises(ConfigError, match=message):
        mmpc.OptimizerConfig(**overrides)
