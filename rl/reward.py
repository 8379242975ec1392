"""The RL reward of ego states in any world (:class:`mmpc.rl.config.RewardConfig`), one formula
for highway-env's vehicles and the batched simulator's rows."""

from __future__ import annotations

from typing import Any

import torch

from mmpc.highway.ego_terms import EgoTerms
from mmpc.highway.highway_env_world import vehicle_terms
from mmpc.rl.config import RewardConfig
from mmpc.scenario import ScenarioConfig


def task_rewards(terms: EgoTerms, reward: RewardConfig, scenario: ScenarioConfig) -> torch.Tensor:
    """(R,) float64 rewards of the states whose egos ``terms`` describe: highway-env's reward terms
    (``source: highway``), or the scenario's meta cost term made a reward (``source: meta_cost``)."""
    if reward.source == "meta_cost":
        cost = scenario.objective.stage_cost(terms.speed, terms.y, scenario.road)
        return reward.meta_cost_reward(cost, terms.crashed, terms.on_road)
    return reward.highway_terms()(terms.forward_speed, terms.lane, scenario.lanes, terms.crashed, terms.on_road)


def vehicle_reward(ego: Any, scenario: ScenarioConfig, reward: RewardConfig) -> float:
    """The reward of a highway-env vehicle ``ego``'s current state (:func:`task_rewards`)."""
    return float(task_rewards(vehicle_terms([ego]), reward, scenario)[0])


def frame_reward(episode: Any, reward: RewardConfig) -> float:
    """The reward of a :class:`mmpc.highway.HighwayEpisode`'s current state (:func:`task_rewards`)."""
    return vehicle_reward(episode.ego, episode.scenario, reward)
