"""The batch non-holonomic trajectory optimizer (alternating minimisation, Adajania et al. 2022).

One iteration, for every (problem, goal) element at once:

1. position QP (x and y): one cached KKT operator times ``[c, u, lambda, b]``;
2. heading QP: pull ``psi = P c_psi`` towards ``atan2(ydot, xdot)``; cached operator;
   ``lambda_psi -= rho P^T (psi - atan2(ydot, xdot))`` (the sign that converges; the paper's
   printed update has it reversed);
3. speed: ``v = clip((xdot, ydot) . (cos psi, sin psi), v_min, v_max)`` — the projection on the
   heading, which minimises the non-holonomic penalty for fixed psi (the paper uses the norm);
4. obstacles: every trajectory point is projected radially out of every ellipse — the closed
   forms of alpha and d = max(1, r) without trigonometry;
5. acceleration: projected onto the disc of radius a_max — the closed forms of alpha_a, d_a;
6. ``lambda -= rho F^T (F c - g)``, with the residual mapped to coefficient space once and
   reused by the next position QP.

There is no Python branching on tensor values and no host synchronisation inside the loop.
"""

from __future__ import annotations

import logging
from typing import NamedTuple, Optional

import torch
from torch import nn

from mmpc.basis import bernstein_basis
from mmpc.config import OptimizerConfig
from mmpc.operators import build_operators
from mmpc.problem import EGO_A, EGO_FIELDS, EGO_PSI, EGO_PSIDOT, EGO_V, EGO_X, EGO_Y, ProblemBatch
from mmpc.result import SolveResult, Status, Trajectories

logger = logging.getLogger(__name__)

#: Where absent obstacle slots are parked, relative to the ego [m]: far enough that no
#: trajectory point is ever inside their ellipse, small enough to square in float32.
_PARKED_DISTANCE = 1.0e5
_EPS_SQUARED = 1.0e-12


class _Residuals(NamedTuple):
    """Constraint residuals of the current iterate. Shapes (E, G, 2, N) unless noted."""

    mapped: torch.Tensor  # (E, G, 2, K) F^T (F c - g)
    obstacle_push: torch.Tensor  # sum over obstacles of (projection - point) [m]
    acceleration: torch.Tensor  # acceleration minus its projection on the a_max disc [m/s^2]
    velocity: torch.Tensor  # (xdot, ydot) - v (cos psi, sin psi) [m/s]
    speed: torch.Tensor  # (E, G, N) v [m/s]


class _Prepared(NamedTuple):
    """Validated inputs in the ego-relative frame, in the module's dtype."""

    origin: torch.Tensor  # (E, 1, 2, 1) ego start position [m]
    b_position: torch.Tensor  # (E, G, 2, n_eq) boundary values of x and y
    b_heading: torch.Tensor  # (E, G, 4) boundary values of psi
    obstacles: torch.Tensor  # (E, M, 2, N) obstacle centres / semi-axes, absent slots parked
    mask: torch.Tensor  # (E, M) bool
    counts: torch.Tensor  # (E,) int64 number of present obstacles
    uniform_count: Optional[int]  # the count when it is the same for every problem
    goal_ahead: torch.Tensor  # (E, G) bool


