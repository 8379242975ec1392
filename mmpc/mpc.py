"""Multi-modal MPC: sample goals, solve the batch, rank by the meta cost, extract the control.

Environment-agnostic: state in (road frame), command and diagnostics out. Adapters (e.g.
:mod:`mmpc.highway`) convert their simulator's state to the tensors below and the command to
their action space. Batched over E problems (e.g. vectorized environments): one optimizer call
per :meth:`MPC.plan`.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Callable, NamedTuple, Optional

import torch

from mmpc.config import require, require_field_types, require_int, require_non_negative, require_positive
from mmpc.goals import GoalSampler
from mmpc.meta_costs import MetaCost
from mmpc.obstacles.prediction import PREDICTIONS
from mmpc.obstacles.shape import (
    HIGHWAY_VEHICLE, OBSTACLE_SHAPES, longest_semi_axes, nearest_obstacles, obstacle_semi_axes, squared_obstacle_distance,
)
from mmpc.problem import EGO_FIELDS, EGO_PSI, EGO_V, EGO_Y, ProblemBatch, require_on_device
from mmpc.ranking import Selection, constraint_violation, lateral_move, select_best
from mmpc.result import SolveResult, Status, Trajectories, WarmStart
from mmpc.road import Road
from mmpc.solver.optimizer import BatchOptimizer
from mmpc.stopping import conflict_deceleration, stop_goals

#: A selection rule for :meth:`MPC.plan_problem`: ``(result, cost (E, G), violation (E, G)) -> Selection``.
Selector = Callable[[SolveResult, torch.Tensor, torch.Tensor], Selection]

#: Status bits that make a candidate unfit to drive even as a fallback: a path that breaks the
#: vehicle model, leaves the heading band or the road, or is numerically broken. (Measured in
#: highway-env: executing the least-infeasible candidate whatever its flaws once steered into
#: a car; braking instead of every infeasible candidate caused 7 collisions in 20 high-speed
#: episodes, as it brakes in front of followers and steers into the nearest lane centre.)
UNDRIVABLE = Status.NONHOLONOMIC | Status.HEADING | Status.SPEED | Status.NUMERICAL | Status.OFF_ROAD


#: How far inside an obstacle's ellipse (in normalised distance) a candidate may start and still
#: be feasible, if it never goes deeper (:meth:`MPC._allow_escape`): the corners of two 5 m x
#: 2 m cars lie at 0.91 of the high-speed scenario's 8 m x 3 m ellipse.
ESCAPE_DEPTH = 0.05

#: With ``fixed_shapes``: the share of a warm-started step's problems that may solve again cold.
#: All of them: a lockstep batch's scheduled restarts (``MPCConfig.warm_cold_every``) coincide, and a
#: problem past a smaller buffer would drive a few warm iterations from a standstill (the high-speed
#: loop re-solves ~22 % of its problems per step on average, 5 of 8 at once in a lockstep batch).
COLD_SHARE = 1.0

#: MPCConfig keys retired on 2026-11-28 (:meth:`MPCConfig.upgrade`): each switch with its off value,
#: and (None) the settings that only mattered while their switch was on.
RETIRED_OPTIONS = {
    "contingencies": 0, "passing_margin": 0.0, "closing_margin": 0.0, "evasive_horizon": 0.0,
    "contingency_window": None, "contingency_lateral_speed": None, "contingency_trigger": None,
    "contingency_min_gain": None, "max_passing_margin": None, "max_closing_margin": None,
}

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class MPCConfig:
    """Settings of the receding-horizon loop.

    Attributes:
        num_obstacles: M, the vehicles given to the optimizer, nearest first within
            ``obstacle_lookahead`` (must not exceed the optimizer's ``max_obstacles``).
        ignore_behind: vehicles more than this far behind the ego are ignored [m].
        obstacle_lookahead: the M obstacles are the vehicles that come nearest within this
            many seconds at constant velocity (:func:`mmpc.obstacles.shape.nearest_obstacles`) [s];
            0: nearest now.
            Measured in high-speed traffic with goals at 24 m/s: ranked by today's distance, a
            7 m/s car 46 m ahead in the ego's lane was left out for cars beside and behind,
            every plan drove through it, and the ego met a wall of slow cars at 23.5 m/s.
        prediction: how the obstacles move over the horizon
            (:data:`mmpc.obstacles.prediction.PREDICTIONS`): ``"lanes"`` (constant velocity,
            lateral motion ending on the next lane centre, :func:`mmpc.predict_within_lanes`)
            or ``"constant_velocity"`` (:func:`mmpc.predict_constant_velocity`, lateral motion
            unbounded): a vehicle changing lanes, extrapolated straight, crosses every lane within
            the horizon and leaves no feasible candidate.
        obstacle_shape: each obstacle's ellipse: ``"fixed"`` (the optimizer's ``ellipse_a``,
            ``ellipse_b`` for every car) or ``"heading"`` (widened across the road to cover the
            car at its direction of motion, :func:`mmpc.obstacles.shape.obstacle_semi_axes`): a car
            changing lanes, turned 10-30 deg, reaches 0.6-1 m beyond the fixed ellipse.
        command_window: the command is the plan's tangential acceleration and heading rate
            averaged over ``[0, command_window]`` [s]. Each plan starts at the current heading
            rate, so with a window of one 0.1 s control period the lateral loop is underdamped
            (it overshoots lane changes); averaging over 0.3 s anticipates the plan's trend at
            no cost in speed tracking.
        tie_tolerance, tie_margin: candidates whose meta cost is within
            ``tie_tolerance * lowest + tie_margin`` of the lowest count as tied [-, meta-cost
            units; 1.0 is e.g. 0.1 m/s of RMS speed error over a 100-sample horizon for the
            cruise cost, and small beside 1 % of the high-speed costs], and the tie goes to the candidate ending nearest the ego laterally
            (:func:`mmpc.ranking.lateral_move`; the baselines rank the same way). Without it, two
            lanes that cost the same (following at 9 m/s in either) were chosen in turn from one
            step to the next, and the ego drove on the lane line for 10 s (cruise seed 11).
        brake_deceleration: deceleration of the lane-keeping brake, the fallback when no
            candidate is feasible and the least-infeasible one is not drivable [m/s^2].
        max_deceleration: the strongest braking a fallback asks for to stay behind a vehicle
            ahead in the ego's lane (:func:`mmpc.stopping.conflict_deceleration`; highway-env's
            full brake) [m/s^2].
        stop_lanes: the goal set gets a stop goal on the ego's lane and this many lanes either
            side (:func:`mmpc.stopping.stop_goals`): rest behind the first vehicle ahead, or
            braking to rest over the horizon on a clear lane. Without them no goal is
            reachable close behind stopped traffic. ``None``: no stop goals.
        stop_gap: room a stop goal leaves beyond the obstacle ellipse, and the fallback's
            braking beyond a vehicle length [m].
        max_steering: steering saturation [rad].
        road_margin: a candidate whose centre comes closer than this to a road edge is
            infeasible (:attr:`mmpc.Status.OFF_ROAD`); the optimizer itself knows no road edges [m].
        warm_iterations: 0: every solve from the cold start. k > 0: a solve given the previous
            step's final iterates (:meth:`plan`'s ``warm``; :class:`mmpc.drivers.MPCDriver` keeps
            them per environment) runs only the last k iterations of the schedule; a problem
            whose warm solve finds no feasible goal is solved again cold.
        warm_cold_every: with warm starts, an environment solves cold every n-th step (and the
            step after its fallback): chains of warm solves drift to costlier plans.
        warm_keep_share: with warm starts, an environment also solves cold at the step after a
            warm solve that found fewer feasible goals than this share of its last cold solve's:
            a goal infeasible at the end of one solve rarely turns feasible in the next one's few
            high-penalty iterations, so the feasible set of a warm chain only shrinks. 0: never.
    """

    num_obstacles: int = 6
    ignore_behind: float = 20.0
    obstacle_lookahead: float = 3.0
    prediction: str = "lanes"
    obstacle_shape: str = "fixed"
    command_window: float = 0.3
    tie_tolerance: float = 0.01
    tie_margin: float = 1.0
    brake_deceleration: float = 4.0
    max_deceleration: float = 5.0
    stop_lanes: Optional[int] = 1
    stop_gap: float = 2.0
    max_steering: float = math.pi / 4
    road_margin: float = 1.0
    warm_iterations: int = 0
    warm_cold_every: int = 10
    warm_keep_share: float = 0.75

    def __post_init__(self) -> None:
        require_field_types(self)
        require(self.prediction in PREDICTIONS,
                f"`prediction` must be one of {sorted(PREDICTIONS)}; got {self.prediction!r}")
        require(self.obstacle_shape in OBSTACLE_SHAPES,
                f"`obstacle_shape` must be one of {list(OBSTACLE_SHAPES)}; got {self.obstacle_shape!r}")
        require_int("", low=0, num_obstacles=self.num_obstacles, warm_iterations=self.warm_iterations)
        require_int("", low=1, warm_cold_every=self.warm_cold_every)
        require(0.0 <= self.warm_keep_share <= 1.0,
                f"`warm_keep_share` must be in [0, 1]; got {self.warm_keep_share!r}")
        names = ("ignore_behind", "command_window", "brake_deceleration", "max_deceleration", "max_steering")
        require_positive("", **{name: getattr(self, name) for name in names})
        require_non_negative("", obstacle_lookahead=self.obstacle_lookahead, road_margin=self.road_margin,
                             tie_tolerance=self.tie_tolerance, tie_margin=self.tie_margin, stop_gap=self.stop_gap)
        require(self.stop_lanes is None or self.stop_lanes >= 0,
                f"`stop_lanes` must be null (no stop goals) or an int >= 0; got {self.stop_lanes!r}")
        require(self.max_deceleration >= self.brake_deceleration,
                f"`max_deceleration` ({self.max_deceleration}) must be >= `brake_deceleration` ({self.brake_deceleration})")

    @classmethod
    def upgrade(cls, values: Mapping, where: str) -> dict:
        """Read a mapping written before the prediction options were retired (the lane-change
        contingencies, the passing and closing margins, ``evasive_horizon``; the verified driver,
        ``verified:mpc``, replaced them): their keys are dropped with a warning where the option
        was off, and refused where it was on (the run cannot be reproduced by this mmpc)."""
        retired = RETIRED_OPTIONS.keys() & set(values)
        if not retired:
            return dict(values)
        switched_on = {name: values[name] for name in sorted(retired) if RETIRED_OPTIONS[name] is not None
                       and values[name] != RETIRED_OPTIONS[name]}
        if switched_on:
            raise ValueError(f"{where}: {switched_on} switch on prediction options this mmpc no longer has (retired "
                             f"2026-11-28: docs/experiments/2026-11-28-verified-driving.md); drive `verified:mpc` "
                             f"for a verified way out, or mmpc at commit 748c42c to reproduce the run")
        logger.warning("%s: retired MPC option key(s) %s ignored (each was off); remove them", where, sorted(retired))
        return {name: value for name, value in values.items() if name not in retired}


class Plan(NamedTuple):
    """One MPC step for E problems.

    Fields:
        problem: the batch that was solved (E problems, G goals, M obstacle slots).
        result: the full solve, (E, G, ...).
        cost: (E, G) meta cost.
        selection: chosen goal per problem (``selection.feasible`` False: fallback).
        trajectory: the chosen trajectories, every field (E, N).
        acceleration: (E,) longitudinal acceleration command [m/s^2].
        steering: (E,) steering angle command [rad].
        heading_rate: (E,) the planned heading rate behind ``steering`` [rad/s].
        solve_ms: wall time of the optimizer call [ms], less ``compile_ms``.
        compile_ms: what the call spent compiling new layouts [ms]
            (:attr:`mmpc.BatchOptimizer.last_compile_ms`; 0 when eager or nothing was new);
            callers that time a whole step subtract it.
    """

    problem: ProblemBatch
    result: SolveResult
    cost: torch.Tensor
    selection: Selection
    trajectory: Trajectories
    acceleration: torch.Tensor
    steering: torch.Tensor
    heading_rate: torch.Tensor
    solve_ms: float
    compile_ms: float = 0.0


class Scored(NamedTuple):
    """The candidates of one solve, scored (:meth:`MPC.score`), before any selection.

    Fields:
        result: the solve, (E, G, ...), with :attr:`mmpc.Status.OFF_ROAD` set by the road filter.
        cost: (E, G) meta cost.
        violation: (E, G) ranking of infeasible candidates, drivable ones first (lower is better).
        solve_ms: wall time of the optimizer call [ms], less ``compile_ms``.
        compile_ms: what the call spent compiling new layouts [ms].
    """

    result: SolveResult
    cost: torch.Tensor
    violation: torch.Tensor
    solve_ms: float
    compile_ms: float = 0.0


def check_state(ego: torch.Tensor, vehicles: torch.Tensor, vehicle_mask: Optional[torch.Tensor],
                values: bool = True) -> None:
    """Refuse what :meth:`MPC.build_problem` cannot plan from, naming what came.

    Args:
        ego: must be a finite (E, 6) float tensor.
        vehicles: must be a (E, V, 4) float tensor, finite in every row ``vehicle_mask`` marks real.
        vehicle_mask: ``None`` or a (E, V) bool tensor on ``vehicles``' device.
        values: check the values too (a host synchronisation); else types, shapes and devices only.
    """
    for name, value in (("ego", ego), ("vehicles", vehicles), ("vehicle_mask", vehicle_mask)):
        if value is not None and not isinstance(value, torch.Tensor):
            raise TypeError(f"`{name}` must be a torch.Tensor; got {type(value).__name__}")
    if ego.ndim != 2 or ego.shape[1] != len(EGO_FIELDS) or not ego.is_floating_point():
        raise ValueError(f"`ego` must be a float tensor of shape (E, {len(EGO_FIELDS)}); got {ego.dtype} {tuple(ego.shape)}")
    if vehicles.ndim != 3 or vehicles.shape[0] != ego.shape[0] or vehicles.shape[2] != 4 or not vehicles.is_floating_point():
        raise ValueError(f"`vehicles` must be a float tensor of shape ({ego.shape[0]}, V, 4); got {vehicles.dtype} {tuple(vehicles.shape)}")
    if values and not bool(torch.isfinite(ego).all()):
        rows = (~torch.isfinite(ego)).any(dim=1).nonzero().flatten().tolist()
        raise ValueError(f"`ego` must be finite; non-finite values in rows {rows}")
    real = torch.ones(vehicles.shape[:2], dtype=torch.bool, device=vehicles.device)
    if vehicle_mask is not None:
        if vehicle_mask.dtype != torch.bool or tuple(vehicle_mask.shape) != tuple(vehicles.shape[:2]):
            raise ValueError(
                f"`vehicle_mask` must be a bool tensor of shape {tuple(vehicles.shape[:2])} (one flag per vehicle); "
                f"got {vehicle_mask.dtype} {tuple(vehicle_mask.shape)}"
            )
        if vehicle_mask.device != vehicles.device:
            raise ValueError(f"`vehicle_mask` must be on {vehicles.device}; got {vehicle_mask.device}")
        real = vehicle_mask
    if not values:
        return
    broken = real & ~torch.isfinite(vehicles).all(dim=-1)
    if bool(broken.any()):
        where = broken.nonzero().tolist()
        raise ValueError(f"`vehicles` must be finite for every real vehicle; non-finite (problem, vehicle): {where[:8]}")


class MPC:
    """Receding-horizon multi-modal MPC over a batch of E problems.

    Args:
        optimizer: the batch optimizer (its config sets horizon, bounds and ellipse).
        goal_sampler: ``f(ego (E, 6), road) -> goals (E, G, 2)``.
        meta_cost: ``f(trajectories, road) -> (E, G)``.
        road: the road (lanes) the goals and costs refer to.
        config: loop settings.
        wheelbase: L of ``steering = atan(L psidot / v)`` [m]; highway-env's kinematic bicycle
            turns at ``v tan(delta) / L`` with L its vehicle length (a scenario's
            ``ScenarioConfig.vehicle`` length, :func:`mmpc.scenario.build_mpc`). Also the
            vehicle length the fallback keeps to the vehicle ahead.
        vehicle_width: every vehicle's width [m]; with ``wheelbase`` as the length, the footprint
            that :attr:`MPCConfig.obstacle_shape` ``"heading"`` covers.
        fixed_shapes: plan without reading a value on the host, every shape known from the input
            shapes (a decision that traces as one graph, what a CUDA graph needs): the optimizer's
            fixed-shape solve (``BatchOptimizer.forward(fixed_shapes=True)``), a warm-started
            step re-solving at most :data:`COLD_SHARE` of its problems cold; the state's values
            unchecked (a non-finite ego state gives a non-finite command, which the simulator
            refuses); no solve timing (:attr:`Scored.solve_ms` NaN: time the call from outside).

    Example:
        >>> import torch, mmpc
        >>> from mmpc.mpc import MPC
        >>> optimizer = mmpc.BatchOptimizer()
        >>> mpc = MPC(optimizer, mmpc.CruiseGoals(horizon=optimizer.config.horizon), mmpc.CruiseCost(), mmpc.Road())
        >>> ego = mmpc.ego_state(0.0, 8.0, 0.0, 14.0)
        >>> plan = mpc.plan(ego, torch.tensor([[[30.0, 8.0, 10.0, 0.0]]]))
        >>> plan.acceleration.shape, bool(plan.selection.feasible[0])
        (torch.Size([1]), True)
    """

    def __init__(
        self,
        optimizer: BatchOptimizer,
        goal_sampler: GoalSampler,
        meta_cost: MetaCost,
        road: Road,
        config: Optional[MPCConfig] = None,
        *,
        wheelbase: float = HIGHWAY_VEHICLE[0],
        vehicle_width: float = HIGHWAY_VEHICLE[1],
        control_period: Optional[float] = None,
        fixed_shapes: bool = False,
    ) -> None:
        require_positive("MPC", wheelbase=wheelbase, vehicle_width=vehicle_width)
        if not isinstance(fixed_shapes, bool):
            raise TypeError(f"`fixed_shapes` must be True or False; got {fixed_shapes!r}")
        if fixed_shapes and optimizer.config.exit_checks:
            raise ValueError(f"`fixed_shapes` needs an optimizer without early exits; got "
                             f"exit_checks={optimizer.config.exit_checks}")
        #: Whether a step reads nothing on the host (see the class's ``fixed_shapes``).
        self.fixed_shapes = fixed_shapes
        if control_period is not None:
            require_positive("MPC", control_period=control_period)
        #: time between two of its steps [s] (a scenario's 1 / frequency), by which a warm start moves
        #: the last solve (:mod:`mmpc.warm`); ``None``: unknown, its users name it.
        self.control_period = control_period
        self.wheelbase = wheelbase
        self.vehicle = (wheelbase, vehicle_width)
        self.optimizer = optimizer
        self.goal_sampler = goal_sampler
        self.meta_cost = meta_cost
        self.road = road
        self.config = config if config is not None else MPCConfig()
        if self.config.num_obstacles > optimizer.config.max_obstacles:
            raise ValueError(
                f"MPCConfig.num_obstacles={self.config.num_obstacles} exceeds the optimizer's "
                f"max_obstacles={optimizer.config.max_obstacles}"
            )
        if self.config.warm_iterations > optimizer.config.iterations:
            raise ValueError(f"MPCConfig.warm_iterations={self.config.warm_iterations} exceeds the optimizer's "
                             f"iterations={optimizer.config.iterations}")

    def build_problem(
        self, ego: torch.Tensor, vehicles: torch.Tensor, vehicle_mask: Optional[torch.Tensor] = None
    ) -> ProblemBatch:
        """Road-frame state -> problem batch: the goal sampler's goals and then the stop goals
        (:attr:`MPCConfig.stop_lanes`), the nearest obstacles predicted over the horizon, and
        their ellipses (:meth:`obstacle_axes`).

        Raises:
            ValueError: a wrong shape, a non-finite value in ``ego`` or in a real vehicle, or a
                ``vehicle_mask`` that is not (E, V) bool.
        """
        opt = self.optimizer
        require_on_device(opt.device, "the MPC's optimizer", ego=ego, vehicles=vehicles, vehicle_mask=vehicle_mask)
        check_state(ego, vehicles, vehicle_mask, values=not self.fixed_shapes)
        ego = ego.to(dtype=opt.dtype)
        vehicles = vehicles.to(dtype=opt.dtype)
        if vehicle_mask is None:
            vehicle_mask = torch.ones(vehicles.shape[:2], dtype=torch.bool, device=vehicles.device)
        vehicles = torch.where(vehicle_mask[..., None], vehicles, torch.zeros_like(vehicles))  # absent rows may hold NaN
        states, mask = self.nearest_obstacles(ego, vehicles, vehicle_mask)
        obstacles = self.predict(states, opt.times)
        axes = self.obstacle_axes(states)
        goals = self.goal_sampler(ego, self.road)
        if self.config.stop_lanes is not None:  # rest behind the longest ellipse of the problem's obstacles
            stops = stop_goals(ego, obstacles, mask, self.road, horizon=opt.config.horizon,
                               ellipse=longest_semi_axes(axes, mask, self.ellipse), lanes=self.config.stop_lanes,
                               gap=self.config.stop_gap)
            goals = torch.cat([goals, stops], dim=1)
        return ProblemBatch(ego, goals, obstacles, mask, axes)

    def obstacle_axes(self, states: torch.Tensor) -> Optional[torch.Tensor]:
        """(E, M, 2) ellipse semi-axes [m] of the (E, M, 4) obstacle states by
        :attr:`MPCConfig.obstacle_shape` (:func:`mmpc.obstacles.shape.obstacle_semi_axes`); ``None``
        for ``"fixed"`` (the optimizer's ellipse)."""
        return obstacle_semi_axes(states, self.config.obstacle_shape, self.ellipse, self.optimizer.config.max_heading_deg,
                                  self.vehicle)

    @property
    def ellipse(self) -> tuple[float, float]:
        """The optimizer's obstacle ellipse semi-axes (a, b) [m]."""
        return self.optimizer.config.ellipse

    def nearest_obstacles(
        self, ego: torch.Tensor, vehicles: torch.Tensor, vehicle_mask: Optional[torch.Tensor]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The (E, M, 4) states and (E, M) mask of the obstacles this MPC plans around:
        :func:`mmpc.obstacles.shape.nearest_obstacles` with the config's count, ignore-behind distance and lookahead
        and the optimizer's ellipse."""
        return nearest_obstacles(
            ego, vehicles, vehicle_mask, self.config.num_obstacles, self.ellipse,
            self.config.ignore_behind, self.config.obstacle_lookahead,
        )

    def predict(self, states: torch.Tensor, times: torch.Tensor) -> torch.Tensor:
        """(E, M, 4) obstacle states -> (E, M, N, 2) centres at ``times`` (N,) [s], by
        :attr:`MPCConfig.prediction`."""
        return PREDICTIONS[self.config.prediction](states, times.to(states.dtype), self.road)

    def tie_break(self, trajectories: Trajectories, ego: torch.Tensor) -> dict:
        """The tie-break keywords of :func:`mmpc.ranking.lowest_feasible` (and
        :func:`mmpc.ranking.select_best`) for (E, G) candidates of the (E, 6) egos: ties within
        :attr:`MPCConfig.tie_tolerance` / ``tie_margin`` go to the smallest
        :func:`mmpc.ranking.lateral_move`. The baselines rank with the same keywords."""
        return {"preference": lateral_move(trajectories, ego), "tie_tolerance": self.config.tie_tolerance,
                "tie_margin": self.config.tie_margin}

    @torch.no_grad()
    def plan(
        self, ego: torch.Tensor, vehicles: torch.Tensor, vehicle_mask: Optional[torch.Tensor] = None, *,
        warm: Optional[WarmStart] = None,
    ) -> Plan:
        """One MPC step for E problems.

        Args:
            ego: (E, 6) ego states in the road frame (see :data:`mmpc.EGO_FIELDS`); ``a`` and
                ``psidot`` are usually the previous command's.
            vehicles: (E, V, 4) other vehicles (x, y, vx, vy) [m, m/s]; V may be 0.
            vehicle_mask: (E, V) bool, True for real vehicles; ``None`` = all real.
            warm: the previous step's final iterates moved to this step (see :meth:`score`).

        Returns:
            A :class:`Plan`. Where no candidate is feasible the fallback of :meth:`command`
            runs: the least-infeasible candidate's path if it is drivable (none of the
            :data:`UNDRIVABLE` bits: kinematically sound and on the road, it only comes too
            close to an obstacle or exceeds ``a_max``), else a lane-keeping brake; either way
            it never accelerates and brakes at least as hard as a conflict ahead needs.

        Raises:
            ValueError: bad input (see :meth:`build_problem`).
        """
        return self.plan_problem(self.build_problem(ego, vehicles, vehicle_mask), warm=warm)

    @torch.no_grad()
    def plan_problem(self, problem: ProblemBatch, selector: Optional[Selector] = None, *,
                     warm: Optional[WarmStart] = None) -> Plan:
        """One MPC step for a problem batch built by the caller (e.g. :meth:`build_problem` with
        goals of its own added), with an optional selection rule: :meth:`score` then :meth:`choose`.

        Args:
            problem: E problems with G goals each.
            selector: ``selector(result, cost, violation) -> Selection`` over the (E, G)
                candidates (``violation`` ranks infeasible ones, see :meth:`plan`); default
                :func:`mmpc.ranking.select_best`, the feasible candidate of lowest meta cost (ties
                within :attr:`MPCConfig.tie_tolerance` to the smallest lateral move).
                A selection with ``feasible`` False gets :meth:`plan`'s fallback.
            warm: see :meth:`score`.

        Returns:
            A :class:`Plan`, as :meth:`plan`.
        """
        return self.choose(problem, self.score(problem, warm), selector)

    @torch.no_grad()
    def score(self, problem: ProblemBatch, warm: Optional[WarmStart] = None) -> Scored:
        """Solve every (problem, goal) of the batch and score it: road filter, escapes from a
        start inside an ellipse (:meth:`_allow_escape`), meta cost and the ranking of infeasible
        candidates. One optimizer call; :meth:`choose` may then pick from the same scores more
        than once (e.g. for several agents' choices). ``warm``: the previous step's final iterates
        (:attr:`mmpc.SolveResult.warm`, :meth:`mmpc.BatchOptimizer.shifted` to this step) to
        start from with :attr:`MPCConfig.warm_iterations` iterations; ignored when that is 0 or
        its shapes are not this batch's (another goal count)."""
        start = None if self.fixed_shapes else time.perf_counter()
        fixed = {"fixed_shapes": True} if self.fixed_shapes else {}
        if warm is None or self.config.warm_iterations == 0 or warm.position.shape[:2] != problem.goals.shape[:2]:
            result = self.optimizer(problem, **fixed)
        else:
            if self.fixed_shapes:
                fixed["cold_capacity"] = max(1, math.ceil(COLD_SHARE * problem.ego.shape[0]))
            result = self.optimizer(problem, warm=warm, warm_iterations=self.config.warm_iterations, **fixed)
        compile_ms = self.optimizer.last_compile_ms
        solve_ms = float("nan")
        if start is not None:
            if result.status.is_cuda:
                torch.cuda.synchronize(result.status.device)
            solve_ms = (time.perf_counter() - start) * 1e3 - compile_ms
        result, road_excess = self._keep_on_road(result, problem.ego)
        result = self._allow_escape(result, problem)
        cost = self.meta_cost(result.trajectories, self.road)
        return Scored(result, cost, self._violation(result, road_excess), solve_ms, compile_ms)

    def select(self, problem: ProblemBatch, scored: Scored) -> Selection:
        """The MPC's own choice among the candidates of ``problem`` from its :meth:`score`: the
        feasible candidate of lowest meta cost (ties broken as :meth:`tie_break`), else the least
        violation."""
        result = scored.result
        return select_best(result, scored.cost, self.optimizer.config, violation=scored.violation,
                           **self.tie_break(result.trajectories, problem.ego))

    def _axes(self, problem: ProblemBatch, dtype: torch.dtype) -> tuple[float, float] | torch.Tensor:
        """The ellipse semi-axes ``problem``'s obstacles were solved with: its (E, M, 2)
        :attr:`mmpc.ProblemBatch.obstacle_axes` in ``dtype``, else the optimizer's (a, b)."""
        return self.ellipse if problem.obstacle_axes is None else problem.obstacle_axes.to(dtype)

    @torch.no_grad()
    def choose(self, problem: ProblemBatch, scored: Scored, selector: Optional[Selector] = None) -> Plan:
        """The :class:`Plan` of ``problem`` from its :meth:`score`: select a candidate per problem
        (``selector``, as :meth:`plan_problem`) and the commands that execute it (:meth:`command`)."""
        result = scored.result
        selection = self.select(problem, scored) if selector is None else selector(result, scored.cost, scored.violation)
        trajectory = result.trajectories.select(selection.index)
        rows = torch.arange(result.status.shape[0], device=result.status.device)
        drivable = (result.status[rows, selection.index] & int(UNDRIVABLE)) == 0
        acceleration, steering, heading_rate = self.command(
            problem.ego, trajectory, selection.feasible, drivable=drivable, obstacles=problem.obstacles,
            mask=problem.obstacle_mask,
        )
        return Plan(
            problem, result, scored.cost, selection, trajectory, acceleration, steering, heading_rate, scored.solve_ms,
            scored.compile_ms,
        )

    def command(
        self,
        ego: torch.Tensor,
        trajectory: Trajectories,
        feasible: torch.Tensor,
        *,
        drivable: Optional[torch.Tensor] = None,
        obstacles: Optional[torch.Tensor] = None,
        mask: Optional[torch.Tensor] = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The commands that execute E chosen plans (any planner's, e.g. the baselines').

        Rows whose plan is not feasible get the fallback: the plan's heading rate where it is
        ``drivable``, else the lane-keeping heading rate; the plan's acceleration capped at 0
        where drivable, else ``-brake_deceleration``; and in both cases at most the
        :func:`mmpc.stopping.conflict_deceleration` for the ``obstacles`` ahead in the ego's
        lane (within half a lane width of its lateral position), which keeps a vehicle length
        (``wheelbase``, highway-env's) plus ``stop_gap`` to them. A car beside does not count
        (braking for the planner's wider ellipse stalled lane changes; see
        docs/experiments/2026-11-23-fail-safe.md).

        Args:
            ego: (E, 6) current states.
            trajectory: the chosen plans, every field (E, N), at ``trajectory.times``.
            feasible: (E,) bool, the plan is feasible.
            drivable: (E,) bool, an infeasible plan may still be driven; ``None``: none may.
            obstacles: (E, M, N, 2) predicted obstacle centres at ``trajectory.times`` [m];
                ``None``: the fallback brakes for none.
            mask: (E, M) bool, present obstacles; ``None``: all.

        Returns:
            acceleration (E,) [m/s^2] and heading rate (E,) [rad/s] averaged over the command
            window, and steering ``atan(L psidot / v)`` (E,) [rad] clamped to ``max_steering``,
            as (acceleration, steering, heading_rate).
        """
        acceleration, heading_rate = self._command(trajectory)
        drivable = torch.zeros_like(feasible) if drivable is None else drivable
        acceleration, heading_rate = self._fallback(
            ego, trajectory, feasible, drivable, acceleration, heading_rate, obstacles, mask
        )
        return acceleration, self.steering(ego, heading_rate), heading_rate

    def candidate_commands(self, ego: torch.Tensor, trajectories: Trajectories) -> tuple[torch.Tensor, torch.Tensor]:
        """The commands that would start executing each of G candidates of E problems, as
        :meth:`command` executes a feasible one: (acceleration [m/s^2], steering [rad]), (E, G) each.

        Args:
            ego: (E, 6) current states.
            trajectories: the candidates, every field (E, G, N).
        """
        num_problems, num_goals = trajectories.x.shape[:2]
        flat = Trajectories(trajectories.times, *(field.flatten(0, 1) for field in trajectories[1:]))
        acceleration, heading_rate = self._command(flat)
        steering = self.steering(ego.repeat_interleave(num_goals, dim=0), heading_rate)
        return acceleration.view(num_problems, num_goals), steering.view(num_problems, num_goals)

    def steering(self, ego: torch.Tensor, heading_rate: torch.Tensor) -> torch.Tensor:
        """(E,) steering angle ``atan(L psidot / v)`` [rad] that turns the (E, 6) egos at
        ``heading_rate`` (E,) [rad/s], clamped to ``max_steering`` (speeds below 1 m/s count as 1)."""
        speed = ego[:, EGO_V].clamp_min(1.0)
        steering = torch.atan(self.wheelbase * heading_rate / speed)
        return steering.clamp(-self.config.max_steering, self.config.max_steering)

    def lateral_band(self, ego: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(E,) lowest and highest y [m] a plan from the ego states ``ego`` (E, 6) may reach:
        ``road_margin`` inside the road's edges, widened to the ego's own y where it is already
        beyond (a plan may bring the ego back, not push it farther out)."""
        left, right = self.road.bounds
        y0 = ego[:, EGO_Y]
        return torch.clamp(y0, max=left + self.config.road_margin), torch.clamp(y0, min=right - self.config.road_margin)

    def _keep_on_road(self, result: SolveResult, ego: torch.Tensor) -> tuple[SolveResult, torch.Tensor]:
        """Flag candidates that leave :meth:`lateral_band` as :attr:`Status.OFF_ROAD`.

        Returns:
            the result with status and feasibility updated, and (E, G) the largest distance
            beyond the allowed band [m].
        """
        low, high = self.lateral_band(ego)
        y = result.trajectories.y
        excess = torch.maximum(low[:, None] - y.amin(dim=-1), y.amax(dim=-1) - high[:, None]).clamp_min(0.0)
        status = result.status | (excess > 0).to(result.status.dtype) * int(Status.OFF_ROAD)
        return result._replace(status=status, feasible=status == 0), excess

    def _allow_escape(self, result: SolveResult, problem: ProblemBatch) -> SolveResult:
        """Clear :attr:`Status.START_IN_COLLISION` and :attr:`Status.OBSTACLE` of the candidates
        that start at most :data:`ESCAPE_DEPTH` inside an obstacle's ellipse and never go deeper
        into it than at the start (and keep clear of every other one, to the optimizer's tolerance).

        An ego riding a plan's ellipse boundary starts the next step slightly inside it (tracking
        error); every candidate shares that start, and without this rule each is infeasible and
        the ego drives the never-accelerating fallback. Deeper starts stay infeasible: there a
        path along the ellipse's contour can reach the corners of the cars' rectangles.
        """
        inside = (result.status & int(Status.START_IN_COLLISION)) != 0
        if not self.fixed_shapes and not bool(inside.any()):  # most steps: nobody starts inside
            return result
        obstacles = problem.obstacles.to(result.trajectories.x.dtype)
        axes = self._axes(problem, obstacles.dtype)
        distance = squared_obstacle_distance(result.trajectories, obstacles, axes).sqrt()  # (E, G, M, N)
        start = distance[..., :1]
        floor = start.clamp_max(1.0) - self.optimizer.config.obstacle_tolerance
        mask = problem.obstacle_mask
        if mask is None:
            mask = torch.ones(obstacles.shape[:2], dtype=torch.bool, device=obstacles.device)
        never_deeper = (distance >= floor).all(dim=-1) & (start[..., 0] >= 1.0 - ESCAPE_DEPTH)  # (E, G, M)
        clear = (never_deeper | ~mask[:, None, :]).all(dim=-1)  # (E, G)
        obstacle_bits = int(Status.START_IN_COLLISION | Status.OBSTACLE)
        escaping = inside & clear & ((result.status & ~obstacle_bits) == 0)
        status = torch.where(escaping, result.status & ~obstacle_bits, result.status)
        return result._replace(status=status, feasible=status == 0)

    def _violation(self, result: SolveResult, road_excess: torch.Tensor) -> torch.Tensor:
        """(E, G) ranking of infeasible candidates: drivable ones first, then the optimizer's
        :func:`constraint_violation` plus the road excess (a lane width beyond the edge weighs like
        a full overlap with an obstacle)."""
        undrivable = (result.status & int(UNDRIVABLE)) != 0
        violation = constraint_violation(result, self.optimizer.config) + 10.0 * road_excess / self.road.lane_width
        return violation + 1e3 * undrivable.to(violation.dtype)

    def _command(self, trajectory: Trajectories) -> tuple[torch.Tensor, torch.Tensor]:
        """Tangential acceleration and heading rate averaged over the command window."""
        times = trajectory.times
        window = times <= self.config.command_window + 1e-9
        window[:2] = True  # at least two samples
        speed = torch.hypot(trajectory.xdot, trajectory.ydot).clamp_min(1e-3)
        tangential = (trajectory.xdot * trajectory.xddot + trajectory.ydot * trajectory.yddot) / speed
        if self.fixed_shapes:  # the window's samples by weight, not by index: no shape read from the times
            weights = window.to(tangential.dtype) / window.sum()
            return tangential @ weights, trajectory.psidot @ weights
        return tangential[:, window].mean(dim=1), trajectory.psidot[:, window].mean(dim=1)

    def _fallback(
        self,
        ego: torch.Tensor,
        trajectory: Trajectories,
        feasible: torch.Tensor,
        drivable: torch.Tensor,
        acceleration: torch.Tensor,
        heading_rate: torch.Tensor,
        obstacles: Optional[torch.Tensor],
        mask: Optional[torch.Tensor],
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The commands of :meth:`command` where the plan is not feasible."""
        lane_y = self.road.lane_index(ego[:, EGO_Y]).to(ego.dtype) * self.road.lane_width
        desired_heading = torch.atan(-0.25 * (ego[:, EGO_Y] - lane_y)).clamp(-0.2, 0.2)
        keep_lane = 1.0 * (desired_heading - ego[:, EGO_PSI])
        fallback_acceleration = torch.where(drivable, acceleration.clamp_max(0.0), -self.config.brake_deceleration)
        if obstacles is not None and obstacles.shape[1] > 0:
            mask = torch.ones(obstacles.shape[:2], dtype=torch.bool, device=obstacles.device) if mask is None else mask
            needed = conflict_deceleration(ego, obstacles, mask, trajectory.times, standoff=self.wheelbase + self.config.stop_gap,
                                           max_deceleration=self.config.max_deceleration, half_width=0.5 * self.road.lane_width)
            fallback_acceleration = torch.minimum(fallback_acceleration, needed)
        # Near rest, brake only as much as stops within the command window (never into reverse).
        fallback_acceleration = torch.maximum(fallback_acceleration, -ego[:, EGO_V] / self.config.command_window)
        return (
            torch.where(feasible, acceleration, fallback_acceleration),
            torch.where(feasible | drivable, heading_rate, keep_lane),
        )
