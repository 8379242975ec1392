"""highway-env's reward as one formula (mmpc.task_reward) and the expert re-weighted by it
(mmpc.meta_costs.TaskRewardCost, ``objective.task_reward_weight``)."""

import math

import pytest
import torch

import mmpc
from mmpc.meta_costs import CruiseCost, HighSpeedCost, LaneChangeCost, TaskRewardCost
from mmpc.scenario import CruiseObjective, HighSpeedObjective
from mmpc.task_reward import HighwayReward


def test_the_reward_has_highway_envs_values_at_its_corners():
    reward = HighwayReward()
    speed = torch.tensor([30.0, 20.0, 25.0, 35.0, 30.0, 30.0])
    lane = torch.tensor([5, 0, 2, 5, 5, 5])  # of 6 lanes: shares 1, 0, 0.4, 1, 1, 1
    crashed = torch.tensor([False, False, False, False, True, False])
    on_road = torch.tensor([True, True, True, True, True, False])
    values = reward(speed, lane, 6, crashed, on_road)
    # normalised from [-1, 0.5] onto [0, 1]: best 1, slowest left lane 2/3, a crash 0 even at best
    expected = [1.0, 1.0 / 1.5, (1.0 + 0.04 + 0.2) / 1.5, 1.0, (0.5 - 1.0 + 1.0) / 1.5, 0.0]
    torch.testing.assert_close(values, torch.tensor(expected))
    raw = HighwayReward(normalize=False)(speed[:1], lane[:1], 6, crashed[:1], on_road[:1])
    assert float(raw) == pytest.approx(0.5)


def _trajectories(v: float, y: float, psi: float = 0.0, samples: int = 5) -> mmpc.Trajectories:
    full = lambda value: torch.full((1, 1, samples), float(value))  # noqa: E731
    return mmpc.Trajectories(torch.linspace(0.0, 1.0, samples), full(0.0), full(y), full(psi), full(v), full(v), full(0.0),
                             full(0.0), full(0.0), full(0.0))


def test_the_task_cost_adds_the_weighted_reward_lost_per_sample():
    road, base = mmpc.Road(), CruiseCost(15.0)
    cost = TaskRewardCost(base, weight=10.0)
    best = _trajectories(30.0, road.right_lane_y)  # reward 1 at every sample: the base alone
    assert float(cost(best, road)) == pytest.approx(float(base(best, road)))
    slow_left = _trajectories(15.0, 0.0)  # reward 2/3 per sample, 5 samples
    assert float(cost(slow_left, road)) == pytest.approx(0.0 + 10.0 * 5 * (1 - 2 / 3))
    turned = _trajectories(30.0, road.right_lane_y, psi=math.acos(25.0 / 30.0))  # forward speed 25 m/s
    assert float(cost(turned, road) - base(turned, road)) == pytest.approx(10.0 * 5 * (1 - 1.3 / 1.5), rel=1e-5)
    with pytest.raises(ValueError, match="weight"):
        TaskRewardCost(base, weight=-1.0)


def test_a_heavy_weight_ranks_the_fast_right_lane_first_against_the_base():
    """Cruise's base prefers 15 m/s on any lane; re-weighted, 30 m/s on the right lane wins."""
    road = mmpc.Road()
    plain, weighted = CruiseObjective().meta_cost(), CruiseObjective(task_reward_weight=1000.0).meta_cost()
    cruise, fast_right = _trajectories(15.0, 8.0), _trajectories(30.0, road.right_lane_y)
    assert float(plain(cruise, road)) < float(plain(fast_right, road))
    assert float(weighted(fast_right, road)) < float(weighted(cruise, road))


def test_objectives_re_weight_only_when_asked():
    assert isinstance(HighSpeedObjective().meta_cost(), HighSpeedCost)
    both = HighSpeedObjective(lane_change_cost=50.0, task_reward_weight=2.0).meta_cost()
    assert isinstance(both, TaskRewardCost) and both.weight == 2.0 and isinstance(both.base, LaneChangeCost)
    with pytest.raises(ValueError, match="task_reward_weight"):
        CruiseObjective(task_reward_weight=-1.0)
