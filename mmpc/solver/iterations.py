"""The alternating-minimisation iterations (Adajania et al. 2022) as pure tensor functions, for
:class:`mmpc.solver.optimizer.BatchOptimizer` to run eagerly or compiled.

One iteration, for every (problem, goal) element at once:

1. position QP (x and y): one cached KKT operator times ``[c, u, lambda, b]``;
2. heading QP: pull ``psi = P c_psi`` towards ``atan2(ydot, xdot)`` (clipped to the heading band
   when ``config.heading_target_deg`` is set); cached operator;
   ``lambda_psi -= rho P^T (psi - atan2(ydot, xdot))`` (the sign that converges; the paper's
   printed update has it reversed);
3. speed: ``v = clip((xdot, ydot) . (cos psi, sin psi), v_min, v_max)`` — the projection on the
   heading, which minimises the non-holonomic penalty for fixed psi (the paper uses the norm);
4. obstacles: every trajectory point is projected radially out of every ellipse — the closed
   forms of alpha and d = max(1, r) without trigonometry; only the push summed over the
   obstacles leaves the step (compiled, the (M, N, E, G) offsets are never stored);
5. acceleration: projected onto the disc of radius a_max — the closed forms of alpha_a, d_a;
6. ``lambda -= rho F^T (F c - g)``, with the residual mapped to coefficient space once and
   reused by the next position QP.

There is no Python branching on tensor values and no host synchronisation inside the loop.
Compiled for the CPU in float32, the iterations take sin, cos and atan2 from :mod:`mmpc.solver.trig`
(short polynomials the compiler fuses into the loops, float32-exact for headings below 1e4 rad);
compiled for the CPU they contract multiply-adds; eager, in float64 and on the GPU they use the
torch functions.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Optional

import torch

from mmpc.solver import trig
from mmpc.problem import EGO_A, EGO_PSI, EGO_PSIDOT, EGO_V, EGO_X, EGO_Y
from mmpc.result import Status, WarmStart
from mmpc.solver.checks import replace_nonfinite
from mmpc.solver.config import OptimizerConfig

#: Where absent obstacle slots are parked, relative to the ego [m]: far enough that no
#: trajectory point is ever inside their ellipse, small enough to square in float32.
_PARKED_DISTANCE = 1.0e5
_EPS_SQUARED = 1.0e-12


class Limits(NamedTuple):
    """Constants of the iterations, as Python floats: constants to a compiler (no memory reads)."""

    v_min: float  # m/s
    v_max: float  # m/s
    a_max: float  # m/s^2, radius of the disc the acceleration step projects onto (a_max less the back-off)
    heading: Optional[float]  # rad, the band the heading targets are clipped to; None: unclipped
    ellipse_a: float  # m, obstacle ellipse semi-axis along x
    ellipse_b: float  # m, along y
    obstacle_radius: float  # normalised radius the obstacle step projects onto (1 + back-off)
    polynomial_trig: bool = False  # sin, cos, atan2 from mmpc.solver.trig (compiled CPU float32) or torch


def _atan2(y: torch.Tensor, x: torch.Tensor, limits: Limits) -> torch.Tensor:
    """Elementwise angle of (x, y) [rad], from the implementation ``limits`` selects."""
    return trig.atan2(y, x) if limits.polynomial_trig else torch.atan2(y, x)


def _safe_sqrt(square: torch.Tensor) -> torch.Tensor:
    """``square.sqrt()`` with gradient 0 (a norm's subgradient) instead of NaN where ``square`` is 0."""
    zero = square == 0
    return torch.where(zero, 0.0, torch.where(zero, 1.0, square).sqrt())


class _Residuals(NamedTuple):
    """Closed-form steps of one iteration. Layout: batch last, columns ordered (axis, e, g)."""

    stacked: torch.Tensor  # (3N, 2, E, G) [obstacle push; acceleration residual; velocity residual]
    speed: torch.Tensor  # (N, E, G) v [m/s]


class Prepared(NamedTuple):
    """Validated inputs in the ego-relative frame, in the module's dtype and solver layout."""

    origin: torch.Tensor  # (E, 2) ego start position [m]
    b_position: torch.Tensor  # (n_eq, 2 E G') boundary values of x and y
    b_heading: torch.Tensor  # (4, E G') boundary values of psi
    obstacles: torch.Tensor  # (M, N, 2, E, 1) obstacle centres / semi-axes, absent slots parked
    axes: Optional[torch.Tensor]  # (M, 1, 4, E, 1) per-obstacle semi-axes a, b [m] and 1/a, 1/b; None: the config's
    mask: torch.Tensor  # (E, M) bool
    counts: torch.Tensor  # (E,) int64 number of present obstacles
    uniform_count: Optional[int]  # the count when it is the same for every problem
    goal_ahead: torch.Tensor  # (E, G') bool
    num_goals: int  # G', the goals solved for: the G given and `padding` copies of the last
    padding: int  # goals appended to fill SIMD vectors (compiled CPU path), dropped from the result
    compiled: bool  # run the compiled functions; False: the eager ones (autograd)
    warm: Optional[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]  # (K, 2B), (K, 2B), (K, B) iterates to start from
    first_iteration: int  # the first iteration of the schedule run: 0 from the cold start
    last_iteration: int  # the schedule runs up to (not including) this iteration


class _State(NamedTuple):
    """What one iteration hands to the next. Columns ordered (axis, e, g)."""

    c: torch.Tensor  # (K, 2B) x, y coefficients relative to the start
    scaled_residual: torch.Tensor  # (K, 2B) rho_k F^T (F c - g)
    multipliers: torch.Tensor  # (K, 2B)
    multipliers_psi: torch.Tensor  # (K, B)


class _Step(NamedTuple):
    """Last iterate of a run of iterations, for the outputs."""

    c_psi: torch.Tensor  # (K, B)
    samples: torch.Tensor  # (3N, 2, E, G)
    residuals: _Residuals
    records: list  # per-iteration (E, G, 3) residual norms when requested


def layout(
    ego: torch.Tensor,
    goals: torch.Tensor,
    obstacles: torch.Tensor,
    mask: torch.Tensor,
    axes: Optional[torch.Tensor],
    start_acceleration: bool,
    semi_axes: tuple[float, float],
    a_max: float,
) -> tuple[Optional[torch.Tensor], ...]:
    """Inputs in the ego-relative frame and the solver layout (see :class:`Prepared`).

    The start acceleration ``(a, v psidot)`` is held to the disc of radius ``a_max``: an ego
    braking harder than a plan may (the fallback's full brake) would otherwise make every
    candidate infeasible from its first sample, and the fallback would follow itself.

    Returns:
        origin (E, 2) [m]; b_position (n_eq, 2 E G); b_heading (4, E G); obstacles
        (M, N, 2, E, 1) in semi-axis units, absent slots parked; axes: ``None`` when every obstacle
        has ``semi_axes``, else the per-obstacle ``axes`` (E, M, 2) and their reciprocals as
        (M, 1, 4, E, 1) (a, b [m], 1/a, 1/b; absent slots given ``semi_axes``); goal_ahead (E, G) bool; counts (E,) int64 present obstacles per problem.
    """
    num_goals = goals.shape[1]
    origin = ego[:, EGO_X : EGO_Y + 1]  # (E, 2)
    psi0, v0 = ego[:, EGO_PSI], ego[:, EGO_V]
    a0, psidot0 = ego[:, EGO_A], ego[:, EGO_PSIDOT]
    cos0, sin0 = torch.cos(psi0), torch.sin(psi0)
    relative_goals = goals - origin[:, None, :]  # (E, G, 2)

    start_velocity = torch.stack([v0 * cos0, v0 * sin0])  # (2, E)
    rows = [torch.zeros_like(start_velocity), start_velocity]
    if start_acceleration:
        tangential, normal = a0, v0 * psidot0
        scale = (a_max * torch.rsqrt((tangential * tangential + normal * normal).clamp_min(_EPS_SQUARED))).clamp_max(1.0)
        tangential, normal = tangential * scale, normal * scale
        rows.append(torch.stack([tangential * cos0 - normal * sin0, tangential * sin0 + normal * cos0]))
    start = torch.stack(rows)[..., None].expand(-1, -1, -1, num_goals)  # (n_start, 2, E, G)
    end = relative_goals.permute(2, 0, 1).unsqueeze(0)  # (1, 2, E, G)
    b_position = torch.cat([start, end]).reshape(len(rows) + 1, -1)

    zeros = torch.zeros_like(psi0)
    b_heading = torch.stack([psi0, psidot0, zeros, zeros])[..., None].expand(-1, -1, num_goals)
    b_heading = b_heading.reshape(4, -1)

    relative = obstacles - origin[:, None, None, :]  # (E, M, N, 2)
    relative = torch.where(mask[:, :, None, None], relative, _PARKED_DISTANCE)
    if axes is None:
        scaled = relative.permute(1, 2, 3, 0).unsqueeze(-1) / relative.new_tensor(semi_axes).view(2, 1, 1)  # (M, N, 2, E, 1)
    else:
        axes = torch.where(mask[..., None], axes, axes.new_tensor(semi_axes))
        axes = axes.permute(1, 2, 0)[:, None, :, :, None]  # (M, 1, 2, E, 1)
        scaled = relative.permute(1, 2, 3, 0).unsqueeze(-1) / axes
        axes = torch.cat([axes, 1.0 / axes], dim=2).contiguous()  # reciprocals: products in the iterations
    return origin, b_position, b_heading, scaled.contiguous(), axes, relative_goals[..., 0] > 0, mask.sum(dim=1)


def solver_layout(warm: WarmStart) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A batch-first warm start -> the iterations' (K, 2B), (K, 2B), (K, B), columns ordered (axis, e, g),
    contiguous as the cold start's iterates (the compiled functions are specialised to strides)."""
    order = warm.position.shape[-1]
    return (warm.position.permute(3, 2, 0, 1).reshape(order, -1).contiguous(),
            warm.multipliers.permute(3, 2, 0, 1).reshape(order, -1).contiguous(),
            warm.heading_multipliers.permute(2, 0, 1).reshape(order, -1).contiguous())


def iterate(
    state: _State,
    b_position: torch.Tensor,
    b_heading: torch.Tensor,
    obstacles: torch.Tensor,
    axes: Optional[torch.Tensor],
    position: torch.Tensor,
    gather: torch.Tensor,
    heading: torch.Tensor,
    heading_gather: torch.Tensor,
    samples_operator: torch.Tensor,
    heading_basis: torch.Tensor,
    limits: Limits,
    history: bool,
) -> tuple[_State, _Step]:
    """Run U = ``gather.shape[0]`` iterations; every operator argument is sliced to those U.

    Shapes: ``position`` (U, 2, K, D) when every problem has the same obstacle count, else
    (U, E, 2, K, D); ``gather`` (U, K, 3N); ``heading`` (U, K, N + K + 4); ``heading_gather``
    (U, K, N); see :class:`mmpc.solver.operators.Operators`; ``obstacles`` and ``axes`` as
    :class:`Prepared`. Pure tensor code without host
    synchronisation, so that it can be compiled.
    """
    c, scaled_residual, multipliers, multipliers_psi = state
    n = samples_operator.shape[0] // 3
    num_problems, num_goals = obstacles.shape[3], b_heading.shape[1] // obstacles.shape[3]
    records = []
    for u in range(gather.shape[0]):
        stacked = torch.cat([c, scaled_residual, multipliers, b_position])
        c = _position_qp(position[u], stacked, num_problems)
        samples = (samples_operator @ c).view(3 * n, 2, num_problems, num_goals)
        psi_target = _atan2(samples[2 * n :, 1], samples[2 * n :, 0], limits).view(n, -1)  # (N, B)
        if limits.heading is not None:
            psi_target = psi_target.clamp(-limits.heading, limits.heading)
        heading_rhs = torch.cat([psi_target, multipliers_psi, b_heading])
        c_psi = heading[u] @ heading_rhs
        psi = heading_basis @ c_psi
        # The targets read back from the right-hand side: a compiler would otherwise recompute atan2.
        multipliers_psi = torch.addmm(multipliers_psi, heading_gather[u], heading_rhs[:n] - psi)
        residuals = _closed_form_steps(samples, psi.view(n, num_problems, num_goals), obstacles, axes, limits)
        scaled_residual = gather[u] @ residuals.stacked.view(3 * n, -1)
        multipliers = multipliers - scaled_residual
        if history:
            records.append(_residual_norms(residuals, _obstacle_offsets(samples[:n], obstacles, axes, limits), axes, limits))
    return _State(c, scaled_residual, multipliers, multipliers_psi), _Step(c_psi, samples, residuals, records)


def _position_qp(operator: torch.Tensor, stacked: torch.Tensor, num_problems: int) -> torch.Tensor:
    """x, y QP: ``stacked`` (D, 2B) -> (K, 2B); ``operator`` (2, K, D), one per axis, shared by
    every problem, or (E, 2, K, D) per problem."""
    rows = stacked.shape[0]
    if operator.ndim == 3:
        solved = operator @ stacked.view(rows, 2, -1).transpose(0, 1)  # (2, K, B)
        return solved.transpose(0, 1).reshape(operator.shape[1], -1)
    per_problem = stacked.view(rows, 2, num_problems, -1).permute(2, 1, 0, 3)  # (E, 2, D, G)
    solved = operator @ per_problem  # (E, 2, K, G)
    return solved.permute(2, 1, 0, 3).reshape(operator.shape[2], -1)


def _closed_form_steps(
    samples: torch.Tensor, psi: torch.Tensor, obstacles: torch.Tensor, axes: Optional[torch.Tensor], limits: Limits
) -> _Residuals:
    """Closed-form speed, obstacle and acceleration steps and the residual F c - g.

    Args:
        samples: (3N, 2, E, G) [position; acceleration; velocity] relative to the start.
        psi: (N, E, G) heading [rad].
        obstacles: (M, N, 2, E, 1) obstacle centres in semi-axis units.
        axes: (M, 1, 4, E, 1) per-obstacle semi-axes and reciprocals (:class:`Prepared`); ``None``: ``limits``'.
        limits: speed and acceleration bounds, ellipse semi-axes.
    """
    n = psi.shape[0]
    position, acceleration, velocity = samples[:n], samples[n : 2 * n], samples[2 * n :]
    sin, cos = trig.sincos(psi) if limits.polynomial_trig else (torch.sin(psi), torch.cos(psi))
    heading = torch.stack([cos, sin], dim=1)  # (N, 2, E, G)
    speed = (velocity * heading).sum(dim=1).clamp(limits.v_min, limits.v_max)
    velocity_residual = torch.addcmul(velocity, speed.unsqueeze(1), heading, value=-1.0)

    norm_squared = (acceleration * acceleration).sum(dim=1, keepdim=True)
    inverse_norm = norm_squared.clamp_min(_EPS_SQUARED).rsqrt()
    excess = torch.rsub(inverse_norm, 1.0, alpha=limits.a_max).clamp_min(0.0)
    acceleration_residual = acceleration * excess

    offset_x, offset_y, outward = _obstacle_offsets(position, obstacles, axes, limits)
    if axes is None:
        push = torch.stack([(offset_x * outward).sum(dim=0) * limits.ellipse_a,
                            (offset_y * outward).sum(dim=0) * limits.ellipse_b], dim=1)
    else:
        push = torch.stack([(offset_x * outward * axes[:, :, 0]).sum(dim=0),
                            (offset_y * outward * axes[:, :, 1]).sum(dim=0)], dim=1)
    return _Residuals(stacked=torch.cat([push, acceleration_residual, velocity_residual]), speed=speed)


def _obstacle_offsets(
    position: torch.Tensor, obstacles: torch.Tensor, axes: Optional[torch.Tensor], limits: Limits
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every point relative to every ellipse, in semi-axis units: ``(dx, dy, (R/r - 1)_+)``.

    ``r = sqrt(dx^2 + dy^2)`` is the normalised distance; the projection of a point with
    r < R onto the ellipse scaled by R (``limits.obstacle_radius``: 1, or 1 + the back-off)
    moves it by ``(dx, dy) (R/r - 1)`` (times the semi-axes in metres), a point outside is
    left where it is.

    Args:
        position: (N, 2, E, G) sample positions relative to the start [m].
        obstacles: (M, N, 2, E, 1) obstacle centres in semi-axis units.
        axes: (M, 1, 4, E, 1) per-obstacle semi-axes and reciprocals (:class:`Prepared`); ``None``: every
            obstacle has ``limits``'.
        limits: holds the ellipse semi-axes (a, b) [m] and R.

    Returns:
        dx, dy, outward, each (M, N, E, G). Inside a compiled chunk these are never stored:
        the sums over M fuse into one pass over the positions.
    """
    # x and y as separate contiguous planes: far fewer memory passes than an axis dimension.
    # Products with the reciprocals: a vector division costs several multiplications.
    if axes is None:
        offset_x = position[:, 0] * (1.0 / limits.ellipse_a) - obstacles[:, :, 0]
        offset_y = position[:, 1] * (1.0 / limits.ellipse_b) - obstacles[:, :, 1]
    else:  # (N, E, G) x (M, 1, E, 1)
        offset_x = position[:, 0] * axes[:, :, 2] - obstacles[:, :, 0]
        offset_y = position[:, 1] * axes[:, :, 3] - obstacles[:, :, 1]
    distance_squared = offset_x * offset_x + offset_y * offset_y
    inverse_distance = distance_squared.clamp_min(_EPS_SQUARED).rsqrt()
    if limits.obstacle_radius != 1.0:  # a Python constant: no branch in the compiled kernels
        inverse_distance = inverse_distance * limits.obstacle_radius
    outward = inverse_distance.sub(1.0).clamp_min(0.0)
    return offset_x, offset_y, outward


def _residual_norms(
    residuals: _Residuals, offsets: tuple[torch.Tensor, torch.Tensor, torch.Tensor], axes: Optional[torch.Tensor],
    limits: Limits,
) -> torch.Tensor:
    """(E, G, 3) L2 norms of the obstacle [m], acceleration [m/s^2] and non-holonomic [m/s] residuals:
    distances to the sets the iterations project onto (backed off where the config says so).

    The obstacle norm is over every (obstacle, sample) gap, hence the per-obstacle ``offsets``
    of :func:`_obstacle_offsets` rather than the push summed over obstacles.
    """
    n = residuals.speed.shape[0]
    offset_x, offset_y, outward = offsets
    if axes is None:
        gap_x = offset_x * outward * limits.ellipse_a
        gap_y = offset_y * outward * limits.ellipse_b
    else:
        gap_x = offset_x * outward * axes[:, :, 0]
        gap_y = offset_y * outward * axes[:, :, 1]
    stacked = residuals.stacked
    norms = torch.stack(
        [
            (gap_x * gap_x + gap_y * gap_y).sum(dim=(0, 1)),
            (stacked[n : 2 * n] ** 2).sum(dim=(0, 1)),
            (stacked[2 * n :] ** 2).sum(dim=(0, 1)),
        ],
        dim=-1,
    )
    return _safe_sqrt(norms)


def cold_iterates(
    b_position: torch.Tensor, position_init: torch.Tensor, num_problems: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Cold start's iterates: the smoothest trajectories meeting the boundary conditions (K, 2B)
    and zero multipliers (K, 2B), (K, B). :func:`resume` from them starts the schedule, so that a
    cold and a warm solve of one layout share every compiled function. Shapes as in :func:`iterate`."""
    c = _position_qp(position_init, b_position, num_problems)
    return c, torch.zeros_like(c), c.new_zeros(c.shape[0], c.shape[1] // 2)


def resume(
    c: torch.Tensor, multipliers: torch.Tensor, multipliers_psi: torch.Tensor, obstacles: torch.Tensor,
    axes: Optional[torch.Tensor], samples_operator: torch.Tensor, gather: torch.Tensor, limits: Limits,
) -> _State:
    """The iterations' state from iterates (K, 2B), (K, 2B), (K, B) (a warm start's, or
    :func:`cold_iterates`): the residual scaled as the first iteration run expects (``gather``: the
    rho of the iteration before it; ``gather[0]`` from the cold start)."""
    return _State(c, _scaled_residual(c, obstacles, axes, samples_operator, gather, limits), multipliers, multipliers_psi)


def _scaled_residual(
    c: torch.Tensor, obstacles: torch.Tensor, axes: Optional[torch.Tensor], samples_operator: torch.Tensor,
    gather: torch.Tensor, limits: Limits,
) -> torch.Tensor:
    """(K, 2B) ``gather @ (F c - g)`` of coefficients ``c`` (K, 2B), the heading taken along the
    velocity: what the position QP after ``gather``'s iteration reads. Shapes as in :func:`iterate`."""
    n = samples_operator.shape[0] // 3
    samples = (samples_operator @ c).view(3 * n, 2, obstacles.shape[3], -1)
    psi = _atan2(samples[2 * n :, 1], samples[2 * n :, 0], limits)
    residuals = _closed_form_steps(samples, psi, obstacles, axes, limits)
    return gather @ residuals.stacked.view(3 * n, -1)


def summarise(
    c: torch.Tensor,
    step: _Step,
    obstacles: torch.Tensor,
    axes: Optional[torch.Tensor],
    mask: torch.Tensor,
    origin: torch.Tensor,
    goal_ahead: torch.Tensor,
    num_goals: int,
    heading_basis: torch.Tensor,
    heading_rate_basis: torch.Tensor,
    config: OptimizerConfig,
    limits: Limits,
) -> tuple[list[torch.Tensor], torch.Tensor, torch.Tensor, list[torch.Tensor], torch.Tensor]:
    """Trajectories, checks and status of the last iterate, batch first.

    Args:
        c: (K, 2 E G') final x, y coefficients, G' >= G goals (padding goals come last).
        step: the last iterate (heading coefficients, samples, residuals) with G' goals.
        obstacles: (M, N, 2, E, 1) in semi-axis units; axes: as :class:`Prepared`; mask: (E, M); origin: (E, 2) [m];
        goal_ahead: (E, G').
        num_goals: G, the goals kept (the first G).

    Returns:
        fields: the nine (E, G, N) :class:`mmpc.Trajectories` fields after ``times``;
        coefficients (E, G, 3, K); norms (E, G, 3); scalars (min obstacle distance, max heading
        deviation, max acceleration, max non-holonomic error), each (E, G); status (E, G) int32.
    """
    n = config.num_steps
    k = c.shape[0]
    num_problems, padded_goals = step.samples.shape[2], step.samples.shape[3]
    goals = slice(0, num_goals)

    def batch_first(t: torch.Tensor) -> torch.Tensor:  # (N, E, G') -> (E, G, N)
        return t[..., goals].permute(1, 2, 0).contiguous()

    samples = step.samples[..., goals]
    position, acceleration, velocity = samples[:n], samples[n : 2 * n], samples[2 * n :]
    residuals = _Residuals(step.residuals.stacked[..., goals], step.residuals.speed[..., goals])
    psi = (heading_basis @ step.c_psi).view(n, num_problems, padded_goals)
    psidot = (heading_rate_basis @ step.c_psi).view(n, num_problems, padded_goals)

    offsets = _obstacle_offsets(position, obstacles, axes, limits)  # each (M, N, E, G)
    norms = _residual_norms(residuals, offsets, axes, limits)
    distance_squared = offsets[0] ** 2 + offsets[1] ** 2
    present = mask.T[:, None, :, None]
    inf = torch.full((), float("inf"), dtype=c.dtype, device=c.device)
    distance_squared = torch.where(present, distance_squared, inf)
    # An always-absent extra slot keeps the minimum defined (+inf) when M = 0.
    distance_squared = torch.cat([distance_squared, inf.expand(1, *distance_squared.shape[1:])])
    min_distance = _safe_sqrt(distance_squared.amin(dim=(0, 1)))
    start_distance = distance_squared[:, 0].amin(dim=0)

    acceleration_norm = _safe_sqrt((acceleration * acceleration).sum(dim=1))  # (N, E, G)
    velocity_residual = residuals.stacked[2 * n :]
    nonholonomic_error = _safe_sqrt((velocity_residual * velocity_residual).sum(dim=1))
    path_speed = (velocity * velocity).sum(dim=1).sqrt()  # status only: no gradient
    heading_deviation = psi[..., goals].abs().amax(dim=0)
    max_acceleration = acceleration_norm.amax(dim=0)
    max_nonholonomic = nonholonomic_error.amax(dim=0)

    max_heading = math.radians(config.max_heading_deg)
    bits = [
        (min_distance < 1.0 - config.obstacle_tolerance, Status.OBSTACLE),
        (max_acceleration > config.a_max + config.acceleration_tolerance, Status.ACCELERATION),
        (max_nonholonomic > config.nonholonomic_tolerance, Status.NONHOLONOMIC),
        (heading_deviation > max_heading, Status.HEADING),
        (
            (path_speed.amax(dim=0) > config.v_max + config.speed_tolerance)
            | (path_speed.amin(dim=0) < config.v_min - config.speed_tolerance),
            Status.SPEED,
        ),
        (start_distance < (1.0 - config.obstacle_tolerance) ** 2, Status.START_IN_COLLISION),
        (~goal_ahead[:, goals], Status.GOAL_BEHIND),
    ]
    status = torch.zeros(num_problems, num_goals, dtype=torch.int32, device=c.device)
    for condition, flag in bits:
        status = status | condition.to(torch.int32) * int(flag)

    start = origin[:, None, None, :]  # (E, 1, 1, 2)
    fields = [
        batch_first(position[:, 0]) + start[..., 0],
        batch_first(position[:, 1]) + start[..., 1],
        batch_first(psi),
        batch_first(residuals.speed),
        batch_first(velocity[:, 0]),
        batch_first(velocity[:, 1]),
        batch_first(acceleration[:, 0]),
        batch_first(acceleration[:, 1]),
        batch_first(psidot),
    ]
    coefficients = torch.cat(
        [c.view(k, 2, num_problems, padded_goals), step.c_psi.view(k, 1, num_problems, padded_goals)], dim=1
    )[..., goals].permute(2, 3, 1, 0)
    finite = torch.stack([f.isfinite().all(dim=-1) for f in fields]).all(dim=0)
    finite = finite & coefficients.isfinite().flatten(2).all(dim=-1)
    status = status | (~finite).to(torch.int32) * int(Status.NUMERICAL)
    fields, coefficients, norms, scalars = replace_nonfinite(
        finite, origin, fields, coefficients, norms, [min_distance, heading_deviation, max_acceleration, max_nonholonomic]
    )
    return fields, coefficients, norms, scalars, status
