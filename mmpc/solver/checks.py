"""Input checks of the solver: a problem batch and a warm start checked (types, shapes, devices,
values) and cast before a solve, and the placeholder put where a solve went non-finite."""

from __future__ import annotations

from typing import Optional

import torch

from mmpc.problem import EGO_FIELDS, EGO_V, ProblemBatch
from mmpc.result import WarmStart
from mmpc.solver.config import OptimizerConfig


def _check_tensor(name: str, value: object, ndim: int, shape_doc: str) -> torch.Tensor:
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"`{name}` must be a torch.Tensor of shape {shape_doc}; got {type(value).__name__}")
    if value.ndim != ndim:
        raise ValueError(f"`{name}` must have shape {shape_doc}; got {tuple(value.shape)}")
    return value


def validate_problem(
    problem: ProblemBatch, config: OptimizerConfig, dtype: torch.dtype, device: torch.device, values: bool = True
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, Optional[torch.Tensor]]:
    """Check shapes, dtypes, devices and (``values``: a host synchronisation) values; return (ego,
    goals, obstacles, mask, axes) cast to ``dtype``."""
    if not isinstance(problem, ProblemBatch):
        raise TypeError(f"`problem` must be a mmpc.ProblemBatch; got {type(problem).__name__}")
    n = config.num_steps
    ego = _check_tensor("ego", problem.ego, 2, f"(E, {len(EGO_FIELDS)})")
    goals = _check_tensor("goals", problem.goals, 3, "(E, G, 2)")
    obstacles = _check_tensor("obstacles", problem.obstacles, 4, f"(E, M, {n}, 2)")
    num_problems = ego.shape[0]
    if ego.shape[1] != len(EGO_FIELDS):
        raise ValueError(
            f"`ego` must have shape (E, {len(EGO_FIELDS)}) with fields {EGO_FIELDS}; got {tuple(ego.shape)}"
        )
    if num_problems == 0:
        raise ValueError(f"empty batch: `ego` must hold at least one problem; got shape {tuple(ego.shape)}")
    if goals.shape[0] != num_problems or goals.shape[2] != 2:
        raise ValueError(f"`goals` must have shape ({num_problems}, G, 2); got {tuple(goals.shape)}")
    if goals.shape[1] == 0:
        raise ValueError(f"empty batch: `goals` must hold at least one goal; got shape {tuple(goals.shape)}")
    if obstacles.shape[0] != num_problems or obstacles.shape[2] != n or obstacles.shape[3] != 2:
        raise ValueError(
            f"`obstacles` must have shape ({num_problems}, M, {n}, 2); got {tuple(obstacles.shape)}"
        )
    num_slots = obstacles.shape[1]
    if num_slots > config.max_obstacles:
        raise ValueError(
            f"`obstacles` has {num_slots} slots but the optimizer was built for at most "
            f"max_obstacles={config.max_obstacles}"
        )
    mask = problem.obstacle_mask
    if mask is None:
        mask = torch.ones(num_problems, num_slots, dtype=torch.bool, device=obstacles.device)
    mask = _check_tensor("obstacle_mask", mask, 2, f"({num_problems}, {num_slots})")
    if mask.dtype != torch.bool:
        raise TypeError(f"`obstacle_mask` must be a bool tensor; got dtype {mask.dtype}")
    if tuple(mask.shape) != (num_problems, num_slots):
        raise ValueError(f"`obstacle_mask` must have shape ({num_problems}, {num_slots}); got {tuple(mask.shape)}")
    axes = problem.obstacle_axes
    if axes is not None:
        axes = _check_tensor("obstacle_axes", axes, 3, f"({num_problems}, {num_slots}, 2)")
        if tuple(axes.shape) != (num_problems, num_slots, 2):
            raise ValueError(f"`obstacle_axes` must have shape ({num_problems}, {num_slots}, 2); got {tuple(axes.shape)}")
    floats = (("ego", ego), ("goals", goals), ("obstacles", obstacles)) + ((("obstacle_axes", axes),) if axes is not None else ())
    for name, tensor in floats:
        if not tensor.dtype.is_floating_point:
            raise TypeError(f"`{name}` must be a floating tensor; got dtype {tensor.dtype}")
    for name, tensor in floats + (("obstacle_mask", mask),):
        if tensor.device != device:
            raise ValueError(f"`{name}` is on {tensor.device} but the optimizer is on {device}; move it with .to()")
    if axes is not None:
        axes = axes.to(dtype)
    ego, goals, obstacles = (t.to(dtype) for t in (ego, goals, obstacles))
    if values:
        _check_values(ego, goals, obstacles, mask, axes)
    return ego, goals, obstacles, mask, axes


