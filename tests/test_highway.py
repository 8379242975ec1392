"""The highway-env adapter: state extraction, action mapping, traffic, and closed-loop behaviour
on hand-built scenes (short episodes, run by default)."""

import math

import numpy as np
import pytest

from mmpc.highway.runner import run_episode
from mmpc.drivers import make_driver
from mmpc.highway import HighwayEpisode, command_to_action, env_config, vehicle_motion
from mmpc.scenario import EgoConfig, HighSpeedObjective, ScenarioConfig
from mmpc.traffic_config import IDMTraffic, ScriptedTraffic, ScriptedVehicle


pytestmark = pytest.mark.usefixtures("one_thread")


def scripted(vehicles, *, lanes=3, ego_lane=1, ego_speed=15.0, duration=12.0, objective=None) -> ScenarioConfig:
    scenario = ScenarioConfig(
        name="scene", lanes=lanes, duration=duration, ego=EgoConfig(speed=ego_speed, lane=ego_lane),
        traffic=ScriptedTraffic(tuple(ScriptedVehicle(*v) if isinstance(v, tuple) else v for v in vehicles)),
    )
    return scenario if objective is None else scenario.replace(objective=objective)


def test_env_config_commands_every_frame_with_continuous_actions():
    config = env_config(ScenarioConfig())
    assert config["simulation_frequency"] == config["policy_frequency"] == 10.0
    assert config["action"]["type"] == "ContinuousAction"
    assert config["lanes_count"] == 6 and config["vehicles_density"] >= 1.5


def test_action_mapping_round_trips_through_highway_env():
    episode = HighwayEpisode(scripted([]), seed=0)
    try:
        for acceleration, steering in [(0.0, 0.0), (2.5, 0.1), (-4.0, -0.3), (9.0, 2.0)]:
            applied = episode.unwrapped.action_type.get_action(command_to_action(acceleration, steering))
            assert applied["acceleration"] == pytest.approx(np.clip(acceleration, -5, 5), abs=1e-5)
            assert applied["steering"] == pytest.approx(np.clip(steering, -math.pi / 4, math.pi / 4), abs=1e-5)
    finally:
        episode.close()


def test_road_state_reads_every_vehicle_in_the_road_frame():
    episode = HighwayEpisode(scripted([(0, 20.0, 9.0), (2, -15.0, 11.0)]), seed=0)
    try:
        state = episode.observe()
        ego = episode.ego
        assert state.ego.shape == (1, 6) and state.vehicles.shape == (1, 2, 4)
        assert state.ego[0, :2].tolist() == pytest.approx(ego.position.tolist(), abs=1e-4)
        assert float(state.ego[0, 3]) == pytest.approx(15.0)
        rows = sorted(state.vehicles[0].tolist())
        assert rows[0][0] == pytest.approx(ego.position[0] - 15.0, abs=1e-3) and rows[0][1] == pytest.approx(8.0)
        assert rows[1][0] == pytest.approx(ego.position[0] + 20.0, abs=1e-3) and rows[1][1] == pytest.approx(0.0)
        assert [rows[0][2], rows[1][2]] == pytest.approx([11.0, 9.0])
    finally:
        episode.close()


def test_commanded_heading_rate_is_what_highway_env_executes():
    """A lane change's first command: the ego's turn rate after one frame matches the plan's."""
    scenario = scripted([(1, 25.0, 8.0)])
    episode, mpc = HighwayEpisode(scenario, seed=0), make_driver("mpc", scenario)
    try:
        for _ in range(5):
            _, decision = episode.step(mpc)
        plan = decision.plan
        _, turn_rate = vehicle_motion(episode.ego)
        assert abs(float(plan.heading_rate[0])) > 1e-3
        assert turn_rate == pytest.approx(float(plan.heading_rate[0]), rel=0.05)
        assert float(episode.ego.action["acceleration"]) == pytest.approx(float(plan.acceleration[0]), abs=1e-5)
    finally:
        episode.close()


def test_idm_traffic_gets_the_scenario_speeds_and_stays_around_the_ego():
    scenario = ScenarioConfig(duration=8.0)
    episode, mpc = HighwayEpisode(scenario, seed=3), make_driver("mpc", scenario)
    try:
        ego = episode.ego
        others = [v for v in episode.unwrapped.road.vehicles if v is not ego]
        assert len(others) == scenario.traffic.vehicles_count
        assert all(7.0 <= v.target_speed <= 12.0 for v in others)
        ahead = [v.position[0] - ego.position[0] for v in others if v.lane_index == ego.lane_index]
        assert all(not (-12.5 < dx < scenario.traffic.initial_clearance) for dx in ahead)
        while not episode.done:
            episode.step(mpc)
        behind, front = scenario.traffic.window
        for vehicle in episode.unwrapped.road.vehicles:
            assert -behind - 3.0 <= vehicle.position[0] - episode.ego.position[0] <= front + 3.0
    finally:
        episode.close()


