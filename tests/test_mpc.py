import math
import subprocess
import sys

import pytest
import torch

import mmpc


@pytest.fixture(scope="module")
def cruise_mpc() -> mmpc.MPC:
    optimizer = mmpc.BatchOptimizer()
    horizon = optimizer.config.horizon
    goals = mmpc.NearLaneGoals(mmpc.CruiseGoals(num_goals=6, horizon=horizon), speeds=(3.0, 6.0, 9.0, 12.0), horizon=horizon)
    return mmpc.MPC(optimizer, goals, mmpc.CruiseCost(15.0), mmpc.Road(num_lanes=6))


def test_library_mpc_does_not_import_the_simulator():
    code = "import sys, mmpc; mmpc.MPC; print(sorted(m for m in ('highway_env', 'gymnasium', 'pygame') if m in sys.modules))"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "[]"


def test_free_road_keeps_lane_and_speeds_up(cruise_mpc):
    ego = mmpc.ego_state(0.0, 8.0, 0.0, 14.0)
    plan = cruise_mpc.plan(ego, torch.zeros(1, 0, 4))
    assert bool(plan.selection.feasible[0])
    assert float(plan.acceleration[0]) > 0.0  # below the cruise speed
    assert abs(float(plan.steering[0])) < 1e-2
    assert plan.trajectory.x.shape == (1, cruise_mpc.optimizer.config.num_steps)


def test_slow_car_ahead_with_free_neighbour_plans_a_lane_change(cruise_mpc):
    ego = mmpc.ego_state(0.0, 8.0, 0.0, 15.0)
    car = torch.tensor([[[30.0, 8.0, 8.0, 0.0]]])
    plan = cruise_mpc.plan(ego, car)
    goal_y = float(plan.problem.goals[0, int(plan.selection.index[0]), 1])
    assert bool(plan.selection.feasible[0]) and goal_y != 8.0
    assert float(plan.result.min_obstacle_distance[0, int(plan.selection.index[0])]) >= 0.99


def test_blocked_lanes_choose_a_following_goal(cruise_mpc):
    road = mmpc.Road(num_lanes=3)
    horizon = cruise_mpc.optimizer.config.horizon
    goals = mmpc.NearLaneGoals(mmpc.CruiseGoals(num_goals=3, horizon=horizon), speeds=(3.0, 6.0, 9.0, 12.0), horizon=horizon)
    mpc = mmpc.MPC(cruise_mpc.optimizer, goals, cruise_mpc.meta_cost, road, mmpc.MPCConfig(num_obstacles=9))
    ego = mmpc.ego_state(0.0, 4.0, 0.0, 12.0)
    walls = [[x, y, 8.0, 0.0] for y in (0.0, 8.0) for x in (-6.0, 8.0, 22.0, 36.0)]  # gaps < 2 a: no way through
    plan = mpc.plan(ego, torch.tensor([[[25.0, 4.0, 8.0, 0.0], *walls]]))
    best = int(plan.selection.index[0])
    assert bool(plan.selection.feasible[0])
    assert plan.problem.goals[0, best, 1] == 4.0 and plan.problem.goals[0, best, 0] < 15.0 * 8.0
    assert float(plan.acceleration[0]) < 0.0


