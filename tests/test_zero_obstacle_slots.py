"""An MPC with no obstacle slots (``mpc.num_obstacles: 0``, an empty road as the planner sees
it) plans; the stop goals then find no conflict (issue 44, item 8)."""

from __future__ import annotations

import math

import torch

from mmpc.road import Road
from mmpc.scenario import PAPER_SCHEDULE, build_mpc, load_scenario
from mmpc.stopping import conflict_deceleration, first_conflict_x, stop_goals


def test_stopping_with_no_obstacle_slots_finds_no_conflict():
    ego = torch.tensor([[0.0, 4.0, 0.0, 15.0, 0.0, 0.0]])
    obstacles, mask = torch.zeros(1, 0, 100, 2), torch.zeros(1, 0, dtype=torch.bool)
    corridor = torch.full((1, 3, 100), 4.0)
    assert first_conflict_x(corridor, ego[:, 0], obstacles, mask, 3.0).tolist() == [[math.inf] * 3]
    goals = stop_goals(ego, obstacles, mask, Road(num_lanes=3), horizon=8.0, ellipse=(8.0, 3.3), lanes=1, gap=2.0)
    assert goals.shape == (1, 3, 2) and torch.allclose(goals[..., 0], torch.tensor(0.5 * 8.0 * 15.0))
    times = torch.linspace(0.0, 8.0, 100)
    braking = conflict_deceleration(ego, obstacles, mask, times, half_width=2.0, standoff=7.0, max_deceleration=5.0)
    assert braking.tolist() == [0.0]


def test_an_mpc_with_no_obstacle_slots_plans_past_the_vehicles_it_ignores():
    scenario = load_scenario("cruise", {"mpc.num_obstacles": 0, "optimizer.iterations": 10, **PAPER_SCHEDULE})
    mpc = build_mpc(scenario, compile=False)
    ego = torch.tensor([[0.0, 8.0, 0.0, 15.0, 0.0, 0.0], [0.0, 4.0, 0.0, 12.0, 0.0, 0.0]])
    vehicles = torch.tensor([[[30.0, 8.0, 10.0, 0.0]], [[20.0, 4.0, 5.0, 0.0]]])
    plan = mpc.plan(ego, vehicles)
    assert plan.problem.obstacles.shape == (2, 0, scenario.optimizer.num_steps, 2)
    assert plan.acceleration.shape == (2,) and bool(torch.isfinite(plan.acceleration).all())
    assert bool(torch.isfinite(plan.steering).all())
