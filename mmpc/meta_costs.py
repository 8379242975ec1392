"""Meta costs: rank the optimized trajectories of a batch by a higher-level driving objective.

A meta cost is any callable ``cost(trajectories, road) -> (E, G)`` over
:class:`mmpc.Trajectories`; lower is better.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import torch

from mmpc.result import Trajectories
from mmpc.road import Road
from mmpc.task_reward import HighwayReward


class MetaCost(Protocol):
    def __call__(self, trajectories: Trajectories, road: Road) -> torch.Tensor:
        """(E, G) cost of each trajectory; lower is better."""
        ...


@dataclass(frozen=True)
class CruiseCost:
    """Cruise driving: ``sum_t (v(t) - v_cruise)^2`` [m^2/s^2].

    Attributes:
        v_cruise: cruise speed [m/s].
    """

    v_cruise: float = 15.0

    def __call__(self, trajectories: Trajectories, road: Road) -> torch.Tensor:
        return ((trajectories.v - self.v_cruise) ** 2).sum(dim=-1)


@dataclass(frozen=True)
class HighSpeedCost:
    """High speed near the right lane: ``sum_t w_speed (v - v_max)^2 + w_lane (y - y_right)^2``.

    Attributes:
        v_max: desired top speed [m/s].
        w_speed: weight of the speed term [s^2/m^2].
        w_lane: weight of the right-lane term [1/m^2].
    """

    v_max: float = 24.0
    w_speed: float = 1.0
    w_lane: float = 0.1

    def __call__(self, trajectories: Trajectories, road: Road) -> torch.Tensor:
        speed_term = (trajectories.v - self.v_max) ** 2
        lane_term = (trajectories.y - road.right_lane_y) ** 2
        return (self.w_speed * speed_term + self.w_lane * lane_term).sum(dim=-1)


@dataclass(frozen=True)
class LaneChangeCost:
    """``base`` plus ``per_lane`` for every lane between the lane a trajectory starts in and the
    lane it ends in (nearest lane centres): hysteresis on the chosen lane. A change must gain at
    least ``per_lane`` to start; past the lane line the new lane is the current one, so going
    back costs as much, and a change once started is completed.

    Attributes:
        base: the driving objective.
        per_lane: cost of one lane changed, in ``base``'s units.
    """

    base: MetaCost
    per_lane: float

    def __post_init__(self) -> None:
        if not self.per_lane >= 0:
            raise ValueError(f"`per_lane` must be >= 0 (meta-cost units per lane); got {self.per_lane}")

    def __call__(self, trajectories: Trajectories, road: Road) -> torch.Tensor:
        lanes = road.lane_index(trajectories.y[..., -1]) - road.lane_index(trajectories.y[..., 0])
        return self.base(trajectories, road) + self.per_lane * lanes.abs().to(trajectories.y.dtype)


@dataclass(frozen=True)
class TaskRewardCost:
    """``base`` re-weighted by highway-env's reward: ``base + weight * sum_t (1 - r_t)``, with
    ``r_t`` :class:`mmpc.task_reward.HighwayReward` of the trajectory's state at t (forward speed
    ``v cos(psi)``, its nearest lane, on the road, no collision), in [0, 1] per sample.

    Attributes:
        base: the driving objective.
        weight: what a sample's lost task reward costs, in ``base``'s units per sample.
        reward: the reward's terms (highway-env's defaults).
    """

    base: MetaCost
    weight: float
    reward: HighwayReward = HighwayReward()

    def __post_init__(self) -> None:
        if not self.weight >= 0:
            raise ValueError(f"`weight` must be >= 0 (meta-cost units per sample); got {self.weight}")

    def __call__(self, trajectories: Trajectories, road: Road) -> torch.Tensor:
        forward_speed = trajectories.v * torch.cos(trajectories.psi)
        no = torch.zeros((), dtype=torch.bool, device=forward_speed.device)
        reward = self.reward(forward_speed, road.lane_index(trajectories.y), road.num_lanes, no, ~no)
        return self.base(trajectories, road) + self.weight * (1.0 - reward).sum(dim=-1)
