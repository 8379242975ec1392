"""The meta cost reward (RewardConfig source: meta_cost) on highway-env, the batched simulator and
the plain highway-env baseline: ``1 - c / scale`` with c the scenario's meta cost term."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from mmpc.config import ConfigError, load_config
from mmpc.highway import HighwayEpisode
from mmpc.rl.config import RewardConfig, RLConfig
from mmpc.rl.reward import frame_reward
from mmpc.rl.engine import SafeEnvs
from mmpc.rl.train import make_highway_env

pytestmark = pytest.mark.usefixtures("one_thread")

META = RewardConfig(source="meta_cost", meta_cost_scale=50.0, collision_reward=-2.0)


@pytest.fixture(scope="module")
def smoke() -> RLConfig:
    return load_config(RLConfig, "smoke")


def test_the_meta_cost_reward_is_linear_in_the_cost_and_punishes_a_crash():
    assert META.meta_cost_reward(0.0, 0.0, 1.0) == 1.0
    assert META.meta_cost_reward(25.0, 0.0, 1.0) == pytest.approx(0.5)
    assert META.meta_cost_reward(25.0, 1.0, 1.0) == -2.0
    assert META.meta_cost_reward(25.0, 0.0, 0.0) == 0.0  # off the road
    costs = torch.tensor([0.0, 10.0, 100.0], dtype=torch.float64)
    values = META.meta_cost_reward(costs, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), torch.ones(3, dtype=torch.float64))
    assert values.tolist() == pytest.approx([1.0, 0.8, -2.0])


@pytest.mark.parametrize("bad, match", [({"source": "speed"}, "source"), ({"meta_cost_scale": 0.0}, "meta_cost_scale")])
def test_reward_config_refuses_unknown_kinds_and_scales(bad, match):
    with pytest.raises(ConfigError, match=match):
        RewardConfig(**bad)


def test_highway_env_frames_earn_the_meta_cost_reward_of_the_ego_state(smoke):
    episode = HighwayEpisode(smoke.scenario, seed=2)
    try:
        for acceleration in (2.0, -3.0):
            episode.apply(acceleration, 0.0)
            ego = episode.ego
            cost = (float(ego.speed) - smoke.scenario.objective.v_cruise) ** 2  # the RL scenario's cruise term
            assert frame_reward(episode, META) == pytest.approx(1.0 - cost / 50.0)
    finally:
        episode.close()


def test_the_batched_simulator_earns_the_same_meta_cost_reward(smoke):
    batch = SafeEnvs(3, smoke.scenario.replace(sim="batched"), smoke.env, META, seed=0)
    batch.reset([0, 1, 2])
    state = batch.world.sim.state
    expected = [1.0 - (float(v) - smoke.scenario.objective.v_cruise) ** 2 / 50.0 for v in state.speed[:, 0]]
    assert batch.task_rewards(torch.arange(3)).tolist() == pytest.approx(expected)
    step = batch.advance([0, 1, 2])
    # a step's reward sums its frames' rewards (less the intervention penalty): within [frames x (-2), frames]
    frames = np.array([info["frames"] for info in step.infos])
    assert np.all(step.rewards <= frames) and np.all(step.rewards >= -2.0 * frames - smoke.env.intervention_penalty * frames)


def test_the_plain_baseline_earns_the_meta_cost_reward_of_the_state_its_step_ends_in(smoke):
    config = dataclasses.replace(smoke, reward=META)
    env = make_highway_env(config)
    try:
        env.reset(seed=4)
        _, reward, _, _, info = env.step(1)  # IDLE
        ego = env.unwrapped.vehicle
        cost = (float(ego.speed) - smoke.scenario.objective.v_cruise) ** 2
        assert reward == pytest.approx(info["frames"] * META.meta_cost_reward(cost, float(ego.crashed), float(ego.on_road)))
    finally:
        env.close()
