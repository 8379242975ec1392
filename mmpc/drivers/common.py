"""Pieces the baselines share with the multi-modal MPC: the obstacle set, the ranking by the
scenario's meta cost, and the command extraction with its fallback.

Every baseline plans against the same obstacles as ours (the M vehicles nearest in
ellipse-normalised distance within the lookahead, :meth:`mmpc.MPC.nearest_obstacles`, predicted
by :meth:`mmpc.MPC.predict`),
ranks its candidates with the same meta cost and tie-break, and turns the chosen plan into a command exactly as
:class:`mmpc.MPC` does (tangential acceleration and heading rate averaged over the command
window; ``steering = atan(L psidot / v)``; the lane-keeping brake where nothing is usable).
"""

from __future__ import annotations

import time
from typing import NamedTuple, Optional

import torch

from mmpc.drivers.base import Candidates, Decision, Observation
from mmpc.mpc import MPC
from mmpc.ranking import lowest_feasible
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
    """The M obstacles of ``mpc``'s settings (:meth:`mmpc.MPC.nearest_obstacles`) predicted at ``times``.

    Returns:
        (E, M, T, 2) predicted centres [m] and (E, M) mask of present slots.
    """
    states, present = mpc.nearest_obstacles(ego, vehicles, mask)
    return mpc.predict(states, times), present


def rank(mpc: MPC, ego: torch.Tensor, trajectories: Trajectories, cost: torch.Tensor, feasible: torch.Tensor) -> Ranked:
    """The lowest ``cost`` (E, C) among the ``feasible`` (E, C) candidates of every row, ties
    broken as :class:`mmpc.MPC` breaks them (:meth:`mmpc.MPC.tie_break`)."""
    index = lowest_feasible(cost, feasible, **mpc.tie_break(trajectories, ego))
    any_feasible = feasible.any(dim=1)
    rows = torch.arange(cost.shape[0])
    chosen = torch.where(any_feasible, cost[rows, index], torch.full_like(cost[:, 0], float("nan")))
    return Ranked(index, chosen, any_feasible)


def checked_ego(observation: Observation, dtype: torch.dtype) -> torch.Tensor:
    """The observation's ego states as ``dtype``, refused unless finite and (E, 6)."""
    ego = observation.ego.to(dtype)
    if ego.ndim != 2 or ego.shape[1] != 6 or not torch.isfinite(ego).all():
        raise ValueError(f"`ego` must be a finite (E, 6) tensor; got shape {tuple(ego.shape)}")
    return ego


def ranked_decision(
    mpc: MPC,
    ego: torch.Tensor,
    trajectories: Trajectories,
    feasible: torch.Tensor,
    start: float,
    goals: Optional[torch.Tensor] = None,
    obstacles: Optional[tuple[torch.Tensor, torch.Tensor]] = None,
) -> Decision:
    """Rank C candidates per problem by ``mpc``'s meta cost, execute the best feasible one (where
    none is, the MPC's fallback: a lane-keeping brake, at least as hard as a conflict ahead needs),
    and report it as a :class:`mmpc.drivers.Decision`.

    Args:
        mpc: the scenario's MPC (meta cost, road, command extraction, output dtype).
        ego: (E, 6) current states.
        trajectories: the candidates, every field (E, C, N).
        feasible: (E, C) bool.
        start: ``time.perf_counter()`` at the start of the decision.
        goals: (E, C, 2) the candidates' goals [m], if they have goals.
        obstacles: ``(centres (E, M, N, 2), mask (E, M))`` predicted at ``trajectories.times``,
            for the fallback's braking (:meth:`mmpc.MPC.command`).
    """
    dtype = mpc.optimizer.dtype
    cost = mpc.meta_cost(trajectories, mpc.road)
    ranked = rank(mpc, ego, trajectories, cost, feasible)
    centres, mask = obstacles if obstacles is not None else (None, None)
    acceleration, steering, _ = mpc.command(ego, trajectories.select(ranked.index), ranked.feasible, obstacles=centres, mask=mask)
    elapsed_ms = (time.perf_counter() - start) * 1e3
    return Decision(
        acceleration=acceleration.to(dtype),
        steering=steering.to(dtype),
        solve_ms=elapsed_ms,
        goal_index=torch.where(ranked.feasible, ranked.index, torch.full_like(ranked.index, -1)),
        feasible_goals=feasible.sum(dim=1),
        fallback=~ranked.feasible,
        plan_cost=ranked.cost.to(dtype),
        candidates=Candidates(
            xy=torch.stack([trajectories.x, trajectories.y], dim=-1).to(dtype), feasible=feasible,
            best=ranked.index, goals=None if goals is None else goals.to(dtype),
        ),
    )


def with_goal_axis(trajectory: Trajectories) -> Trajectories:
    """Fields (E, N) -> (E, 1, N): one plan per problem seen as a batch of one goal (for meta costs)."""
    return Trajectories(trajectory.times, *(field[:, None] for field in trajectory[1:]))