def test_a_neighbour_changing_lanes_ahead_does_not_block_the_cruise_plans(cruise_mpc):
    # A scene from cruise traffic (seed 4, t = 2.6 s): the car 13 m ahead, two lanes to the left,
    # moves right at 2.7 m/s (highway-env's lane change). Straight extrapolation sweeps it through
    # the ego's lane and beyond; the lane-bounded prediction ends its motion on the adjacent centre.
    ego = mmpc.ego_state(0.0, 15.0, 0.0, 14.6)
    cars = torch.tensor([[[-0.5, 20.0, 9.7, 0.0], [2.0, 0.2, 7.5, -0.55], [13.2, 10.0, 6.7, 2.72], [35.5, 20.0, 10.4, 0.0],
                          [40.1, 8.4, 8.7, -0.89], [51.5, 3.6, 7.7, -1.98], [59.3, 12.0, 6.4, 0.0]]])
    lanes = cruise_mpc.plan(ego, cars)
    straight = mmpc.MPC(cruise_mpc.optimizer, cruise_mpc.goal_sampler, cruise_mpc.meta_cost, cruise_mpc.road,
                        mmpc.MPCConfig(prediction="constant_velocity")).plan(ego, cars)
    changing = (lanes.problem.obstacles[0, :, 0] - torch.tensor([13.2, 10.0])).norm(dim=-1).argmin()
    assert float(lanes.problem.obstacles[0, changing, :, 1].max()) == 12.0
    assert float(straight.problem.obstacles[0, changing, :, 1].max()) > 20.0
    assert bool(lanes.selection.feasible[0]) and bool(straight.selection.feasible[0])
    assert int(lanes.result.feasible.sum()) > int(straight.result.feasible.sum())
    assert float(lanes.selection.cost[0]) < 0.1 * float(straight.selection.cost[0])  # ~3 vs ~230


def test_candidates_leaving_the_road_are_flagged(cruise_mpc):
    off_road = lambda ego, road: torch.tensor([[[120.0, 8.0], [120.0, 30.0], [120.0, -9.0]]])  # noqa: E731
    mpc = mmpc.MPC(cruise_mpc.optimizer, off_road, cruise_mpc.meta_cost, cruise_mpc.road)
    plan = mpc.plan(mmpc.ego_state(0.0, 8.0, 0.0, 15.0), torch.zeros(1, 0, 4))
    status = plan.result.status[0]
    assert not status[0] & mmpc.Status.OFF_ROAD
    assert status[1] & mmpc.Status.OFF_ROAD and status[2] & mmpc.Status.OFF_ROAD
    assert plan.result.feasible[0, :3].tolist() == [True, False, False] and int(plan.selection.index[0]) == 0  # then the stop goals


def test_ego_outside_the_margin_may_come_back(cruise_mpc):
    left, right = cruise_mpc.road.bounds
    ego = mmpc.ego_state(0.0, right - 0.5, 0.0, 15.0)  # beyond the 1 m margin already
    plan = cruise_mpc.plan(ego, torch.zeros(1, 0, 4))
    assert bool(plan.selection.feasible[0])
    assert float(plan.trajectory.y.max()) <= right - 0.5 + 1e-3


def test_no_feasible_candidate_falls_back_to_the_least_infeasible(cruise_mpc):
    ego = mmpc.ego_state(0.0, 8.0, 0.0, 15.0)
    inside = torch.tensor([[[3.0, 8.0, 15.0, 0.0]]])  # the ego starts inside the ellipse
    plan = cruise_mpc.plan(ego, inside)
    assert not bool(plan.selection.feasible[0])
    assert (plan.result.status[0] & mmpc.Status.START_IN_COLLISION).all()
    assert math.isfinite(float(plan.acceleration[0])) and math.isfinite(float(plan.steering[0]))
    assert abs(float(plan.steering[0])) <= cruise_mpc.config.max_steering


def test_an_ego_inside_a_neighbours_ellipse_may_drive_away_from_it(cruise_mpc):
    # Beside a car with a lane line between them: just inside its 5.6 m x 3 m ellipse, not touching.
    ego = mmpc.ego_state(0.0, 5.1, 0.0, 15.0)  # normalised distance 0.97
    beside = torch.tensor([[[1.0, 8.0, 15.0, 0.0]]])
    plan = cruise_mpc.plan(ego, beside)
    best = int(plan.selection.index[0])
    assert bool(plan.selection.feasible[0])
    inside = (plan.result.status[0] & mmpc.Status.START_IN_COLLISION) != 0
    assert plan.result.feasible[0].any() and inside.any()  # cleared where escaping, kept where not
    towards = (plan.problem.goals[0, :, 1] == 8.0) & (plan.problem.goals[0, :, 0] > 60.0)
    assert not plan.result.feasible[0, towards].all()
    gap = torch.hypot((plan.trajectory.x[0] - (1.0 + 15.0 * plan.trajectory.times)) / 5.6, (plan.trajectory.y[0] - 8.0) / 3.0)
    assert float(gap.min()) >= float(gap[0]) - cruise_mpc.optimizer.config.obstacle_tolerance  # never deeper
    assert float(plan.problem.goals[0, best, 1]) != 8.0
    deeper = cruise_mpc.plan(mmpc.ego_state(0.0, 5.5, 0.0, 15.0), beside)  # 0.84: a contour could reach the car's corner
    assert not deeper.result.feasible.any()