def test_scripted_scene_with_a_window_recycles_vehicles_in_their_own_lane():
    """The ego at 15 m/s passes two 5 m/s cars; each falls out of the 20 m window behind and
    re-enters 75-100 m ahead in its own lane; a scene without a window leaves them behind."""
    vehicles = (ScriptedVehicle(lane=0, x=10.0, speed=5.0), ScriptedVehicle(lane=2, x=-5.0, speed=5.0))
    for window in [(20.0, 100.0), None]:
        scenario = scripted([]).replace(traffic=ScriptedTraffic(vehicles, window=window))
        episode = HighwayEpisode(scenario, seed=0)
        try:
            lowest = math.inf
            for _ in range(40):  # 4 s; at 10 m/s closing, both leave the window after 2-3 s
                episode.apply(0.0, 0.0)
                others = [v for v in episode.unwrapped.road.vehicles if v is not episode.ego]
                offsets = [v.position[0] - episode.ego.position[0] for v in others]
                lowest = min(lowest, *offsets)
            if window is None:
                assert all(dx < -20.0 for dx in offsets)
                continue
            assert lowest >= -21.5 and all(40.0 < dx <= 100.0 for dx in offsets)
            assert sorted(v.lane_index[2] for v in others) == [0, 2]
            assert all(v.target_lane_index == v.lane_index and v.speed == pytest.approx(5.0) for v in others)
        finally:
            episode.close()


def test_vehicle_size_resizes_every_vehicle_and_the_steering_inverts_the_new_wheelbase():
    """The authors' 4 m x 1.4 m cars: every vehicle (ego included) gets the footprint, and a
    lane change's commanded turn rate is what highway-env's bicycle executes with L = 4 m."""
    scenario = scripted([(1, 25.0, 8.0), (0, -10.0, 12.0)]).replace(vehicle_size=(4.0, 1.4))
    episode, mpc = HighwayEpisode(scenario, seed=0), make_driver("mpc", scenario)
    try:
        vehicles = episode.unwrapped.road.vehicles
        assert len(vehicles) == 3
        assert all((v.LENGTH, v.WIDTH, v.diagonal) == pytest.approx((4.0, 1.4, math.hypot(4.0, 1.4))) for v in vehicles)
        for _ in range(5):
            _, decision = episode.step(mpc)
        _, turn_rate = vehicle_motion(episode.ego)
        assert abs(float(decision.plan.heading_rate[0])) > 1e-3
        assert turn_rate == pytest.approx(float(decision.plan.heading_rate[0]), rel=0.05)
    finally:
        episode.close()


def test_default_traffic_option_keeps_highway_env_speeds():
    scenario = ScenarioConfig(duration=1.0, traffic=IDMTraffic(target_speeds=None))
    episode = HighwayEpisode(scenario, seed=0)
    try:
        speeds = [v.target_speed for v in episode.unwrapped.road.vehicles if v is not episode.ego]
        assert min(speeds) >= 20.0
    finally:
        episode.close()


# ------------------------------------------------------------------------ behaviour on hand-built scenes


def _lanes(result):
    return [r.lane for r in result.records]


def test_slow_car_ahead_with_a_free_lane_is_overtaken():
    scene = scripted([ScriptedVehicle(lane=1, x=40.0, speed=8.0, constant_speed=True)], duration=14.0)
    result = run_episode(scene, seed=0)
    assert result.metrics["collisions"] == 0 and result.metrics["offroad"] == 0
    assert set(_lanes(result)) - {1}, "the ego never left its lane"
    final = result.records[-1]
    slow_car_x = result.records[0].x + 40.0 + 8.0 * final.time
    assert final.x > slow_car_x + 10.0, "the ego did not get past the slow car"
    assert final.v > 14.0
    assert result.metrics["min_clearance"] >= 0.95


def test_blocked_neighbour_lanes_make_the_ego_follow():
    walls = [ScriptedVehicle(lane=lane, x=x, speed=8.0, constant_speed=True)
             for lane in (0, 2) for x in np.arange(-24.0, 200.0, 12.0)]
    leader = ScriptedVehicle(lane=1, x=35.0, speed=8.0, constant_speed=True)
    result = run_episode(scripted([leader, *walls], ego_speed=12.0, duration=14.0), seed=0)
    assert result.metrics["collisions"] == 0
    assert set(_lanes(result)) == {1}
    assert result.records[-1].v == pytest.approx(8.0, abs=1.0)
    gap = result.records[0].x + 35.0 + 8.0 * result.records[-1].time - result.records[-1].x
    assert gap > 8.0, "following closer than the safety ellipse"
    assert result.metrics["min_clearance"] >= 0.95


def test_high_speed_with_the_right_lane_free_ends_in_the_right_lane():
    traffic = [ScriptedVehicle(lane=1, x=60.0, speed=14.0), ScriptedVehicle(lane=0, x=30.0, speed=16.0)]
    scene = scripted(traffic, lanes=4, ego_lane=1, ego_speed=18.0, duration=14.0, objective=HighSpeedObjective())
    result = run_episode(scene, seed=0)
    assert result.metrics["collisions"] == 0 and result.metrics["offroad"] == 0
    final = result.records[-1]
    assert final.lane == 3 and abs(final.y - 12.0) < 0.5
    assert final.v > 20.0


def test_episodes_are_reproducible_from_the_seed():
    scenario = ScenarioConfig(duration=2.0)
    first, second = run_episode(scenario, seed=5), run_episode(scenario, seed=5)
    assert [r[:10] for r in first.records] == [r[:10] for r in second.records]
