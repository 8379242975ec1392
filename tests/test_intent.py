"""Which cars may change lanes next: the ego's estimate of MOBIL against the simulator's own MOBIL."""

import pytest
import torch

import mmpc
from mmpc.intent import DriverModel, mobil_lane_changes
from mmpc.sim.config import SimConfig
from mmpc.sim.mobil import mobil_accepts
from mmpc.sim.state import vehicle_state
from tests.test_obstacle_shape import _mpc

ROAD = mmpc.Road()
FAR_BEHIND = torch.tensor([[-500.0, 0.0, 20.0]])  # the ego, out of every decision


def _change(cars: list[list[float]], ego: torch.Tensor = FAR_BEHIND, model: DriverModel = DriverModel()) -> int:
    """MOBIL's lane change for the first of ``cars`` (lane 2 at y = 8 m), the others its traffic."""
    traffic = torch.tensor([cars])
    seen = torch.ones(traffic.shape[:2], dtype=torch.bool)
    return int(mobil_lane_changes(traffic[:, :1], traffic, seen, ego, ROAD, model)[0, 0])


def test_a_car_held_up_by_its_leader_moves_to_a_free_lane_the_right_one_first():
    held_up = [[0.0, 8.0, 10.0, 0.0], [25.0, 8.0, 8.0, 0.0]]  # a slower leader 25 m ahead on lane 2
    assert _change(held_up) == 1  # both neighbours free: MOBIL's right (lane 3) wins
    assert _change(held_up + [[20.0, 12.0, 8.0, 0.0]]) == -1  # lane 3 worse: left
    assert _change(held_up + [[20.0, 12.0, 8.0, 0.0], [20.0, 4.0, 8.0, 0.0]]) == 0  # both worse
    assert _change([[0.0, 8.0, 10.0, 0.0]]) == 0  # nobody ahead: nothing to gain
    assert _change(held_up + [[-8.0, 12.0, 14.0, 0.0], [-8.0, 4.0, 14.0, 0.0]]) == 0  # would cut off both followers
    assert _change(held_up + [[-60.0, 12.0, 10.0, 0.0]]) == 1  # lane 3's car far behind
    assert _change([[0.0, 8.0, 0.5, 0.0], [6.0, 8.0, 0.0, 0.0]]) == 0  # below 1 m/s MOBIL does not run
    astride = [[25.0, 5.5, 8.0, 0.0], [25.0, 10.5, 8.0, 0.0]]  # between lanes 1/2 and 2/3: on both
    assert _change(held_up[:1] + astride) == 0


def test_the_ego_behind_on_the_lane_keeps_cars_out_and_a_lower_threshold_warns_earlier():
    held_up = [[0.0, 8.0, 10.0, 0.0], [25.0, 8.0, 8.0, 0.0]]
    assert _change(held_up, torch.tensor([[-60.0, 11.0, 20.0]])) == -1  # the ego 1 m from lane 3, far behind: on it (3 m)
    assert _change(held_up, torch.tensor([[-60.0, 8.8, 20.0]])) == 1  # 0.8 m off lane 2: not yet on lane 3 (3 m of it)
    closing_in = [[0.0, 8.0, 10.0, 0.0], [60.0, 8.0, 9.0, 0.0], [65.0, 12.0, 10.0, 0.0], [40.0, 4.0, 8.0, 0.0]]
    assert _change(closing_in) == 0 and _change(closing_in, model=DriverModel(min_gain=0.0)) == 1  # gains 0.13 m/s^2


def test_no_traffic_no_change_and_bad_model_values_refused():
    cars = torch.tensor([[[0.0, 8.0, 10.0, 0.0]]])
    empty = mobil_lane_changes(cars, torch.zeros(1, 0, 4), torch.zeros(1, 0, dtype=torch.bool), FAR_BEHIND, ROAD)
    assert empty.tolist() == [[0]]
    absent = mobil_lane_changes(cars, torch.tensor([[[25.0, 8.0, 8.0, 0.0]]]), torch.zeros(1, 1, dtype=torch.bool),
                                FAR_BEHIND, ROAD)
    assert absent.tolist() == [[0]]  # a masked row is nobody
    with pytest.raises(ValueError, match=r"expected cars \(E, M, 4\).*got \(1, 1, 4\), \(1, 3\)"):
        mobil_lane_changes(cars, torch.zeros(1, 3), torch.zeros(1, 3, dtype=torch.bool), FAR_BEHIND, ROAD)
    with pytest.raises(ValueError, match="traffic_mask"):
        mobil_lane_changes(cars, cars, torch.ones(1, 1), FAR_BEHIND, ROAD)  # a float mask
    with pytest.raises(ValueError, match="comfort_deceleration"):
        DriverModel(comfort_acc_min=1.0)
    with pytest.raises(ValueError, match="lane_margin"):
        DriverModel(lane_margin=-0.1)


