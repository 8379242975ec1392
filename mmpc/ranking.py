"""Pick the best trajectory of every problem: lowest meta cost among the feasible ones."""

from __future__ import annotations

import math
from typing import NamedTuple, Optional

import torch

from mmpc.config import require_non_negative
from mmpc.problem import EGO_Y
from mmpc.result import SolveResult, Trajectories
from mmpc.solver.config import OptimizerConfig


class Selection(NamedTuple):
    """The chosen goal of each problem.

    Shapes:
        index: (E,) int64 goal index into the G goals.
        cost: (E,) meta cost of the chosen element.
        feasible: (E,) bool; False means no element of the problem was feasible and ``index`` is
            the least-infeasible one (smallest :func:`constraint_violation`), a fallback the
            caller should treat as unsafe.
    """

    index: torch.Tensor
    cost: torch.Tensor
    feasible: torch.Tensor


def constraint_violation(result: SolveResult, config: OptimizerConfig) -> torch.Tensor:
    """(E, G) dimensionless sum of how far each element is from feasible; 0 when feasible-ish.

    Obstacle penetration (1 - normalised distance), acceleration excess over a_max, the
    non-holonomic error over the tolerance and the heading excess, each normalised by its bound.
    Collision terms are weighted 10x: a fallback should rather break kinematics than collide.
    """
    penetration = (1.0 - result.min_obstacle_distance).clamp_min(0.0)
    acceleration = (result.max_acceleration - config.a_max).clamp_min(0.0) / config.a_max
    nonholonomic = (result.max_nonholonomic_error - config.nonholonomic_tolerance).clamp_min(0.0)
    max_heading = math.radians(config.max_heading_deg)
    heading = (result.max_heading_deviation - max_heading).clamp_min(0.0) / max_heading
    return 10.0 * penetration + acceleration + nonholonomic / max(config.v_max, 1.0) + heading


def lateral_move(trajectories: Trajectories, ego: torch.Tensor) -> torch.Tensor:
    """(E, G) how far each candidate ends from the ego's lateral position [m]: the preference
    that breaks ties between candidates of (nearly) equal meta cost towards the smaller lane move."""
    return (trajectories.y[..., -1] - ego[:, None, EGO_Y]).abs()


def lowest_feasible(
    cost: torch.Tensor,
    feasible: torch.Tensor,
    *,
    preference: Optional[torch.Tensor] = None,
    tie_tolerance: float = 0.0,
    tie_margin: float = 0.0,
) -> torch.Tensor:
    """(E,) index of the feasible candidate of lowest ``cost`` in every row (0 in rows with none).

    Args:
        cost: (E, G), lower is better; NaN counts as +inf.
        feasible: (E, G) bool.
        preference: (E, G) tie-break, lower is preferred: among the feasible candidates whose
            cost is within ``tie_tolerance * |lowest| + tie_margin`` of the lowest, the one of
            lowest preference wins (the first of equals). ``None``: no tie-break.
        tie_tolerance: relative width of the tie band [-] (0.01: within 1 % of the lowest).
        tie_margin: absolute width of the tie band, in the units of ``cost``.
    """
    if feasible.shape != cost.shape:
        raise ValueError(f"`feasible` must have shape {tuple(cost.shape)}; got {tuple(feasible.shape)}")
    inf = torch.full((), float("inf"), dtype=cost.dtype, device=cost.device)
    feasible_cost = torch.where(feasible, torch.nan_to_num(cost, nan=float("inf")), inf)
    if preference is None:
        return feasible_cost.argmin(dim=-1)
    if preference.shape != cost.shape:
        raise ValueError(f"`preference` must have shape {tuple(cost.shape)}; got {tuple(preference.shape)}")
    require_non_negative("", tie_tolerance=tie_tolerance, tie_margin=tie_margin)
    lowest = feasible_cost.amin(dim=-1, keepdim=True)
    tied = feasible & (feasible_cost <= lowest + tie_tolerance * lowest.abs() + tie_margin)
    return torch.where(tied, preference.to(cost.dtype), inf).argmin(dim=-1)


def select_best(
    result: SolveResult,
    cost: torch.Tensor,
    config: OptimizerConfig,
    *,
    violation: Optional[torch.Tensor] = None,
    preference: Optional[torch.Tensor] = None,
    tie_tolerance: float = 0.0,
    tie_margin: float = 0.0,
) -> Selection:
    """Best element of every problem: the feasible one with the lowest ``cost`` (ties broken by
    ``preference``, see :func:`lowest_feasible`); when a problem has none feasible, the one with
    the smallest violation (flagged).

    Args:
        result: the solve of E problems with G goals each.
        cost: (E, G) meta cost, lower is better; NaN counts as +inf.
        config: the optimizer's config (bounds for the violation measure).
        violation: (E, G) how far each element is from feasible; default
            :func:`constraint_violation` (a caller that adds constraints of its own adds their
            violation to it).
        preference, tie_tolerance, tie_margin: the tie-break of :func:`lowest_feasible`.
    """
    if cost.shape != result.feasible.shape:
        raise ValueError(f"`cost` must have shape {tuple(result.feasible.shape)}; got {tuple(cost.shape)}")
    if violation is None:
        violation = constraint_violation(result, config)
    elif violation.shape != cost.shape:
        raise ValueError(f"`violation` must have shape {tuple(cost.shape)}; got {tuple(violation.shape)}")
    best_feasible = lowest_feasible(
        cost, result.feasible, preference=preference, tie_tolerance=tie_tolerance, tie_margin=tie_margin
    )
    any_feasible = result.feasible.any(dim=-1)
    least_infeasible = violation.argmin(dim=-1)
    index = torch.where(any_feasible, best_feasible, least_infeasible)
    rows = torch.arange(cost.shape[0], device=cost.device)
    cost = torch.nan_to_num(cost, nan=float("inf"))
    return Selection(index=index, cost=cost[rows, index], feasible=any_feasible)