class BatchOptimizer(nn.Module):
    """Batch non-holonomic trajectory optimizer with every constant matrix cached as a buffer.

    Solves, for each of E problems and each of its G goals, ::

        min  sum_t xddot^2 + yddot^2 + psiddot^2   (weighted)
        s.t. xdot = v cos psi, ydot = v sin psi, v_min <= v <= v_max, |(xddot, yddot)| <= a_max,
             outside every obstacle ellipse (a, b) at every sample, boundary conditions,

    in ``config.iterations`` alternating-minimisation iterations from a cold start.

    Args:
        config: optimizer settings; defaults are the paper authors' values.
        dtype: floating dtype of the buffers and of every computation (inputs are cast once).
        device: where the buffers live; inputs must already be there.

    Shapes:
        see :class:`mmpc.ProblemBatch` (inputs) and :class:`mmpc.SolveResult` (outputs).

    Example:
        >>> import torch, mmpc
        >>> opt = mmpc.BatchOptimizer()
        >>> ego = mmpc.ego_state(0.0, 8.0, 0.0, 14.0)
        >>> goals = torch.tensor([[[120.0, 4.0], [120.0, 8.0]]])
        >>> obstacles = torch.zeros(1, 0, opt.config.num_steps, 2)
        >>> result = opt(mmpc.ProblemBatch(ego, goals, obstacles))
        >>> result.trajectories.x.shape, bool(result.feasible.all())
        (torch.Size([1, 2, 100]), True)
    """

    def __init__(
        self,
        config: Optional[OptimizerConfig] = None,
        *,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        if not dtype.is_floating_point:
            raise TypeError(f"`dtype` must be a floating dtype; got {dtype}")
        self.config = config if config is not None else OptimizerConfig()
        basis = bernstein_basis(self.config.order, self.config.num_steps, self.config.horizon)
        operators = build_operators(basis, self.config)
        for name, value in operators._asdict().items():
            self.register_buffer(name, value.to(dtype=dtype, device=device), persistent=False)
        self.register_buffer("times", basis.times.to(dtype=dtype, device=device), persistent=False)
        semi_axes = torch.tensor(
            [[self.config.ellipse_a], [self.config.ellipse_b]], dtype=dtype, device=device
        )
        self.register_buffer("semi_axes", semi_axes, persistent=False)
        self._rho = self.config.rho_schedule()

    @property
    def dtype(self) -> torch.dtype:
        return self.samples.dtype

    @property
    def device(self) -> torch.device:
        return self.samples.device

    @property
    def num_coefficients(self) -> int:
        return self.config.order + 1

    def forward(self, problem: ProblemBatch, *, history: bool = False) -> SolveResult:
        """Solve every (problem, goal) element of ``problem``.

        Args:
            problem: the batch (see :class:`mmpc.ProblemBatch` for shapes and units).
            history: also return the residual norms after every iteration.

        Returns:
            A :class:`mmpc.SolveResult` with leading dims (E, G).

        Raises:
            TypeError: a non-tensor or non-floating input, or a non-bool mask.
            ValueError: a wrong shape or device, an empty batch, too many obstacle slots,
                NaN/inf in the ego state, the goals or a present obstacle, a negative speed.
        """
        prepared = self._prepare(problem)
        c = prepared.b_position @ self.position_init
        kinematics = self._kinematics(c)
        psi = torch.atan2(kinematics[2][..., 1, :], kinematics[2][..., 0, :])
        residuals = self._residuals(*kinematics, psi, prepared.obstacles)
        multipliers = torch.zeros_like(c)
        multipliers_psi = torch.zeros_like(prepared.b_heading[..., :1]).expand(
            *prepared.b_heading.shape[:-1], self.num_coefficients
        )
        records = []
        for k, rho in enumerate(self._rho):
            c = self._position_step(k, c, residuals.mapped, multipliers, prepared)
            kinematics = self._kinematics(c)
            psi_target = torch.atan2(kinematics[2][..., 1, :], kinematics[2][..., 0, :])
            stacked = torch.cat([psi_target, multipliers_psi, prepared.b_heading], dim=-1)
            c_psi = stacked @ self.heading[k]
            psi = c_psi @ self.heading_basis
            multipliers_psi = multipliers_psi - rho * ((psi - psi_target) @ self.heading_gather)
            residuals = self._residuals(*kinematics, psi, prepared.obstacles)
            multipliers = multipliers - rho * residuals.mapped
            if history:
                records.append(self._residual_norms(residuals, kinematics[0], prepared.obstacles))
        return self._finish(prepared, c, c_psi, kinematics, residuals, records if history else None)

    # ----------------------------------------------------------------------------- iteration

    def _position_step(
        self,
        k: int,
        c: torch.Tensor,
        mapped: torch.Tensor,
        multipliers: torch.Tensor,
        prepared: _Prepared,
    ) -> torch.Tensor:
        """x, y QP of iteration k: (E, G, 2, K) coefficients."""
        stacked = torch.cat([c, mapped, multipliers, prepared.b_position], dim=-1)
        if prepared.uniform_count is not None:
            return stacked @ self.position[k, prepared.uniform_count]
        operator = self.position[k].index_select(0, prepared.counts)  # (E, D, K)
        return stacked @ operator[:, None]

    def _kinematics(self, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Position, acceleration and velocity samples, each (E, G, 2, N), relative to the start."""
        samples = c @ self.samples
        n = self.config.num_steps
        return samples[..., :n], samples[..., n : 2 * n], samples[..., 2 * n :]

    def _residuals(
        self,
        position: torch.Tensor,
        acceleration: torch.Tensor,
        velocity: torch.Tensor,
        psi: torch.Tensor,
        obstacles: torch.Tensor,
    ) -> _Residuals:
        """Closed-form speed, obstacle and acceleration steps and the residual F c - g."""
        cfg = self.config
        heading = torch.stack([torch.cos(psi), torch.sin(psi)], dim=-2)  # (E, G, 2, N)
        speed = (velocity * heading).sum(dim=-2).clamp(cfg.v_min, cfg.v_max)
        velocity_residual = velocity - speed.unsqueeze(-2) * heading

        norm_squared = acceleration.square().sum(dim=-2, keepdim=True).clamp_min(_EPS_SQUARED)
        excess = (1.0 - cfg.a_max * norm_squared.rsqrt()).clamp_min(0.0)
        acceleration_residual = acceleration * excess

        offset = self._obstacle_offsets(position, obstacles)
        distance_squared = offset.square().sum(dim=-2, keepdim=True).clamp_min(_EPS_SQUARED)
        outward = (distance_squared.rsqrt() - 1.0).clamp_min(0.0)
        push = (offset * outward).sum(dim=2) * self.semi_axes

        stacked = torch.cat([-push, acceleration_residual, velocity_residual], dim=-1)
        return _Residuals(
            mapped=stacked @ self.gather,
            obstacle_push=push,
            acceleration=acceleration_residual,
            velocity=velocity_residual,
            speed=speed,
        )

    def _obstacle_offsets(self, position: torch.Tensor, obstacles: torch.Tensor) -> torch.Tensor:
        """(E, G, M, 2, N) offsets from each obstacle in ellipse-normalised units."""
        return (position / self.semi_axes).unsqueeze(2) - obstacles.unsqueeze(1)

    def _residual_norms(
        self, residuals: _Residuals, position: torch.Tensor, obstacles: torch.Tensor
    ) -> torch.Tensor:
        """(E, G, 3) L2 norms of the obstacle, acceleration and non-holonomic residuals."""
        offset = self._obstacle_offsets(position, obstacles)
        distance = offset.square().sum(dim=-2, keepdim=True).clamp_min(_EPS_SQUARED).sqrt()
        # Per obstacle and sample: |point - projection| = |offset| (1/r - 1)_+ in metres.
        gap = offset * (1.0 / distance - 1.0).clamp_min(0.0) * self.semi_axes.unsqueeze(0)
        return torch.stack(
            [
                gap.square().sum(dim=(2, 3, 4)).sqrt(),
                residuals.acceleration.square().sum(dim=(-2, -1)).sqrt(),
                residuals.velocity.square().sum(dim=(-2, -1)).sqrt(),
            ],
            dim=-1,
        )

    # ----------------------------------------------------------------------------- outputs

    def _finish(
        self,
        prepared: _Prepared,
        c: torch.Tensor,
        c_psi: torch.Tensor,
        kinematics: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
        residuals: _Residuals,
        records: Optional[list[torch.Tensor]],
    ) -> SolveResult:
        cfg = self.config
        position, acceleration, velocity = kinematics
        psi = c_psi @ self.heading_basis
        psidot = c_psi @ self.heading_rate_basis
        speed = residuals.speed

        norms = self._residual_norms(residuals, position, prepared.obstacles)
        offset = self._obstacle_offsets(position, prepared.obstacles)
        distance_squared = offset.square().sum(dim=-2)  # (E, G, M, N)
        present = prepared.mask[:, None, :, None]
        inf = torch.full((), float("inf"), dtype=self.dtype, device=self.device)
        distance_squared = torch.where(present, distance_squared, inf)
        # An always-absent extra slot keeps the minimum defined (+inf) when M = 0.
        distance_squared = torch.cat([distance_squared, inf.expand_as(distance_squared[:, :, :1])], 2)
        min_distance = distance_squared.flatten(2).amin(dim=-1).sqrt()
        start_distance = distance_squared[..., 0].amin(dim=-1)

        acceleration_norm = acceleration.square().sum(dim=-2).sqrt()
        nonholonomic_error = residuals.velocity.square().sum(dim=-2).sqrt()
        path_speed = velocity.square().sum(dim=-2).sqrt()
        heading_deviation = psi.abs().amax(dim=-1)
        max_acceleration = acceleration_norm.amax(dim=-1)
        max_nonholonomic = nonholonomic_error.amax(dim=-1)

        max_heading = torch.deg2rad(torch.tensor(cfg.max_heading_deg, dtype=torch.float64)).item()
        bits = [
            (min_distance < 1.0 - cfg.obstacle_tolerance, Status.OBSTACLE),
            (max_acceleration > cfg.a_max + cfg.acceleration_tolerance, Status.ACCELERATION),
            (max_nonholonomic > cfg.nonholonomic_tolerance, Status.NONHOLONOMIC),
            (heading_deviation > max_heading, Status.HEADING),
            (
                (path_speed.amax(dim=-1) > cfg.v_max + cfg.speed_tolerance)
                | (path_speed.amin(dim=-1) < cfg.v_min - cfg.speed_tolerance),
                Status.SPEED,
            ),
            (start_distance < 1.0, Status.START_IN_COLLISION),
            (~prepared.goal_ahead, Status.GOAL_BEHIND),
        ]
        status = torch.zeros(c.shape[:2], dtype=torch.int32, device=self.device)
        for condition, flag in bits:
            status = status | condition.to(torch.int32) * int(flag)

        origin = prepared.origin
        fields = [
            position[..., 0, :] + origin[..., 0, :],
            position[..., 1, :] + origin[..., 1, :],
            psi,
            speed,
            velocity[..., 0, :],
            velocity[..., 1, :],
            acceleration[..., 0, :],
            acceleration[..., 1, :],
            psidot,
        ]
        coefficients = torch.cat([c, c_psi.unsqueeze(-2)], dim=-2)
        finite = torch.stack([f.isfinite().all(dim=-1) for f in fields]).all(dim=0)
        finite = finite & coefficients.isfinite().flatten(2).all(dim=-1)
        status = status | (~finite).to(torch.int32) * int(Status.NUMERICAL)
        fields, coefficients, norms, scalars = _replace_nonfinite(
            finite,
            origin,
            fields,
            coefficients,
            norms,
            [min_distance, heading_deviation, max_acceleration, max_nonholonomic],
        )
        history = None
        if records is not None:
            history = torch.nan_to_num(torch.stack(records), nan=float("inf"))
        return SolveResult(
            trajectories=Trajectories(self.times, *fields),
            coefficients=coefficients,
            residual_obstacle=norms[..., 0],
            residual_acceleration=norms[..., 1],
            residual_nonholonomic=norms[..., 2],
            min_obstacle_distance=scalars[0],
            max_heading_deviation=scalars[1],
            max_acceleration=scalars[2],
            max_nonholonomic_error=scalars[3],
            status=status,
            feasible=status == 0,
            history=history,
        )

    # ----------------------------------------------------------------------------- inputs

    def _prepare(self, problem: ProblemBatch) -> _Prepared:
        ego, goals, obstacles, mask = _validate(problem, self.config, self.dtype, self.device)
        cfg = self.config
        origin = ego[:, None, EGO_X : EGO_Y + 1, None]  # (E, 1, 2, 1)
        psi0, v0 = ego[:, EGO_PSI], ego[:, EGO_V]
        a0, psidot0 = ego[:, EGO_A], ego[:, EGO_PSIDOT]
        cos0, sin0 = torch.cos(psi0), torch.sin(psi0)
        relative_goals = goals - origin[..., 0]  # (E, G, 2)
        num_goals = goals.shape[1]

        start_velocity = torch.stack([v0 * cos0, v0 * sin0], dim=-1)  # (E, 2)
        columns = [torch.zeros_like(start_velocity), start_velocity]
        if cfg.start_acceleration:
            columns.append(
                torch.stack(
                    [a0 * cos0 - v0 * psidot0 * sin0, a0 * sin0 + v0 * psidot0 * cos0], dim=-1
                )
            )
        start = torch.stack(columns, dim=-1)  # (E, 2, n_start)
        start = start[:, None].expand(-1, num_goals, -1, -1)
        b_position = torch.cat([start, relative_goals.unsqueeze(-1)], dim=-1)

        zeros = torch.zeros_like(psi0)
        b_heading = torch.stack([psi0, psidot0, zeros, zeros], dim=-1)[:, None]
        b_heading = b_heading.expand(-1, num_goals, -1)

        relative = obstacles - origin[:, 0, :, 0][:, None, None, :]  # (E, M, N, 2)
        parked = torch.full_like(relative, _PARKED_DISTANCE)
        relative = torch.where(mask[:, :, None, None], relative, parked)
        scaled = relative.transpose(-1, -2) / self.semi_axes  # (E, M, 2, N)

        counts = mask.sum(dim=1)
        count_values = counts.unique()
        uniform = int(count_values[0]) if count_values.numel() == 1 else None
        return _Prepared(
            origin=origin,
            b_position=b_position,
            b_heading=b_heading,
            obstacles=scaled,
            mask=mask,
            counts=counts,
            uniform_count=uniform,
            goal_ahead=relative_goals[..., 0] > 0,
        )


def _replace_nonfinite(
    finite: torch.Tensor,
    origin: torch.Tensor,
    fields: list[torch.Tensor],
    coefficients: torch.Tensor,
    norms: torch.Tensor,
    scalars: list[torch.Tensor],
) -> tuple[list[torch.Tensor], torch.Tensor, torch.Tensor, list[torch.Tensor]]:
    """Put a standing-still placeholder where an element went non-finite (it is flagged NUMERICAL)."""
    bad = ~finite
    zero = torch.zeros((), dtype=coefficients.dtype, device=coefficients.device)
    inf = torch.full((), float("inf"), dtype=coefficients.dtype, device=coefficients.device)
    start_x = torch.nan_to_num(origin[..., 0, :], nan=0.0, posinf=0.0, neginf=0.0)
    start_y = torch.nan_to_num(origin[..., 1, :], nan=0.0, posinf=0.0, neginf=0.0)
    placeholders = [start_x, start_y] + [zero] * (len(fields) - 2)
    fields = [
        torch.where(bad[..., None], placeholder, field)
        for field, placeholder in zip(fields, placeholders)
    ]
    coefficients = torch.where(bad[..., None, None], zero, coefficients)
    norms = torch.where(bad[..., None], inf, norms)
    scalars = [torch.where(bad, inf, s) for s in scalars]
    scalars[0] = torch.where(bad, zero, scalars[0])  # no claimed clearance
    return fields, coefficients, norms, scalars


def _check_tensor(name: str, value: object, ndim: int, shape_doc: str) -> torch.Tensor:
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"`{name}` must be a torch.Tensor of shape {shape_doc}; got {type(value).__name__}")
    if value.ndim != ndim:
        raise ValueError(f"`{name}` must have shape {shape_doc}; got {tuple(value.shape)}")
    return value


def _validate(
    problem: ProblemBatch, config: OptimizerConfig, dtype: torch.dtype, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Check shapes, dtypes, devices and values; return (ego, goals, obstacles, mask) cast to ``dtype``."""
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
    for name, tensor in (("ego", ego), ("goals", goals), ("obstacles", obstacles)):
        if not tensor.dtype.is_floating_point:
            raise TypeError(f"`{name}` must be a floating tensor; got dtype {tensor.dtype}")
    for name, tensor in (("ego", ego), ("goals", goals), ("obstacles", obstacles), ("obstacle_mask", mask)):
        if tensor.device != device:
            raise ValueError(f"`{name}` is on {tensor.device} but the optimizer is on {device}; move it with .to()")

    ego, goals, obstacles = (t.to(dtype) for t in (ego, goals, obstacles))
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
    return ego, goals, obstacles, mask
