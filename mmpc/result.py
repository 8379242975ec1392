"""Solver outputs as data: trajectories, residuals and a status bit mask per batch element."""

from __future__ import annotations

import enum
from typing import Callable, NamedTuple, Optional, Sequence

import torch

from mmpc.compaction import scatter


class Status(enum.IntFlag):
    """Why an element is not feasible; ``OK`` (0) means feasible. Bits combine."""

    OK = 0
    OBSTACLE = 1  #: some predicted obstacle comes inside its ellipse
    ACCELERATION = 2  #: acceleration norm above a_max + tolerance
    NONHOLONOMIC = 4  #: (xdot, ydot) departs from v (cos psi, sin psi) by more than tolerance
    HEADING = 8  #: heading leaves the +-max_heading band around the road direction
    SPEED = 16  #: path speed outside [v_min, v_max] by more than tolerance
    START_IN_COLLISION = 32  #: the ego starts inside an obstacle ellipse (beyond the obstacle tolerance)
    GOAL_BEHIND = 64  #: the goal is not ahead of the ego
    NUMERICAL = 128  #: the iterations produced non-finite values; outputs replaced by the initial guess
    OFF_ROAD = 256  #: leaves the road surface (set by :class:`mmpc.MPC`'s road filter, not by the optimizer)

    @classmethod
    def describe(cls, code: int) -> str:
        """Human-readable names of the bits set in ``code`` ("OK" for 0)."""
        if code == 0:
            return "OK"
        return "|".join(flag.name for flag in cls if flag and code & flag)  # type: ignore[misc]


class Trajectories(NamedTuple):
    """Optimized trajectories in the road frame, sampled at the basis times.

    Shapes (E problems, G goals, N samples):
        times: (N,) [s]
        x, y: (E, G, N) position [m]
        psi: (E, G, N) heading [rad]
        v: (E, G, N) speed variable of the non-holonomic constraint [m/s]
        xdot, ydot: (E, G, N) velocity [m/s]
        xddot, yddot: (E, G, N) acceleration [m/s^2]
        psidot: (E, G, N) heading rate [rad/s]
    """

    times: torch.Tensor
    x: torch.Tensor
    y: torch.Tensor
    psi: torch.Tensor
    v: torch.Tensor
    xdot: torch.Tensor
    ydot: torch.Tensor
    xddot: torch.Tensor
    yddot: torch.Tensor
    psidot: torch.Tensor

    def select(self, index: torch.Tensor) -> "Trajectories":
        """One goal per problem: ``index`` (E,) of goals -> every field (E, N)."""
        rows = torch.arange(self.x.shape[0], device=self.x.device)
        picked = [field[rows, index] for field in self[1:]]
        return Trajectories(self.times, *picked)


class WarmStart(NamedTuple):
    """The iterates a solve ended with, to start a later solve of the same goals from (the next
    control step's, after :meth:`mmpc.BatchOptimizer.shifted`). Batch dims lead: (E, G, ...).

    Fields:
        position: (E, G, 2, K) x, y Bernstein coefficients relative to the problem's start [m].
        multipliers: (E, G, 2, K) the position constraints' Lagrange multipliers.
        heading_multipliers: (E, G, K) the heading constraint's multipliers.
    """

    position: torch.Tensor
    multipliers: torch.Tensor
    heading_multipliers: torch.Tensor

    def take(self, rows: torch.Tensor) -> "WarmStart":
        """The problems ``rows`` (long or bool over E)."""
        return WarmStart(*(field[rows] for field in self))

    def finite(self) -> torch.Tensor:
        """(E,) bool, every iterate of the problem is finite (NaN marks a problem to restart)."""
        return torch.stack([field.isfinite().flatten(1).all(dim=1) for field in self]).all(dim=0)


