"""Fail-safe: stop goals, a fallback that never accelerates into a conflict, bad MPC input, and
stopped-traffic scenes driven on highway-env (mmpc.highway.stopped_traffic)."""

import math

import pytest
import torch

import mmpc
from mmpc.highway.runner import run_episode
from mmpc.drivers import make_driver
from mmpc.obstacles.prediction import predict_constant_velocity
from mmpc.scenario import load_scenario
from mmpc.highway.stopped_traffic import STOPPED_SPEED, stopped_traffic_grid, stopped_traffic_scene
from mmpc.stopping import MIN_ADVANCE, conflict_deceleration, stop_goals

ELLIPSE = (8.0, 3.3)
TIMES = torch.linspace(0.0, 8.0, 100)


def predicted(states):
    states = torch.tensor(states, dtype=torch.float32).reshape(1, -1, 4)
    return predict_constant_velocity(states, TIMES), torch.ones(states.shape[:2], dtype=torch.bool)


def wall_mpc(stop_lanes=1):
    scenario = load_scenario("cruise", {"lanes": 3, "mpc.stop_lanes": stop_lanes})
    return mmpc.scenario.build_mpc(scenario)


def test_stop_goals_rest_behind_the_first_vehicle_ahead_in_each_lane():
    road = mmpc.Road(num_lanes=3)
    ego = mmpc.ego_state(100.0, 4.0, 0.0, 20.0)
    # lane 0: a stopped car 50 m ahead; lane 1: one behind the ego (ignored) and one 90 m ahead;
    # lane 2: clear but for a masked slot 20 m ahead.
    obstacles, mask = predicted([[150.0, 0.0, 0.0, 0.0], [80.0, 4.0, 0.0, 0.0], [190.0, 4.0, 0.0, 0.0], [120.0, 8.0, 0.0, 0.0]])
    mask[0, 3] = False
    goals = stop_goals(ego, obstacles, mask, road, horizon=8.0, ellipse=ELLIPSE, lanes=1, gap=2.0)
    assert goals.shape == (1, 3, 2)
    assert goals[0, :, 1].tolist() == [0.0, 4.0, 8.0]
    assert goals[0, 0, 0].item() == pytest.approx(150.0 - 8.0 - 2.0)
    assert goals[0, 1, 0].item() == pytest.approx(100.0 + 0.5 * 8.0 * 20.0)  # 80 m of room > braking to rest over 8 s
    assert goals[0, 2, 0].item() == pytest.approx(100.0 + 80.0)
    # Already at the obstacle: the goal stays just ahead (the optimizer needs it ahead).
    close = stop_goals(mmpc.ego_state(145.0, 0.0, 0.0, 1.0), obstacles, mask, road, horizon=8.0, ellipse=ELLIPSE, lanes=0, gap=2.0)
    assert close[0, 0].tolist() == pytest.approx([145.0 + MIN_ADVANCE, 0.0])


def test_stop_goals_see_a_vehicle_that_cuts_into_the_lane():
    road = mmpc.Road(num_lanes=2)
    ego = mmpc.ego_state(0.0, 4.0, 0.0, 20.0)
    cutting = predict_constant_velocity(torch.tensor([[[40.0, 0.0, 10.0, 1.0]]]), TIMES)  # reaches lane 1 at ~1 s
    goals = stop_goals(ego, cutting, torch.ones(1, 1, dtype=torch.bool), road, horizon=8.0, ellipse=ELLIPSE, lanes=0, gap=2.0)
    assert goals[0, 0, 1].item() == 4.0
    assert 40.0 - 8.0 - 2.0 < goals[0, 0, 0].item() < 60.0 - 8.0 - 2.0