def test_an_ego_braking_harder_than_a_max_still_has_feasible_plans(cruise_mpc):
    # the fallback brakes at up to 5 m/s^2, beyond the plans' 4: the next plans start at the disc's edge
    at_edge = cruise_mpc.plan(mmpc.ego_state(0.0, 8.0, 0.0, 15.0, a=-4.0), torch.zeros(1, 0, 4))
    beyond = cruise_mpc.plan(mmpc.ego_state(0.0, 8.0, 0.0, 15.0, a=-5.0), torch.zeros(1, 0, 4))
    assert bool(beyond.selection.feasible[0]) and int(beyond.result.feasible.sum()) > 10
    assert torch.equal(beyond.result.status, at_edge.result.status)


def test_steering_inverts_the_kinematic_turn_rate(cruise_mpc):
    ego = mmpc.ego_state(0.0, 4.0, 0.0, 15.0)
    plan = cruise_mpc.plan(ego, torch.tensor([[[30.0, 4.0, 8.0, 0.0]]]))
    expected = math.atan(cruise_mpc.wheelbase * float(plan.heading_rate[0]) / 15.0)
    assert float(plan.steering[0]) == pytest.approx(expected, rel=1e-5)


def test_near_lane_goals_cover_the_lanes_around_the_ego():
    road = mmpc.Road(num_lanes=4)
    sampler = mmpc.NearLaneGoals(mmpc.CruiseGoals(num_goals=4, horizon=8.0), speeds=(5.0, 10.0), horizon=8.0, lanes_around=1)
    goals = sampler(mmpc.ego_state(0.0, 0.4, 0.0, 10.0), road)[0]
    assert goals.shape == (4 + 2 * 3, 2)
    extra = goals[4:]
    assert sorted(extra[:, 1].tolist()) == [0.0, 0.0, 4.0, 4.0, 8.0, 8.0]  # edge lane: the window shifts inwards
    assert sorted(set(extra[:, 0].tolist())) == [40.0, 80.0]
    middle = sampler(mmpc.ego_state(0.0, 8.2, 0.0, 10.0), road)[0, 4:]
    assert sorted(set(middle[:, 1].tolist())) == [4.0, 8.0, 12.0]
    wide = mmpc.NearLaneGoals(sampler.base, speeds=(5.0,), horizon=8.0, lanes_around=3)
    assert sorted(wide(mmpc.ego_state(0.0, 8.0, 0.0, 10.0), road)[0, 4:, 1].tolist()) == [0.0, 4.0, 8.0, 12.0]
    every_lane = mmpc.NearLaneGoals(sampler.base, speeds=(5.0,), horizon=8.0, lanes_around=None)
    assert every_lane(mmpc.ego_state(0.0, 0.0, 0.0, 10.0), road)[0, 4:, 1].tolist() == [0.0, 4.0, 8.0, 12.0]


@pytest.mark.parametrize("kwargs, name", [({"command_window": 0.0}, "command_window"), ({"road_margin": -1.0}, "road_margin"),
                                          ({"num_obstacles": -1}, "num_obstacles"),
                                          ({"prediction": "straight"}, "prediction"), ({"tie_margin": -1.0}, "tie_margin"),
                                          ({"tie_tolerance": float("inf")}, "tie_tolerance"),
                                          ({"obstacle_lookahead": -3.0}, "obstacle_lookahead")])