class SolveResult(NamedTuple):
    """Everything a batch solve returns. Batch dims lead: (E, G, ...).

    Fields:
        trajectories: :class:`Trajectories`.
        coefficients: (E, G, 3, K) Bernstein coefficients of x, y (relative to the ego's start
            position) and psi.
        residual_obstacle: (E, G) L2 norm over obstacles and time of the distance from each
            trajectory point to its projection out of each ellipse [m] (the ellipses the iterations
            project onto: scaled by 1 + ``OptimizerConfig.obstacle_backoff``).
        residual_acceleration: (E, G) L2 norm over time of the excess acceleration over the
            disc the iterations project onto (``a_max - acceleration_backoff``) [m/s^2].
        residual_nonholonomic: (E, G) L2 norm over time of (xdot, ydot) - v (cos psi, sin psi) [m/s].
        min_obstacle_distance: (E, G) smallest normalised ellipse distance
            sqrt((dx/a)^2 + (dy/b)^2) over present obstacles and time; < 1 means overlap, +inf
            without obstacles.
        max_heading_deviation: (E, G) largest |psi| over the horizon [rad].
        max_acceleration: (E, G) largest acceleration norm [m/s^2].
        max_nonholonomic_error: (E, G) largest |(xdot, ydot) - v (cos psi, sin psi)| [m/s].
        status: (E, G) int32 bit mask of :class:`Status`.
        feasible: (E, G) bool, ``status == 0``.
        iterations: (E, G) int32, iterations run for the element: the schedule's, fewer from a
            warm start, both where a warm start found no feasible goal and its problem was solved again cold.
        history: (I, E, G, 3) obstacle, acceleration and non-holonomic residuals after every
            iteration, when requested; otherwise ``None``.
        warm: the final iterates (:class:`WarmStart`), to warm-start the next step's solve.
    """

    trajectories: Trajectories
    coefficients: torch.Tensor
    residual_obstacle: torch.Tensor
    residual_acceleration: torch.Tensor
    residual_nonholonomic: torch.Tensor
    min_obstacle_distance: torch.Tensor
    max_heading_deviation: torch.Tensor
    max_acceleration: torch.Tensor
    max_nonholonomic_error: torch.Tensor
    status: torch.Tensor
    feasible: torch.Tensor
    iterations: torch.Tensor
    history: Optional[torch.Tensor] = None
    warm: Optional[WarmStart] = None

    @staticmethod
    def concatenate(parts: Sequence["SolveResult"], dim: int) -> "SolveResult":
        """Join results of sub-batches along the problem (``dim=0``) or goal (``dim=1``) axis."""
        if dim not in (0, 1) or not parts:
            raise ValueError(f"need at least one part and dim 0 or 1; got {len(parts)} parts, dim={dim}")
        if len(parts) == 1:
            return parts[0]
        return SolveResult._combine(parts, lambda tensors, offset: torch.cat(tensors, dim=dim + offset))

    @staticmethod
    def interleave(parts: Sequence["SolveResult"], rows: Sequence[torch.Tensor], num_problems: int) -> "SolveResult":
        """Join results of subsets of ``num_problems`` problems: ``parts[i]`` solved the problems
        ``rows[i]`` (long indices); where subsets overlap, the later part's problems are kept."""
        if not parts or len(parts) != len(rows):
            raise ValueError(f"need one row index per part; got {len(parts)} parts and {len(rows)} row indices")

        def join(tensors: list[torch.Tensor], offset: int) -> torch.Tensor:
            shape = tensors[0].shape
            out = tensors[0].new_empty((*shape[:offset], num_problems, *shape[offset + 1 :]))
            for tensor, index in zip(tensors, rows):
                out.index_copy_(offset, index, tensor)
            return out

        return SolveResult._combine(parts, join)

    def problem_iterations(self) -> torch.Tensor:
        """(E,) long, the iterations each problem's goals ran, averaged over its goals (rounded):
        the schedule's, fewer after a warm start or an early exit (``OptimizerConfig.exit_checks``)."""
        return self.iterations.float().mean(dim=1).round().long()

    def replace_elements(self, part: "SolveResult", elements: torch.Tensor) -> "SolveResult":
        """A copy whose (problem, goal) elements ``elements`` (long, indices into the flattened
        (E, G)) are ``part``'s (R, 1) elements, in order; ``history``: ``part``'s iterations where it
        ran (not NaN), this result's elsewhere."""
        if part.status.shape != (elements.numel(), 1):
            raise ValueError(f"`part` must hold one goal per element replaced, ({elements.numel()}, 1); "
                             f"got {tuple(part.status.shape)}")

        def join(tensors: list[torch.Tensor], offset: int) -> torch.Tensor:
            base, new = tensors
            out = base.clone(memory_format=torch.contiguous_format)
            flat, new = out.flatten(offset, offset + 1), new.flatten(offset, offset + 1)  # a view of ``out``
            if offset == 0:
                flat.index_copy_(0, elements, new)
            else:  # history (I, E, G, 3)
                flat[:, elements] = torch.where(new.isnan(), flat[:, elements], new)
            return out

        return SolveResult._combine([self, part], join)

    def replace_rows(self, part: "SolveResult", rows: torch.Tensor) -> "SolveResult":
        """A copy whose problems ``rows`` (R,) long, distinct, are ``part``'s R problems, in order;
        an index of E (one past the last problem) drops that problem of ``part`` (a fixed-size
        buffer's padding), without a host synchronisation."""
        return SolveResult._combine([self, part], lambda tensors, offset: scatter(tensors[0], offset, rows, tensors[1]))

    def take_goals(self, index: torch.Tensor) -> "SolveResult":
        """The goals ``index`` (E, K) long of each problem, in that order (a goal may repeat)."""
        def gather(tensors: list[torch.Tensor], offset: int) -> torch.Tensor:
            tensor = tensors[0]
            shape = (*tensor.shape[:offset], *index.shape, *tensor.shape[offset + 2:])
            spread = index.view(*(1,) * offset, *index.shape, *(1,) * (tensor.dim() - offset - 2)).expand(shape)
            return tensor.gather(offset + 1, spread)

        return SolveResult._combine([self], gather)

    def head(self, num_problems: int, num_goals: int) -> "SolveResult":
        """The first ``num_problems`` problems and, of each, the first ``num_goals`` goals."""
        return SolveResult._combine(
            [self], lambda tensors, offset: tensors[0][(slice(None),) * offset + (slice(num_problems), slice(num_goals))]
        )

    @staticmethod
    def _combine(parts: Sequence["SolveResult"],
                 combine: Callable[[list[torch.Tensor], int], torch.Tensor]) -> "SolveResult":
        """A result whose every batched tensor is ``combine(that tensor of each part, offset)``, the
        problem axis at ``offset`` (1 for ``history``, else 0); the sample times are shared."""
        first = parts[0]
        trajectories = Trajectories(
            first.trajectories.times,
            *(combine([part.trajectories[i] for part in parts], 0) for i in range(1, len(Trajectories._fields))),
        )
        per_element = {
            name: combine([getattr(part, name) for part in parts], 0)
            for name in SolveResult._fields
            if name not in ("trajectories", "history", "warm")
        }
        history = None if first.history is None else combine([part.history for part in parts], 1)
        warm = None if first.warm is None else WarmStart(*(combine(list(fields), 0)
                                                             for fields in zip(*(part.warm for part in parts))))
        return SolveResult(trajectories=trajectories, **per_element, history=history, warm=warm)