def test_conflict_deceleration_keeps_a_vehicle_length_to_the_leader_in_the_lane():
    ego = mmpc.ego_state(0.0, 0.0, 0.0, 20.0)
    kw = dict(half_width=2.0, standoff=7.0, max_deceleration=5.0)
    # stopped ahead in the lane; beside in the next lane; behind and faster: only the first counts
    obstacles, mask = predicted([[60.0, 0.0, 0.0, 0.0], [30.0, 4.0, 0.0, 0.0], [-20.0, 0.0, 30.0, 0.0]])
    assert conflict_deceleration(ego, obstacles, mask, TIMES, **kw).item() == pytest.approx(-(20.0**2) / (2 * 53.0), rel=1e-5)
    slower, _ = predicted([[60.0, 0.0, 15.0, 0.0]])
    assert conflict_deceleration(ego, slower, mask[:, :1], TIMES, **kw).item() == pytest.approx(-(5.0**2) / (2 * 53.0), rel=1e-4)
    cutting_in, _ = predicted([[30.0, 4.0, 10.0, -1.0]])  # from the next lane into the ego's
    assert conflict_deceleration(ego, cutting_in, mask[:, :1], TIMES, **kw).item() == pytest.approx(-(10.0**2) / (2 * 23.0), rel=1e-4)
    beside, _ = predicted([[3.0, 3.3, 10.0, 0.0]])  # inside the planner's ellipse, but not in the lane
    assert conflict_deceleration(ego, beside, mask[:, :1], TIMES, **kw).item() == 0.0
    inside, _ = predicted([[6.0, 0.0, 0.0, 0.0]])
    assert conflict_deceleration(ego, inside, mask[:, :1], TIMES, **kw).item() == -5.0
    assert conflict_deceleration(ego, obstacles[:, :0], mask[:, :0], TIMES, **kw).item() == 0.0


@pytest.mark.parametrize("speed, distance", [(5.0, 25.0), (14.0, 60.0), (25.0, 110.0)])
def test_in_front_of_a_stopped_wall_the_mpc_never_accelerates(speed, distance):
    """Every lane blocked by stopped cars: today's goals all lie ``v t_f`` ahead, and without
    stop goals the least-infeasible plan accelerated into the wall."""
    mpc = wall_mpc()
    ego = mmpc.ego_state(0.0, 4.0, 0.0, speed)
    wall = torch.tensor([[[distance, 4.0 * lane, 0.0, 0.0] for lane in range(3)]])
    plan = mpc.plan(ego, wall)
    assert plan.acceleration.item() < 0.0
    assert plan.selection.feasible.item() or plan.acceleration.item() <= -(speed**2) / (2 * (distance - 7.0)) + 1e-6
    if plan.selection.feasible.item():
        assert plan.trajectory.x[0, -1].item() <= distance - ELLIPSE[0]  # a stop goal, short of the wall


def test_a_fallback_never_accelerates_and_brakes_for_the_conflict_ahead():
    mpc = wall_mpc(stop_lanes=None)
    ego = mmpc.ego_state(0.0, 4.0, 0.0, 6.0)
    wall = torch.tensor([[[25.0, 4.0 * lane, 0.0, 0.0] for lane in range(3)]])
    plan = mpc.plan(ego, wall)
    assert not plan.selection.feasible.item()
    assert plan.acceleration.item() <= -(6.0**2) / (2 * (25.0 - 5.0 - 2.0)) + 1e-6


def test_mpc_plan_refuses_bad_input():
    mpc = wall_mpc()
    ego = mmpc.ego_state(0.0, 4.0, 0.0, 14.0)
    cars = torch.tensor([[[30.0 + 5 * k, 4.0 * (k % 3), 10.0, 0.0] for k in range(8)]])
    broken = cars.clone()
    broken[0, 7, 0] = float("nan")  # beyond the 6 slots the optimizer sees
    with pytest.raises(ValueError, match=r"vehicles.*finite.*\[\[0, 7\]\]"):
        mpc.plan(ego, broken)
    with pytest.raises(ValueError, match="vehicle_mask.*shape \\(1, 8\\).*\\(1, 1\\)"):
        mpc.plan(ego, cars, torch.zeros(1, 1, dtype=torch.bool))
    with pytest.raises(ValueError, match="vehicle_mask.*bool.*torch.int64"):
        mpc.plan(ego, cars, torch.ones(1, 8, dtype=torch.long))
    with pytest.raises(ValueError, match="ego.*finite"):
        mpc.plan(ego * float("inf"), cars)
    with pytest.raises(TypeError, match="vehicles.*Tensor"):
        mpc.plan(ego, cars.tolist())
    # A NaN in a slot the mask marks absent is not a vehicle: same plan as without it.
    mask = torch.ones(1, 8, dtype=torch.bool)
    mask[0, 7] = False
    clean = cars.clone()
    clean[0, 7] = 0.0
    assert torch.equal(mpc.plan(ego, broken, mask).acceleration, mpc.plan(ego, clean, mask).acceleration)