def test_the_estimate_is_the_simulators_mobil_for_cars_at_their_target_speed():
    """Random traffic on 6 lanes, every car at its target speed (the free-road term the ego cannot
    see cancels out of the gain; a new follower's is then 0 as the estimate assumes), the ego
    among them: the simulator's MOBIL decision, left or right, for every car."""
    generator = torch.Generator().manual_seed(7)
    environments, cars, lanes = 64, 12, 6
    config = SimConfig(lanes=lanes)
    x = torch.rand(environments, cars, generator=generator, dtype=torch.float64) * 150.0
    y = torch.randint(0, lanes, (environments, cars), generator=generator).to(torch.float64) * 4.0
    y = y + (torch.rand(environments, cars, generator=generator, dtype=torch.float64) - 0.5) * 1.6
    speed = 7.0 + 5.0 * torch.rand(environments, cars, generator=generator, dtype=torch.float64)
    speed[:, 0] = 20.0
    state = vehicle_state(x, y, speed=speed, config=config)
    traffic = torch.stack([x, y, speed, torch.zeros_like(x)], dim=-1)[:, 1:]
    seen = torch.ones(traffic.shape[:2], dtype=torch.bool)
    ego = torch.stack([x[:, 0], y[:, 0], speed[:, 0]], dim=-1)
    ours = mobil_lane_changes(traffic, traffic, seen, ego, mmpc.Road(num_lanes=lanes))
    slots = torch.arange(1, cars).expand(environments, -1)
    left, right = (mobil_accepts(state, state.lane[:, 1:] + side, config, slots) for side in (-1, 1))
    theirs = torch.where(right, 1, torch.where(left, -1, 0))
    assert torch.equal(ours, theirs)
    assert int(left.sum()) > 20 and int(right.sum()) > 20  # plenty of changes each way, not only refusals
    off_road = torch.stack([x[:, 0], torch.full_like(x[:, 0], -100.0), speed[:, 0]], dim=-1)
    assert not torch.equal(mobil_lane_changes(traffic, traffic, seen, off_road, mmpc.Road(num_lanes=lanes)), ours)


def test_the_incentive_trigger_gives_contingencies_to_the_cars_mobil_would_move():
    ego = mmpc.ego_state(0.0, 8.0, 0.0, 20.0)  # lane 2
    vehicles = torch.tensor([[[20.0, 8.0, 10.0, 0.0],    # ahead on the ego's lane, held up: will move right
                              [45.0, 8.0, 8.0, 0.0],     # its slower leader
                              [40.0, 4.0, 8.0, 0.0],     # lane 1, no better
                              [30.0, 16.0, 10.0, 0.0]]])  # lane 4, two lanes over, nothing to gain
    reach = _mpc(max_obstacles=6, contingencies=1, contingency_window=3.0, contingency_trigger="reach")
    incentive = _mpc(max_obstacles=6, contingencies=1, contingency_window=3.0)  # the default trigger
    assert bool(reach.build_problem(ego, vehicles).obstacle_mask[0, -1])  # lane 4's car, toward the ego
    problem = incentive.build_problem(ego, vehicles)
    contingency = problem.obstacles[0, -1]
    assert bool(problem.obstacle_mask[0, -1]) and float(contingency[0, 0]) == 20.0
    assert float(contingency[0, 1]) == 8.0 and float(contingency[-1, 1]) == 12.0  # lane 2 -> 3, MOBIL's side
    with pytest.raises(ValueError, match="contingency_trigger"):
        mmpc.MPCConfig(contingency_trigger="always")
