"""Goal samplers: where, at the end of the horizon, each batch element should arrive.

A goal sampler is any callable ``sampler(ego, road) -> goals`` with ``ego`` (E, 6) (see
:data:`mmpc.EGO_FIELDS`) and ``goals`` (E, G, 2) positions [m]; the first two below are the paper's.

The samplers that place goals by speed take the planning horizon as a required keyword: the
horizon of the optimizer that solves for their goals (``OptimizerConfig.horizon``; e.g.
``CruiseGoals(horizon=optimizer.config.horizon)``), which :func:`mmpc.scenario.build_mpc` passes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Protocol

import torch

from mmpc.config import require_int
from mmpc.problem import EGO_X, EGO_Y
from mmpc.road import Road


class GoalSampler(Protocol):
    def __call__(self, ego: torch.Tensor, road: Road) -> torch.Tensor:
        """Goals (E, G, 2) [m] for ego states (E, 6) on ``road``."""
        ...


@dataclass(frozen=True)
class CruiseGoals:
    """Cruise driving: ``num_goals`` goals at ``x0 + v_cruise * horizon``, spread evenly across
    the road from the leftmost to the rightmost lane centre (the authors: 11 goals, so goals sit
    on lane centres and on lane boundaries of a 6-lane road).

    Attributes:
        v_cruise: cruise speed [m/s].
        horizon: planning horizon t_f [s], the optimizer's (keyword, required).
        num_goals: number of goals G.
    """

    v_cruise: float = 15.0
    horizon: float = field(kw_only=True)
    num_goals: int = 11

    def __post_init__(self) -> None:
        require_int("", low=1, num_goals=self.num_goals)
        if not self.v_cruise > 0 or not self.horizon > 0:
            raise ValueError(f"`v_cruise` and `horizon` must be > 0; got {self.v_cruise}, {self.horizon}")

    def __call__(self, ego: torch.Tensor, road: Road) -> torch.Tensor:
        lateral = torch.linspace(0.0, road.right_lane_y, self.num_goals, dtype=ego.dtype, device=ego.device)
        if self.num_goals == 1:
            lateral = torch.zeros(1, dtype=ego.dtype, device=ego.device)
        x = ego[:, EGO_X, None] + self.v_cruise * self.horizon
        return torch.stack(torch.broadcast_tensors(x, lateral[None]), dim=-1)


@dataclass(frozen=True)
class HighSpeedGoals:
    """High speed near the right lane: ``round(right_lane_fraction * num_goals)`` goals on the
    right lane at distances evenly spaced in ``right_lane_distances``; the rest spread across the
    other lanes at ``other_distance`` ahead (the authors' layout).

    Attributes:
        num_goals: number of goals G (at least 2).
        right_lane_fraction: share of goals on the right lane, in (0, 1).
        right_lane_distances: (nearest, farthest) right-lane goal distance ahead [m].
        other_distance: distance ahead of the goals on the other lanes [m].
    """

    num_goals: int = 11
    right_lane_fraction: float = 0.6
    right_lane_distances: tuple[float, float] = (150.0, 175.0)
    other_distance: float = 160.0

    def __post_init__(self) -> None:
        require_int("", low=2, num_goals=self.num_goals)
        if not 0 < self.right_lane_fraction < 1:
            raise ValueError(f"`right_lane_fraction` must be in (0, 1); got {self.right_lane_fraction}")
        near, far = self.right_lane_distances
        if not 0 < near <= far:
            raise ValueError(f"`right_lane_distances` must satisfy 0 < near <= far; got {self.right_lane_distances}")
        if not self.other_distance > 0:
            raise ValueError(f"`other_distance` must be > 0 m; got {self.other_distance}")

    def __call__(self, ego: torch.Tensor, road: Road) -> torch.Tensor:
        kw = dict(dtype=ego.dtype, device=ego.device)
        n_right = min(max(round(self.right_lane_fraction * self.num_goals), 1), self.num_goals - 1)
        n_other = self.num_goals - n_right
        near, far = self.right_lane_distances
        right_x = torch.linspace(near, far, n_right, **kw)
        right_y = torch.full((n_right,), road.right_lane_y, **kw)
        other_lanes = road.lane_centers(**kw)[:-1] if road.num_lanes > 1 else road.lane_centers(**kw)
        other_y = other_lanes[torch.arange(n_other, device=ego.device) % other_lanes.numel()]
        other_x = torch.full((n_other,), self.other_distance, **kw)
        offsets = torch.stack([torch.cat([right_x, other_x]), torch.cat([right_y, other_y])], dim=-1)
        goals = offsets[None].repeat(ego.shape[0], 1, 1)
        goals[..., 0] += ego[:, EGO_X, None]
        return goals


@dataclass(frozen=True)
class NearLaneGoals:
    """Goals of ``base`` plus goals on the lanes around the ego at several average speeds.

    The paper's goals all lie a fixed distance ahead (``v_ref * horizon``, or 150-175 m for high
    speed, where the authors' layout also leaves a lane without goals). Behind a slower car with
    the neighbouring lanes occupied none of them is reachable, and the MPC could only fall back.
    These extra goals sit on the centres of the ``2 lanes_around + 1`` lanes nearest the ego's
    lane: its lane and ``lanes_around`` either side, the window shifted to stay on the road (on
    an edge lane: the edge lane and the next ``2 lanes_around`` inwards, so no goal repeats), at
    ``x0 + s * horizon`` for every average speed ``s`` in ``speeds``. The end speed is free, so a
    goal short of a leader's predicted position yields a car-following trajectory; the meta cost
    still prefers the fastest feasible goal.

    Attributes:
        base: the sampler whose goals come first (G0 goals).
        speeds: average speeds of the extra goals [m/s].
        horizon: planning horizon t_f [s], the optimizer's (keyword, required).
        lanes_around: lanes either side of the ego's lane that also get the extra goals;
            ``None``: every lane of the road.

    Shapes:
        returns (E, G0 + len(speeds) * L, 2) with L = min(2 lanes_around + 1, lane count), or
        the lane count when ``lanes_around`` is ``None``.
    """

    base: GoalSampler
    speeds: tuple[float, ...] = (3.0, 6.0, 9.0, 12.0)
    horizon: float = field(kw_only=True)
    lanes_around: Optional[int] = 1

    def __post_init__(self) -> None:
        if not self.speeds or any(not s > 0 for s in self.speeds):
            raise ValueError(f"`speeds` must be a non-empty sequence of speeds > 0 m/s; got {self.speeds!r}")
        if not self.horizon > 0:
            raise ValueError(f"`horizon` must be > 0 s; got {self.horizon}")
        if self.lanes_around is not None:
            require_int("", low=0, lanes_around=self.lanes_around)

    def __call__(self, ego: torch.Tensor, road: Road) -> torch.Tensor:
        kw = dict(dtype=ego.dtype, device=ego.device)
        if self.lanes_around is None:
            lane_y = road.lane_centers(**kw).expand(ego.shape[0], -1)  # (E, L)
        else:
            lane_y = road.lanes_around(ego[:, EGO_Y], self.lanes_around).to(ego.dtype) * road.lane_width  # (E, L)
        ahead = torch.tensor(self.speeds, **kw) * self.horizon  # (S,)
        x = ego[:, EGO_X, None, None] + ahead[None, None, :]  # (E, 1, S)
        y = lane_y[:, :, None]  # (E, L, 1)
        extra = torch.stack(torch.broadcast_tensors(x, y), dim=-1).flatten(1, 2)  # (E, L S, 2)
        return torch.cat([self.base(ego, road), extra], dim=1)
