"""Pieces the baselines share with the multi-modal MPC: the obstacle set, the ranking by the
scenario's meta cost, and the command extraction with its fallback.

Every baseline plans against the same obstacles as ours (the M nearest vehicles in
ellipse-normalised distance, constant-velocity prediction; :func:`mmpc.mpc.nearest_obstacles`),
ranks its candidates with the same meta cost, and turns the chosen plan into a command exactly as
:class:`mmpc.MPC` does (tangential acceleration and heading rate averaged over the command
window; ``steering = atan(L psidot / v)``; the lane-keeping brake where nothing is usable).
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from mmpc.mpc import MPC, nearest_obstacles
from mmpc.problem import EGO_V, predict_constant_velocity
from mmpc.result import Trajectories


class Ranked(NamedTuple):
    """The chosen candidate of each of E problems.

    Shapes:
        index: (E,) long, the lowest-cost feasible candidate (0 where none is feasible).
        cost: (E,) its meta cost (NaN where none is feasible).
        feasible: (E,) bool, some candidate was feasible.
    """

    index: torch.Tensor
    cost: torch.Tensor
    feasible: torch.Tensor


def obstacles_for(mpc: MPC, ego: torch.Tensor, vehicles: torch.Tensor, mask, times: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The M nearest vehicles of ``mpc``'s settings predicted at ``times``.

    Returns:
        (E, M, T, 2) predicted centres [m] and (E, M) mask of present slots.
    """
    cfg = mpc.optimizer.config
    states, present = nearest_obstacles(
        ego, vehicles, mask, mpc.config.num_obstacles, (cfg.ellipse_a, cfg.ellipse_b), mpc.config.ignore_behind
    )
    return predict_constant_velocity(states, times.to(states.dtype)), present


def rank(cost: torch.Tensor, feasible: torch.Tensor) -> Ranked:
    """Lowest ``cost`` (E, C) among the ``feasible`` (E, C) candidates of every row."""
    masked = torch.where(feasible, torch.nan_to_num(cost, nan=float("inf")), torch.full_like(cost, float("inf")))
    index = masked.argmin(dim=1)
    any_feasible = feasible.any(dim=1)
    rows = torch.arange(cost.shape[0])
    chosen = torch.where(any_feasible, cost[rows, index], torch.full_like(cost[:, 0], float("nan")))
    return Ranked(index, chosen, any_feasible)


def commands(mpc: MPC, ego: torch.Tensor, trajectory: Trajectories, usable: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(acceleration (E,) [m/s^2], steering (E,) [rad]) from the chosen plans, as :meth:`mmpc.MPC.plan`
    extracts them; rows where ``usable`` is False get the MPC's lane-keeping brake.

    Args:
        mpc: the scenario's MPC (its command window, wheelbase, steering limit and fallback).
        ego: (E, 6) current states.
        trajectory: the chosen plans, every field (E, N), at ``trajectory.times``.
        usable: (E,) bool.
    """
    acceleration, heading_rate = mpc._command(trajectory)
    acceleration, heading_rate = mpc._fallback(ego, usable, acceleration, heading_rate)
    speed = ego[:, EGO_V].clamp_min(1.0)
    steering = torch.atan(mpc.config.wheelbase * heading_rate / speed)
    return acceleration, steering.clamp(-mpc.config.max_steering, mpc.config.max_steering)


def with_goal_axis(trajectory: Trajectories) -> Trajectories:
    """Fields (E, N) -> (E, 1, N): one plan per problem seen as a batch of one goal (for meta costs)."""
    return Trajectories(trajectory.times, *(field[:, None] for field in trajectory[1:]))