def _check_values(ego: torch.Tensor, goals: torch.Tensor, obstacles: torch.Tensor, mask: torch.Tensor,
                  axes: Optional[torch.Tensor]) -> None:
    """``ValueError`` naming the first kind of bad value found and where: non-finite or non-positive
    semi-axes of a present obstacle, NaN or inf in the ego state, the goals or a present obstacle, a
    negative ego speed."""
    if axes is not None:
        bad_axes = mask & ~((axes > 0) & axes.isfinite()).all(dim=2)
        if bool(bad_axes.any()):
            raise ValueError(f"`obstacle_axes` must be finite and > 0 m for present obstacles; got "
                             f"{axes[bad_axes][:4].tolist()} at (problem, slot) {bad_axes.nonzero()[:4].tolist()}")
    ego_finite = ego.isfinite().all(dim=1)
    goals_finite = goals.isfinite().all(dim=2)
    obstacles_finite = obstacles.isfinite().all(dim=3).all(dim=2) | ~mask
    negative_speed = ego[:, EGO_V] < 0
    checks = torch.stack(
        [~ego_finite.all(), ~goals_finite.all(), ~obstacles_finite.all(), negative_speed.any()]
    ).tolist()
    if checks[0]:
        rows = (~ego_finite).nonzero().flatten().tolist()
        raise ValueError(f"`ego` contains NaN or inf in problem(s) {rows}")
    if checks[1]:
        rows = (~goals_finite).nonzero().tolist()
        raise ValueError(f"`goals` contains NaN or inf at (problem, goal) {rows}")
    if checks[2]:
        rows = (~obstacles_finite).nonzero().tolist()
        raise ValueError(
            f"`obstacles` contains NaN or inf at present (problem, slot) {rows}; "
            "mark absent slots False in `obstacle_mask`"
        )
    if checks[3]:
        rows = negative_speed.nonzero().flatten().tolist()
        speeds = ego[negative_speed, EGO_V].tolist()
        raise ValueError(f"ego speed `v` must be >= 0 m/s; got {speeds} in problem(s) {rows}")


def validate_warm(warm: Optional[WarmStart], iterations: Optional[int], config: OptimizerConfig, batch: tuple[int, int],
                   dtype: torch.dtype, device: torch.device) -> tuple[Optional[WarmStart], int]:
    """A warm start checked against the (E, G) ``batch`` and cast to ``dtype``, and the first
    iteration it runs from (0 without one)."""
    if warm is None:
        if iterations is not None:
            raise ValueError(f"`warm_iterations` needs a `warm` start; got warm_iterations={iterations!r} without one")
        return None, 0
    if not isinstance(warm, WarmStart):
        raise TypeError(f"`warm` must be a mmpc.WarmStart (a result's `warm`); got {type(warm).__name__}")
    if isinstance(iterations, bool) or not isinstance(iterations, int) or not 1 <= iterations <= config.iterations:
        raise ValueError(f"`warm_iterations` must be an int in [1, {config.iterations}]; got {iterations!r}")
    order = config.order + 1
    expected = {"position": (*batch, 2, order), "multipliers": (*batch, 2, order), "heading_multipliers": (*batch, order)}
    fields = []
    for name, shape in expected.items():
        value = getattr(warm, name)
        if not isinstance(value, torch.Tensor) or tuple(value.shape) != shape:
            got = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
            raise ValueError(f"`warm.{name}` must have shape {shape} for this batch; got {got}")
        if value.device != device:
            raise ValueError(f"`warm.{name}` is on {value.device} but the optimizer is on {device}; move it with .to()")
        fields.append(value.to(dtype))  # problems with NaN or inf start cold (BatchOptimizer.forward)
    return WarmStart(*fields), config.iterations - iterations


def replace_nonfinite(
    finite: torch.Tensor,
    origin: torch.Tensor,  # (E, 2)
    fields: list[torch.Tensor],
    coefficients: torch.Tensor,
    norms: torch.Tensor,
    scalars: list[torch.Tensor],
) -> tuple[list[torch.Tensor], torch.Tensor, torch.Tensor, list[torch.Tensor]]:
    """Put a standing-still placeholder where an element went non-finite (it is flagged NUMERICAL)."""
    bad = ~finite[..., None]
    zero = torch.zeros((), dtype=coefficients.dtype, device=coefficients.device)
    inf = torch.full((), float("inf"), dtype=coefficients.dtype, device=coefficients.device)
    start = torch.nan_to_num(origin, nan=0.0, posinf=0.0, neginf=0.0)[:, None, None, :]
    placeholders = [start[..., 0], start[..., 1]] + [zero] * (len(fields) - 2)
    fields = [torch.where(bad, placeholder, field) for field, placeholder in zip(fields, placeholders)]
    coefficients = torch.where(bad[..., None], zero, coefficients)
    norms = torch.where(bad, inf, norms)
    bad = bad[..., 0]
    scalars = [torch.where(bad, inf, s) for s in scalars]
    scalars[0] = torch.where(bad, zero, scalars[0])  # no claimed clearance
    return fields, coefficients, norms, scalars