def test_stop_lanes_is_validated_and_adds_goals():
    with pytest.raises(ValueError, match="stop_lanes"):
        mmpc.MPCConfig(stop_lanes=-1)
    with pytest.raises(ValueError, match="max_deceleration"):
        mmpc.MPCConfig(brake_deceleration=4.0, max_deceleration=3.0)
    ego = mmpc.ego_state(0.0, 4.0, 0.0, 14.0)
    with_stops = wall_mpc().build_problem(ego, torch.zeros(1, 0, 4))
    without = wall_mpc(stop_lanes=None).build_problem(ego, torch.zeros(1, 0, 4))
    assert with_stops.goals.shape[1] == without.goals.shape[1] + 3
    assert torch.equal(with_stops.goals[:, : without.goals.shape[1]], without.goals)  # standard goals keep their indices


def test_grid_scenes_are_what_they_say():
    base = load_scenario("cruise")
    scenes = stopped_traffic_grid(base, speeds=(10.0, 30.0), ratios=(1.3, 5.0))
    assert len(scenes) == 2 * 2 * 2 + 2
    wall = stopped_traffic_scene(base, "wall", 20.0, 2.0)
    assert wall.gap == pytest.approx(2.0 * 20.0**2 / (2 * base.optimizer.a_max))
    assert [v.x for v in wall.scenario.traffic.vehicles] == [wall.gap + 5.0] * 3 and wall.scenario.lanes == 3
    assert stopped_traffic_scene(base, "single", 30.0, 1.3).scenario.optimizer.v_max == 30.0
    assert not stopped_traffic_scene(base, "cut_in", 10.0, 1.3).blocked
    with pytest.raises(ValueError, match="layout"):
        stopped_traffic_scene(base, "jam", 10.0, 1.3)


@pytest.mark.usefixtures("one_thread")
@pytest.mark.parametrize("layout, speed, ratio", [("single", 10.0, 1.3), ("wall", 25.0, 1.6), ("cut_in", 14.0, 1.3)])
def test_the_mpc_stops_for_stopped_traffic_on_highway_env(layout, speed, ratio):
    """``wall`` 25 m/s x 1.6 is the reported case (stopped cars 130 m ahead in every lane):
    before the stop goals the fallback accelerated into them at 13.8 m/s."""
    scene = stopped_traffic_scene(load_scenario("cruise"), layout, speed, ratio)
    result = run_episode(scene.scenario, 0)
    assert result.metrics["collisions"] == 0
    assert scene.passed(result.metrics["collisions"], result.records[-1].v)
    assert all(r.command_acceleration <= 0.0 for r in result.records if r.fallback)


@pytest.mark.usefixtures("one_thread")
def test_the_frenet_baseline_shares_the_stop():
    scene = stopped_traffic_scene(load_scenario("cruise"), "single", 10.0, 1.3)
    result = run_episode(scene.scenario, 0, driver=make_driver("frenet", scene.scenario))
    assert result.metrics["collisions"] == 0 and result.records[-1].v < STOPPED_SPEED


@pytest.mark.usefixtures("one_thread")
def test_the_safe_rl_layer_stops_whatever_a_random_agent_asks():
    from mmpc.rl.envs import SafeHighwayEnv

    scene = stopped_traffic_scene(load_scenario("cruise"), "single", 20.0, 1.3)
    env = SafeHighwayEnv(scene.scenario)
    env.action_space.seed(3)
    env.reset(seed=0)
    done, crashed, steps = False, False, 0
    while not done:
        _, _, terminated, truncated, info = env.step(int(env.action_space.sample()))
        crashed, done, steps = crashed or info["crashed"], terminated or truncated, steps + 1
    assert not crashed and env.episode.ego.speed < STOPPED_SPEED
    assert steps == math.ceil(scene.scenario.duration * scene.scenario.frequency / env.config.decision_frames)
    env.close()