def test_mpc_config_is_validated(kwargs, name):
    with pytest.raises(ValueError, match=name):
        mmpc.MPCConfig(**kwargs)


def test_undrivable_candidates_give_a_lane_keeping_brake(cruise_mpc):
    off_road = lambda ego, road: torch.tensor([[[120.0, 40.0], [120.0, -20.0]]])  # noqa: E731
    no_stops = mmpc.MPCConfig(stop_lanes=None)  # a stop goal in the lane would be feasible
    mpc = mmpc.MPC(cruise_mpc.optimizer, off_road, cruise_mpc.meta_cost, cruise_mpc.road, no_stops)
    plan = mpc.plan(mmpc.ego_state(0.0, 8.5, 0.0, 15.0), torch.zeros(1, 0, 4))
    assert not bool(plan.selection.feasible[0])
    assert (plan.result.status[0] & mmpc.mpc.UNDRIVABLE).all()
    assert float(plan.acceleration[0]) == -mpc.config.brake_deceleration
    assert float(plan.heading_rate[0]) < 0.0  # back towards the centre of lane 2 (y = 8)


def test_auto_compile_is_the_float32_path_with_a_kernel_compiler(monkeypatch):
    from mmpc.solver import execution

    assert not mmpc.BatchOptimizer(compile="auto").compiled  # conftest: MMPC_COMPILE=0
    monkeypatch.setenv(execution.COMPILE_ENV, "maybe")
    with pytest.raises(ValueError, match="MMPC_COMPILE"):
        mmpc.BatchOptimizer(compile="auto")
    monkeypatch.delenv(execution.COMPILE_ENV)
    assert mmpc.BatchOptimizer(compile="auto").compiled
    assert not mmpc.BatchOptimizer(compile="auto", dtype=torch.float64).compiled  # mmpc.solver.trig is float32-exact
    monkeypatch.setattr(execution, "kernel_compiler_found", lambda on_cpu: False)
    assert not mmpc.BatchOptimizer(compile="auto").compiled
    with pytest.raises(ValueError, match="compile"):
        mmpc.BatchOptimizer(compile="fast")


def test_a_compiled_optimizer_compiles_each_layout_outside_the_timed_solve(cruise_mpc):
    runs = []

    class Counting(mmpc.BatchOptimizer):
        def _run(self, prepared, history):
            runs.append(prepared.mask.shape)
            return super()._run(prepared, history)

    optimizer = Counting()
    optimizer.compiled = True  # the warm-up rule only reads the flag; eager keeps the test fast
    mpc = mmpc.MPC(optimizer, cruise_mpc.goal_sampler, cruise_mpc.meta_cost, cruise_mpc.road)
    ego = mmpc.ego_state(0.0, 8.0, 0.0, 14.0)
    car = torch.tensor([[[40.0, 8.0, 10.0, 0.0]]])
    first, second = mpc.plan(ego, car), mpc.plan(ego, car)
    assert len(runs) == 3  # the new layout once untimed, then one call per step
    assert first.compile_ms > 0 and second.compile_ms == 0 and optimizer.last_compile_ms == 0
    two = torch.cat([ego, ego])
    mpc.plan(two, torch.cat([car, torch.zeros(1, 1, 4)]), torch.tensor([[True], [False]]))  # E = 2, mixed counts
    mpc.plan(two, torch.cat([car, car]))  # E = 2, uniform counts
    assert len(runs) == 7
    # Tiled, each tile's layout counts: the batch mixes counts, its one-problem tiles do not.
    tiled = Counting(tile_size=mpc.plan(ego, car).result.status.shape[1])
    tiled.compiled = True
    mmpc.MPC(tiled, cruise_mpc.goal_sampler, cruise_mpc.meta_cost, cruise_mpc.road).plan(
        two, torch.cat([car, torch.zeros(1, 1, 4)]), torch.tensor([[True], [False]])
    )
    assert len(runs) == 8 + 3  # the plan above; then one layout (1 problem, uniform): compile, two tiles
