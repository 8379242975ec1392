"""Gradients flow from the outputs to goals and obstacle inputs."""

import torch

import mmpc
from tests.conftest import small_config


def test_gradcheck_goals_and_obstacles():
    config = small_config(num_steps=12, order=6, iterations=6, max_obstacles=2)
    opt = mmpc.BatchOptimizer(config, dtype=torch.float64)
    ego = mmpc.ego_state(0.0, 4.0, 0.02, 12.0, 0.3, 0.01, dtype=torch.float64)
    goals = torch.tensor([[[95.0, 4.0], [100.0, 8.0]]], dtype=torch.float64, requires_grad=True)
    # An obstacle the straight path runs into, so the obstacle step is active.
    states = torch.tensor([[[25.0, 5.0, 9.0, 0.0], [60.0, 8.5, 7.0, 0.0]]], dtype=torch.float64)
    obstacles = mmpc.predict_constant_velocity(states, opt.times).requires_grad_(True)

    def outputs(goals, obstacles):
        result = opt(mmpc.ProblemBatch(ego, goals, obstacles))
        return result.trajectories.x, result.trajectories.y, result.trajectories.v, result.trajectories.psi

    active = opt(mmpc.ProblemBatch(ego, goals.detach(), obstacles.detach()))
    assert (active.residual_obstacle > 0).any() or (active.min_obstacle_distance < 1.5).any()
    assert torch.autograd.gradcheck(outputs, (goals, obstacles), eps=1e-6, atol=1e-4, rtol=1e-3)


def test_meta_cost_gradient_reaches_goals():
    opt = mmpc.BatchOptimizer(small_config(), dtype=torch.float64)
    ego = mmpc.ego_state(0.0, 4.0, 0.0, 12.0, dtype=torch.float64)
    goals = torch.tensor([[[100.0, 4.0]]], dtype=torch.float64, requires_grad=True)
    obstacles = torch.zeros(1, 0, opt.config.num_steps, 2, dtype=torch.float64)
    result = opt(mmpc.ProblemBatch(ego, goals, obstacles))
    cost = mmpc.CruiseCost(15.0)(result.trajectories, mmpc.Road()).sum()
    cost.backward()
    # Pulling the goal further ahead raises the speed towards 15 m/s: the x-gradient is negative.
    assert goals.grad[0, 0, 0] < 0
