"""The plain agent's meta-actions drive as highway-env's MDPVehicle, and the plain environments
train on the safe environments' world without a layer."""

from __future__ import annotations

import gymnasium as gym
import highway_env  # noqa: F401
import numpy as np
import pytest
import torch

from mmpc.config import load_config
from mmpc.highway.episode import RoadFrame, road_state
from mmpc.rl.config import RLConfig
from mmpc.rl.meta_actions import FASTER, IDLE, LANE_LEFT, LANE_RIGHT, META_ACTIONS, SLOWER, TARGET_SPEEDS, MetaActions
from mmpc.road import Road


@pytest.mark.parametrize("speed, speeds", [(25.0, TARGET_SPEEDS), (14.0, TARGET_SPEEDS), (14.0, (0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0))])
def test_meta_actions_command_what_highway_envs_mdp_vehicle_commands(speed, speeds):
    """Frame by frame, on highway-env's own road: a real MDPVehicle given a sequence of meta-actions
    (lane changes at the edge and in a row, speed steps at the ends of the set) and the meta-action
    controller reading the road-frame state agree on the targets and on the command, with
    highway-env's target speeds and a set that reaches down to rest."""
    from highway_env.vehicle.controller import MDPVehicle

    env = gym.make("highway-v0", config={"action": {"type": "DiscreteMetaAction"}, "lanes_count": 4, "vehicles_count": 0,
                                         "simulation_frequency": 10, "policy_frequency": 5, "initial_lane_id": 1})
    env.reset(seed=3)
    highway = env.unwrapped
    ego = highway.vehicle
    ego.speed = speed  # an ego created at this speed targets the nearest speed of the set
    ego = highway.vehicle = MDPVehicle(highway.road, ego.position, ego.heading, ego.speed, target_speeds=speeds)
    highway.road.vehicles = [ego]
    road, frame = Road(num_lanes=4, lane_width=4.0), RoadFrame.of(highway)
    meta = MetaActions(road, ego.LENGTH, speeds)
    state = road_state(highway, frame, dtype=torch.float64).ego
    targets = meta.start(state)
    assert (int(targets.lane[0]), int(targets.speed_index[0])) == (ego.target_lane_index[2], ego.speed_index)
    actions = [LANE_LEFT, LANE_LEFT, IDLE, FASTER, FASTER, FASTER, LANE_RIGHT, LANE_RIGHT, LANE_RIGHT, IDLE, SLOWER,
               LANE_LEFT, SLOWER, SLOWER, IDLE, LANE_RIGHT, FASTER] + [IDLE] * 4
    commands = []
    for action in actions:
        for first in (True, False):
            state = road_state(highway, frame, dtype=torch.float64).ego
            if first:
                targets = meta.apply(targets, torch.tensor([action]), state)
                ego.act(META_ACTIONS[action])
            highway.road.act()
            assert (int(targets.lane[0]), float(meta.target_speeds(targets)[0])) == (ego.target_lane_index[2], ego.target_speed)
            acceleration, steering = meta.command(targets, state)
            commands.append(((float(acceleration), float(steering)), (ego.action["acceleration"], ego.action["steering"])))
            highway.road.step(1 / 10)
    ours, theirs = np.array([c[0] for c in commands]), np.array([c[1] for c in commands])
    np.testing.assert_allclose(ours, theirs, atol=1e-6)
    assert np.abs(theirs[:, 1]).max() > 0.05 and np.abs(theirs[:, 0]).max() > 5  # lanes changed, speeds stepped


def test_meta_actions_refuse_an_index_outside_the_set_and_speeds_they_cannot_step_through():
    from mmpc.rl.config import SafeEnvConfig

    meta = MetaActions(Road(num_lanes=3), 5.0)
    ego = torch.tensor([[0.0, 4.0, 0.0, 25.0, 0.0, 0.0]], dtype=torch.float64)
    with pytest.raises(ValueError, match="LANE_LEFT"):
        meta.apply(meta.start(ego), torch.tensor([5]), ego)
    for speeds in [(20.0,), (30.0, 25.0, 20.0), (15.0, 25.0, 30.0), ("fast", 30.0)]:
        with pytest.raises(ValueError, match="meta_speeds"):
            SafeEnvConfig(meta_speeds=speeds)
        with pytest.raises(ValueError, match="evenly spaced"):  # the same check where no config stands before it
            MetaActions(Road(num_lanes=3), 5.0, speeds)
    assert SafeEnvConfig(meta_speeds=(0.0, 10.0, 20.0, 30.0)).meta_speeds[-1] == 30.0


def test_the_plain_environments_drive_the_safe_environments_world_without_a_layer():
    """PlainEnvs on the batched world: the agent's car in the recipe's traffic, reward summed over
    the frames, crashes end episodes that start again, bad actions refused before anything moves."""
    from mmpc.rl.plain import PlainEnvs

    config = load_config(RLConfig, "smoke", {"scenario.sim": "batched"})
    envs = PlainEnvs(4, config.scenario, config.env, config.reward, seed=0)
    observations, infos = envs.reset([11, 12, 13, 14])
    assert observations.shape == (4, config.env.kinematics_vehicles * 5) and infos[0] == {"episode_seed": 11}
    assert np.abs(observations).max() <= 1
    lanes = envs.targets.lane.clone()
    step = envs.advance([LANE_RIGHT, IDLE, FASTER, SLOWER])
    assert step.rewards.shape == (4,) and (step.rewards > 0).all()
    assert [info["frames"] for info in step.infos] == [config.env.decision_frames] * 4
    assert envs.targets.lane[0] == min(lanes[0] + 1, config.scenario.road.num_lanes - 1)
    with pytest.raises(ValueError, match="environment 1: `action` must be an int in \\[0, 5\\)"):
        envs.advance([0, 7, 0, 0])
    with pytest.raises(ValueError, match="meta-action"):
        envs.advance([0, 1.5, 0, 0])
    ended = 0
    for _ in range(12):  # the smoke scenario's 2 s episodes: at most 10 agent steps
        step = envs.advance([FASTER] * 4)
        ended += len(step.final)
        for row in step.final:
            assert step.reset_infos[row]["episode_seed"] == envs.seeds[row]
    assert ended >= 4  # every episode ended (crashed or timed out) and started again
    envs.close()
