"""highway-env's ``highway-v0`` reward of the egos, batched (:class:`mmpc.task_reward.HighwayReward`;
the ego's lane is its nearest lane)."""

from __future__ import annotations

import torch

from mmpc.sim.config import SimConfig
from mmpc.sim.state import VehicleState, on_road
from mmpc.task_reward import HighwayReward


def highway_reward(state: VehicleState, config: SimConfig, terms: HighwayReward = HighwayReward()) -> torch.Tensor:
    """(E,) the reward ``terms`` give each environment's current state (slot 0, the ego), in the state's dtype."""
    forward_speed = state.speed[:, 0] * torch.cos(state.heading[:, 0])
    return terms(forward_speed, state.lane[:, 0], config.lanes, state.crashed[:, 0], on_road(state.y[:, 0], config))
