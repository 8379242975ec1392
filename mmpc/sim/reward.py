"""highway-env's ``highway-v0`` reward of the egos, batched.

``r = collision_reward * crashed + right_lane_reward * lane / max(lanes - 1, 1)
+ high_speed_reward * clip((v cos(heading) - low) / (high - low), 0, 1)``, mapped from
``[collision_reward, high_speed_reward + right_lane_reward]`` onto [0, 1] when ``normalize``,
times 0 off the road (``HighwayEnv._reward``; the ego's lane is its nearest lane). The defaults
are highway-env's.
"""

from __future__ import annotations

import torch

from mmpc.sim.config import SimConfig
from mmpc.sim.state import VehicleState, on_road


def highway_reward(
    state: VehicleState,
    config: SimConfig,
    *,
    collision_reward: float = -1.0,
    right_lane_reward: float = 0.1,
    high_speed_reward: float = 0.4,
    reward_speed_range: tuple[float, float] = (20.0, 30.0),
    normalize: bool = True,
) -> torch.Tensor:
    """(E,) the reward of each environment's current state (slot 0, the ego), in the state's dtype."""
    low, high = reward_speed_range
    forward_speed = state.speed[:, 0] * torch.cos(state.heading[:, 0])
    scaled_speed = ((forward_speed - low) / (high - low)).clamp(0.0, 1.0)
    lane = state.lane[:, 0].to(state.x.dtype) / max(config.lanes - 1, 1)
    reward = collision_reward * state.crashed[:, 0].to(state.x.dtype) + right_lane_reward * lane + high_speed_reward * scaled_speed
    if normalize:
        reward = (reward - collision_reward) / (high_speed_reward + right_lane_reward - collision_reward)
    return reward * on_road(state.y[:, 0], config).to(state.x.dtype)
