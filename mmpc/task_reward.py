"""highway-env's reward (``HighwayEnv._reward``), the task reward of mmpc's RL and evaluation
figures, as one formula on tensors.

``r = collision_reward * crashed + right_lane_reward * lane / max(lanes - 1, 1) + high_speed_reward *
clip((v cos(heading) - low) / (high - low), 0, 1)``, mapped from ``[collision_reward,
high_speed_reward + right_lane_reward]`` onto [0, 1] when ``normalize``, times 0 off the road;
``lane`` is the nearest lane's index (0 leftmost, ``lanes - 1`` the right lane).
The defaults are highway-env's. The batched simulator (:func:`mmpc.sim.reward.highway_reward`),
the RL environments and the task-reward meta cost (:class:`mmpc.meta_costs.TaskRewardCost`) use it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class HighwayReward:
    """highway-env's reward terms (its ``HighwayEnv`` defaults).

    Attributes:
        collision_reward: reward of a crashed state.
        right_lane_reward: reward on the right lane (``lane_share`` 1).
        high_speed_reward: reward at or above ``reward_speed_range[1]`` of forward speed.
        reward_speed_range: (low, high) forward speeds mapped onto [0, 1] [m/s].
        normalize: map the sum onto [0, 1].
    """

    collision_reward: float = -1.0
    right_lane_reward: float = 0.1
    high_speed_reward: float = 0.4
    reward_speed_range: tuple[float, float] = (20.0, 30.0)
    normalize: bool = True

    def __call__(self, forward_speed: torch.Tensor, lane: torch.Tensor, lanes: int, crashed: torch.Tensor,
                 on_road: torch.Tensor) -> torch.Tensor:
        """The reward of states given as tensors of one shape (any): forward speed ``v cos(heading)``
        [m/s], ``lane`` the nearest lane's index on a road of ``lanes`` lanes, ``crashed`` and
        ``on_road`` as bool or 0/1."""
        dtype = forward_speed.dtype
        low, high = self.reward_speed_range
        scaled_speed = ((forward_speed - low) / (high - low)).clamp(0.0, 1.0)
        lane_share = lane.to(dtype) / max(lanes - 1, 1)
        reward = (self.collision_reward * crashed.to(dtype) + self.right_lane_reward * lane_share
                  + self.high_speed_reward * scaled_speed)
        if self.normalize:
            reward = (reward - self.collision_reward) / (self.high_speed_reward + self.right_lane_reward - self.collision_reward)
        return reward * on_road.to(dtype)
