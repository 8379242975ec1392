"""The safety layer: an agent's goal command -> a kinematically feasible, collision-avoiding plan.

An agent does not steer; it names a *goal command* ``(y, v)``: a target lateral position y [m]
and a target average speed v [m/s]. At every simulation frame the layer turns the command
into the goal ``(x_ego + v * t_f, y)`` (t_f the optimizer's horizon), puts it first in the
batch, ahead of the scenario's standard goals, and solves E environments x (1 + G0) goals in
ONE optimizer call (:meth:`mmpc.MPC.plan_problem`). The executed candidate follows the agent
(:func:`follow_agent`):

1. the agent's candidate, if it is feasible;
2. otherwise the feasible candidate nearest to the agent's goal, in
   ``hypot(dv / speed_scale, dy / lane_width)`` (an *intervention*);
3. otherwise the MPC's fallback (the least-infeasible candidate if it is drivable, else a
   lane-keeping brake; also an intervention).

The layer also measures, for observations, how every goal of the discrete grid fares at the
current state (:meth:`SafetyLayer.decision_solve`, :meth:`SafetyLayer.features`). With the
scenario's warm starts (:attr:`mmpc.MPCConfig.warm_iterations`) each environment's decision solve
starts from its last one, one decision period earlier (:class:`mmpc.warm.WarmStarts`), and a
frame's solve (a frame's plan, the rows replanned between decisions) from the same environment's
solve one frame earlier: the decision's candidates at the first frame after a decision.

Replanning (:attr:`SafeEnvConfig.replan`): ``"frame"`` solves at every frame of an agent step;
``"decision"`` solves at the agent's decision only and tracks the chosen plan between decisions
(:mod:`mmpc.tracking`), replanning a row at once where the plan held runs into an obstacle as
predicted now, the ego has left it, or no candidate was feasible (:meth:`SafetyLayer.frame`).
With discrete goals the decision's frame is taken from the solve that made the observation's
solver features (the goal grid plus the standard goals at the same state), in either mode.
With :attr:`SafeEnvConfig.expert_action` one more discrete action drives the candidate the MPC
expert would choose from that solve.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Optional

import numpy as np
import torch

from mmpc.drivers import Observation
from mmpc.drivers.verified import guarded_command
from mmpc.mpc import MPC, Plan, Scored, Selector
from mmpc.problem import EGO_X, EGO_Y, ProblemBatch
from mmpc.ranking import Selection
from mmpc.result import SolveResult, Trajectories
from mmpc.rl.config import SafeEnvConfig
from mmpc.scenario import ScenarioConfig, build_mpc
from mmpc.tracking import needs_replan, plan_clearance, track
from mmpc.verify import Guard, Verifier
from mmpc.warm import WarmRound, WarmStarts

#: Solver features per goal of the grid: feasible flag, squashed meta cost, clearance.
FEATURES_PER_GOAL = 3


def follow_agent(agent_index: torch.Tensor, goals: torch.Tensor, speed_scale: float, horizon: float, lane_width: float) -> Selector:
    """A selection rule for :meth:`mmpc.MPC.plan_problem` that follows the agent's goal.

    Args:
        agent_index: (E,) long, which of the G goals of each problem is the agent's.
        goals: (E, G, 2) the goals of the batch [m].
        speed_scale: a lane weighs like this difference of average speed [m/s].
        horizon: the optimizer's horizon t_f [s] (goal x differences / t_f = speed differences).
        lane_width: [m].

    Returns:
        ``selector(result, cost, violation) -> Selection``: the agent's goal where feasible,
        else the nearest feasible goal, else the least violation (``feasible`` False).
    """

    def select(result: SolveResult, cost: torch.Tensor, violation: torch.Tensor) -> Selection:
        feasible = result.feasible
        rows = torch.arange(feasible.shape[0], device=feasible.device)
        index = agent_index.to(feasible.device)
        target = goals[rows, index]  # (E, 2)
        dv = (goals[..., 0] - target[:, None, 0]) / (horizon * speed_scale)
        dy = (goals[..., 1] - target[:, None, 1]) / lane_width
        distance = torch.where(feasible, torch.hypot(dv, dy), torch.full_like(dv, math.inf))
        any_feasible = feasible.any(dim=1)
        chosen = torch.where(
            feasible[rows, index], index, torch.where(any_feasible, distance.argmin(dim=1), violation.argmin(dim=1))
        )
        return Selection(index=chosen, cost=cost[rows, chosen], feasible=any_feasible)

    return select


class SafePlan(NamedTuple):
    """One frame of the safety layer for E environments.

    Fields:
        plan: the MPC's :class:`mmpc.Plan` over (E, 1 + G0) candidates, the agent's first.
        agent_feasible: (E,) bool, the agent's own candidate was feasible and is executed.
        intervention: (E,) bool, ``~agent_feasible``: another candidate or the fallback drove.
        fallback: (E,) bool, no candidate was feasible (the MPC's fallback drove).
        feasible_goals: (E,) long, feasible candidates, the agent's included.
        commands: (E, 2) the agents' goal commands ``(y [m], v [m/s])``, held over the agent step.
        agent_index: (E,) long, the agent's candidate among the plan's (0 where the layer solved
            the agent's goal first; a :class:`DecisionSolve`'s column where taken from one).
    """

    plan: Plan
    agent_feasible: torch.Tensor
    intervention: torch.Tensor
    fallback: torch.Tensor
    feasible_goals: torch.Tensor
    commands: torch.Tensor
    agent_index: torch.Tensor

    def residuals(self) -> torch.Tensor:
        """(E, 3) the executed candidate's obstacle, acceleration and non-holonomic residuals."""
        result, executed = self.plan.result, self.plan.selection.index
        rows = torch.arange(executed.shape[0], device=executed.device)
        return torch.stack([result.residual_obstacle[rows, executed], result.residual_acceleration[rows, executed],
                            result.residual_nonholonomic[rows, executed]], dim=1)


class FrameStarts(NamedTuple):
    """Warm starts of one agent step's frame solves (:meth:`SafetyLayer.frame_starts`): each
    environment's solve one frame before, its goals named by slot.

    Fields:
        store: the solves kept (:class:`mmpc.warm.WarmStarts`, one frame period apart).
        agent_slots: (E,) long, the slot of each agent's goal: its column in the decision solve,
            or -1 (a goal no decision solve had, e.g. a continuous one).
    """

    store: WarmStarts
    agent_slots: torch.Tensor

    def take(self, rows: torch.Tensor) -> "FrameStarts":
        """The same store, for the rows ``rows`` (long, into E)."""
        return FrameStarts(self.store, self.agent_slots[rows.to(self.agent_slots.device)])


class DecisionSolve(NamedTuple):
    """One solve of the discrete goal grid and the standard goals at E states
    (:meth:`SafetyLayer.decision_solve`): the observation's solver features, and with discrete
    goals the candidates of the agent's next decision (:meth:`SafetyLayer.decide`).

    Fields:
        problem: E problems, goals (E, A + G0, 2): the grid's A first, then the standard goals.
        scored: the candidates solved and scored.
        ids: (E,) long, the environments' ids (:attr:`mmpc.drivers.Observation.env_ids`).
        expert: (E,) long, the candidate the MPC expert would drive (``expert_action``; else None).
    """

    problem: ProblemBatch
    scored: Scored
    ids: torch.Tensor
    expert: Optional[torch.Tensor] = None


class HeldPlan(NamedTuple):
    """The plans the layer executes between solves, one per environment (``replan: decision``).

    Fields:
        trajectory: the plans, every field (E, N), at ``trajectory.times`` (N,) [s].
        planned_at: (E,) time of the agent step at which each was made [s].
        valid: (E,) bool, a feasible candidate (False: the fallback drove; replan every frame).
        intervention, agent_feasible: (E,) bool, as in :class:`SafePlan`, of the solve that made it.
        feasible_goals: (E,) long, of that solve.
        residuals: (E, 3) the plan's residuals (:meth:`SafePlan.residuals`).
    """

    trajectory: Trajectories
    planned_at: torch.Tensor
    valid: torch.Tensor
    intervention: torch.Tensor
    agent_feasible: torch.Tensor
    feasible_goals: torch.Tensor
    residuals: torch.Tensor

    def take(self, index: torch.Tensor) -> "HeldPlan":
        """The plans of the rows ``index`` (long or bool over E, on any device), e.g. those of
        the environments still running."""
        if isinstance(index, torch.Tensor):
            index = index.to(self.planned_at.device)
        trajectory = Trajectories(self.trajectory.times, *(field[index] for field in self.trajectory[1:]))
        return HeldPlan(trajectory, *(field[index] for field in self[1:]))


class FrameControl(NamedTuple):
    """What the layer executes at one frame of E environments (:meth:`SafetyLayer.frame`).

    Fields:
        acceleration, steering: (E,) the commands [m/s^2, rad].
        intervention, fallback, agent_feasible: (E,) bool, as in :class:`SafePlan`, of the plan executed.
        feasible_goals: (E,) long, feasible candidates of the solve behind the plan executed.
        residuals: (E, 3) the executed plan's residuals.
        solved: (E,) bool, rows a solve served at this frame (the others tracked a held plan).
        solve_ms: wall time of this frame's optimizer call [ms] (0 without one).
        held: the plans to hold for the next frame.
        plan: the plan every row executes when all of them execute a fresh one (``None`` where
            some tracked a held plan).
        verified, failsafe: (E,) bool, with ``verify``: the command executed verified; nothing
            verified and the stored fail-safe drove (``None`` without ``verify``).
    """

    acceleration: torch.Tensor
    steering: torch.Tensor
    intervention: torch.Tensor
    fallback: torch.Tensor
    agent_feasible: torch.Tensor
    feasible_goals: torch.Tensor
    residuals: torch.Tensor
    solved: torch.Tensor
    solve_ms: float
    held: HeldPlan
    plan: Optional[SafePlan] = None
    verified: Optional[torch.Tensor] = None
    failsafe: Optional[torch.Tensor] = None

    def host(self) -> "FrameControl":
        """The per-environment fields (commands, flags, counts, residuals) on the CPU, one copy
        each; ``held`` stays where the layer computes."""
        names = ("acceleration", "steering", "intervention", "fallback", "agent_feasible", "feasible_goals", "residuals",
                 "solved", "verified", "failsafe")
        return self._replace(**{name: getattr(self, name).cpu() for name in names if getattr(self, name) is not None})


def observation_rows(observation: Observation, rows: torch.Tensor) -> Observation:
    """The road-frame state of the environments ``rows`` (kinematics left out), on the
    observation's device."""
    rows = rows.to(observation.ego.device)
    mask = None if observation.vehicle_mask is None else observation.vehicle_mask[rows]
    ids = observation.ids()[rows]
    return Observation(observation.ego[rows], observation.vehicles[rows], mask, None, ids)


class SafetyLayer:
    """Goal commands of E agents -> safe plans, one optimizer call per frame for all of them.

    Args:
        mpc: the scenario's MPC (optimizer, standard goals, meta cost, road).
        config: the environment settings (goal grid, action ranges, intervention distance).
        warm_starts: warm-start the decision solves from each environment's last one (when the
            MPC's config asks for warm starts; one decision period apart: ``decision_frames`` x
            the MPC's control period), and a frame's solve from the solve one frame before (the
            decision's candidates at the first frame after it). The caller then names its
            environments consistently (:attr:`mmpc.drivers.Observation.env_ids`), solves every
            one at each decision and calls :meth:`forget` for those that start a new episode.
        verifier: the check of ``config.verify`` (:meth:`mmpc.verify.Verifier.for_scenario`);
            the caller names its environments consistently (the stored fail-safes are kept per id)
            and calls :meth:`forget` as for warm starts. :meth:`for_scenario` makes both.

    The layer computes on its MPC's device (:attr:`device`): the observations, egos, actions and
    commands it is given elsewhere (highway-env's CPU tensors, SB3's numpy actions) are moved
    there at its entry points, and what it returns lies there, except :meth:`features` (numpy).

    Example:
        >>> import torch
        >>> from mmpc.rl.config import RL_SCENARIO, SafeEnvConfig
        >>> from mmpc.scenario import load_scenario
        >>> from mmpc.drivers import Observation
        >>> from mmpc.problem import ego_state
        >>> layer = SafetyLayer.for_scenario(load_scenario(RL_SCENARIO), SafeEnvConfig())
        >>> ego = ego_state(0.0, 4.0, 0.0, 25.0)
        >>> observation = Observation(ego, torch.tensor([[[60.0, 4.0, 20.0, 0.0]]]))
        >>> commands = layer.discrete_commands(ego, torch.tensor([8]))  # right lane at 15 m/s
        >>> safe = layer.plan(observation, commands)
        >>> bool(safe.agent_feasible[0]), tuple(commands[0].tolist())
        (True, (8.0, 15.0))
    """

    def __init__(self, mpc: MPC, config: SafeEnvConfig, *, warm_starts: bool = True,
                 verifier: Optional[Verifier] = None) -> None:
        if config.verify and verifier is None:
            raise ValueError("`config.verify` needs the scenario's `verifier` (SafetyLayer.for_scenario builds it)")
        self.mpc = mpc
        self.config = config
        #: the check of every frame's command (``config.verify``); ``None`` without
        self.guard = Guard(verifier) if config.verify else None
        period = None if mpc.control_period is None else mpc.control_period * config.decision_frames
        warm = warm_starts and mpc.config.warm_iterations > 0 and period is not None
        #: the decision solves' warm starts; ``None`` where the caller asked for none
        self.warm_starts = WarmStarts(mpc, period) if warm else None
        #: the frame solves warm-start (:meth:`frame_starts`)
        self.warm_frames = warm
        self.road = mpc.road
        self.horizon = mpc.optimizer.config.horizon
        offsets, speeds = np.meshgrid(np.asarray(config.lane_offsets), np.asarray(config.speeds), indexing="ij")
        device = mpc.optimizer.device
        self._grid_offsets = torch.as_tensor(offsets.reshape(-1), dtype=torch.long, device=device)  # (A,)
        self._grid_speeds = torch.as_tensor(speeds.reshape(-1), dtype=mpc.optimizer.dtype, device=device)  # (A,)
        self._env_ids_given = 0

    @classmethod
    def for_scenario(cls, scenario: ScenarioConfig, config: SafeEnvConfig, *, warm_starts: bool = True) -> "SafetyLayer":
        """The layer of ``scenario``'s MPC, with its verifier where ``config.verify`` asks for one."""
        verifier = Verifier.for_scenario(scenario) if config.verify else None
        return cls(build_mpc(scenario), config, warm_starts=warm_starts, verifier=verifier)

    def new_env_id(self) -> int:
        """An environment id no other environment of this layer was given (0, 1, 2, ...): the key of
        its warm starts and stored fail-safe (:class:`mmpc.rl.engine.SafeEnvs`)."""
        self._env_ids_given += 1
        return self._env_ids_given - 1

    def forget(self, ids: Optional[torch.Tensor] = None) -> None:
        """Environments ``ids`` (long tensor; ``None``: all) start new episodes: their warm starts
        and stored fail-safes are dropped."""
        if self.warm_starts is not None:
            self.warm_starts.reset() if ids is None else self.warm_starts.forget(ids)
        if self.guard is not None:
            self.guard.reset() if ids is None else self.guard.forget(ids.tolist())

    @property
    def device(self) -> torch.device:
        """Where the layer computes: its MPC's optimizer's device."""
        return self.mpc.optimizer.device

    @property
    def num_discrete_goals(self) -> int:
        """A, the size of the discrete goal grid."""
        return self._grid_offsets.numel()

    @property
    def num_actions(self) -> int:
        """Discrete actions: the grid's A goals, then (``expert_action``) the expert's choice, action A."""
        return self.config.num_actions

    # ------------------------------------------------------------------ actions -> goal commands

    def discrete_commands(self, ego: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Discrete actions -> goal commands.

        Args:
            ego: (E, 6) ego states at decision time (any device).
            actions: (E,) indices into the grid ``lane_offsets x speeds`` (offset-major).

        Returns:
            (E, 2) commands on the layer's device: target lane centre y [m] (the ego's nearest
            lane plus the offset, clamped to the road) and target average speed [m/s].
        """
        actions = torch.as_tensor(actions, dtype=torch.long).reshape(-1)
        if actions.shape[0] != ego.shape[0]:
            raise ValueError(f"`actions` must have shape ({ego.shape[0]},); got {tuple(actions.shape)}")
        if bool(((actions < 0) | (actions >= self.num_discrete_goals)).any()):
            raise ValueError(f"discrete actions must lie in [0, {self.num_discrete_goals}); got {actions.tolist()}")
        ego, actions = ego.to(self.device), actions.to(self.device)
        return self._grid_commands(ego)[torch.arange(ego.shape[0], device=self.device), actions]

    def continuous_commands(self, ego: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Continuous actions in [-1, 1]^2 (clipped) -> goal commands (E, 2).

        ``a[0]``: lateral target, the ego lane's centre plus ``a[0] * lateral_range`` lane
        widths, clamped to the road's lane centres; ``a[1]``: speed, linear onto ``speed_range``.
        ``ego`` and ``actions`` may lie on any device; the commands lie on the layer's.
        """
        actions = torch.as_tensor(actions, dtype=ego.dtype).reshape(-1, 2)
        if actions.shape[0] != ego.shape[0]:
            raise ValueError(f"`actions` must have shape ({ego.shape[0]}, 2); got {tuple(actions.shape)}")
        if not bool(torch.isfinite(actions).all()):
            raise ValueError(f"continuous actions must be finite; got {actions.tolist()}")
        ego, actions = ego.to(self.device), actions.to(self.device)
        actions = actions.clamp(-1.0, 1.0)
        lane_y = self.road.lane_index(ego[:, EGO_Y]).to(ego.dtype) * self.road.lane_width
        y = (lane_y + actions[:, 0] * self.config.lateral_range * self.road.lane_width).clamp(0.0, self.road.right_lane_y)
        low, high = self.config.speed_range
        speed = low + 0.5 * (actions[:, 1] + 1.0) * (high - low)
        return torch.stack([y, speed], dim=1)

    def _grid_commands(self, ego: torch.Tensor) -> torch.Tensor:
        """(E, A, 2) commands of the whole discrete grid at the egos' current lanes."""
        lanes = self.road.lane_index(ego[:, EGO_Y])[:, None] + self._grid_offsets[None]  # (E, A)
        y = lanes.clamp(0, self.road.num_lanes - 1).to(ego.dtype) * self.road.lane_width
        speed = self._grid_speeds.to(ego.dtype)[None].expand_as(y)
        return torch.stack([y, speed], dim=-1)

    def goals(self, ego: torch.Tensor, commands: torch.Tensor) -> torch.Tensor:
        """Goal commands (E, C, 2) -> goal positions (E, C, 2): ``(x_ego + v t_f, y)`` [m]."""
        x = ego[:, EGO_X, None] + commands[..., 1] * self.horizon
        return torch.stack([x, commands[..., 0]], dim=-1)

    # ------------------------------------------------------------------ planning

    def plan(self, observation: Observation, commands: torch.Tensor, starts: Optional[FrameStarts] = None) -> SafePlan:
        """One frame for E environments: the agents' goals plus the standard goals, one solve.

        Args:
            observation: the E environments' road-frame state (any device).
            commands: (E, 2) goal commands ``(y [m], v [m/s])``.
            starts: the agent step's frame warm starts (:meth:`frame_starts`), its E rows': the
                solve starts from each environment's solve one frame before, where that solved the
                same goals, and is kept for the next frame. ``None``: a cold solve, not kept.

        Returns:
            A :class:`SafePlan`; ``plan.acceleration`` / ``plan.steering`` are the commands to apply.
        """
        observation = observation.to(self.device)
        commands = torch.as_tensor(commands, dtype=self.mpc.optimizer.dtype, device=self.device)
        if commands.shape != (observation.num_envs, 2):
            raise ValueError(f"`commands` must have shape ({observation.num_envs}, 2); got {tuple(commands.shape)}")
        problem = self.mpc.build_problem(observation.ego, observation.vehicles, observation.vehicle_mask)
        goals = torch.cat([self.goals(problem.ego, commands[:, None]), problem.goals], dim=1)
        problem = problem._replace(goals=goals)
        agent = torch.zeros(observation.num_envs, dtype=torch.long, device=self.device)
        if starts is None:
            scored = self.mpc.score(problem)
        else:
            slots = self._frame_slots(starts.agent_slots.to(self.device), problem.num_goals - 1)
            scored = starts.store.score(observation.ids(), problem.ego, problem, slots)
        return self._safe_plan(self.mpc.choose(problem, scored, self._selector(agent, problem)), agent, commands)

    def frame_starts(self, count: int, solve: Optional[DecisionSolve] = None,
                     agent_index: Optional[torch.Tensor] = None) -> Optional[FrameStarts]:
        """Warm starts for the frame solves of one agent step of ``count`` environments, or ``None``
        where the layer solves cold. With the step's decision ``solve`` and the agents' candidates
        ``agent_index`` (E,) in it (:meth:`decide`), the first frame after the decision starts from
        those candidates; else from cold."""
        if not self.warm_frames:
            return None
        store = WarmStarts(self.mpc, self.mpc.control_period)
        if solve is None:
            return FrameStarts(store, torch.full((count,), -1, dtype=torch.long, device=self.device))  # no solve had it
        columns = self._frame_slots(agent_index, solve.problem.num_goals - self.num_discrete_goals)
        cold = torch.zeros_like(agent_index)
        store.keep(solve.ids, solve.problem.ego, solve.scored.result.take_goals(columns), WarmRound(None, cold, cold),
                   columns)
        return FrameStarts(store, agent_index)

    def _frame_slots(self, agent_slots: torch.Tensor, num_standard_goals: int) -> torch.Tensor:
        """(E, 1 + G0) long slots naming a frame solve's goals: the agent's goal ``agent_slots`` (E,)
        (its column in a :class:`DecisionSolve`; negative: a goal no decision solve had), then the
        G0 standard goals as the decision solve's columns."""
        standard = self.num_discrete_goals + torch.arange(num_standard_goals, device=agent_slots.device)
        return torch.cat([agent_slots[:, None], standard.expand(agent_slots.shape[0], -1)], dim=1)

    def needs_decision_solve(self, continuous: bool) -> bool:
        """Whether an agent's observation comes with a :meth:`decision_solve`: for its solver
        features, and for discrete agents with ``replan: decision`` (their plans are taken from it)."""
        return self.config.solver_features or (self.config.replan == "decision" and not continuous)

    def decision_solve(self, observation: Observation, *, warm: bool = True) -> DecisionSolve:
        """ONE solve of the discrete goal grid (at the egos' current lanes) and the standard goals
        for E states (``observation`` on any device): the observation's solver features, and the
        candidates of a discrete decision. ``warm`` False: a solve apart from the decisions (the
        last states of episodes that ended), cold and not kept for the next decision's warm start."""
        observation = observation.to(self.device)
        problem = self.mpc.build_problem(observation.ego, observation.vehicles, observation.vehicle_mask)
        grid = self.goals(problem.ego, self._grid_commands(problem.ego))
        problem = problem._replace(goals=torch.cat([grid, problem.goals], dim=1))
        if self.warm_starts is None or not warm:
            scored = self.mpc.score(problem)
        else:
            scored = self.warm_starts.score(observation.ids(), problem.ego, problem)
        expert = self.mpc.select(problem, scored).index if self.config.expert_action else None
        return DecisionSolve(problem, scored, observation.ids(), expert)

    def agent_candidates(self, solve: DecisionSolve, actions: torch.Tensor) -> torch.Tensor:
        """(E,) long, the candidate of a :meth:`decision_solve` each discrete action names: grid
        action i its goal i; the expert action (A) the candidate the MPC would drive (:meth:`mmpc.MPC.select`)."""
        actions = torch.as_tensor(actions, dtype=torch.long).reshape(-1)
        if actions.shape[0] != solve.problem.num_problems:
            raise ValueError(f"`actions` must have shape ({solve.problem.num_problems},); got {tuple(actions.shape)}")
        if bool(((actions < 0) | (actions >= self.num_actions)).any()):
            raise ValueError(f"discrete actions must lie in [0, {self.num_actions}); got {actions.tolist()}")
        actions = actions.to(solve.problem.ego.device)
        if solve.expert is None:
            return actions
        return torch.where(actions == self.num_discrete_goals, solve.expert, actions)

    def _decision_commands(self, solve: DecisionSolve, index: torch.Tensor) -> torch.Tensor:
        """(E, 2) goal commands ``(y [m], v [m/s])`` of the candidates ``index`` (:meth:`agent_candidates`)
        of a :meth:`decision_solve`: the grid's commands, and for the expert's candidate its goal
        ``(x, y)`` as ``(y, (x - x_ego) / t_f)``."""
        ego = solve.problem.ego
        rows = torch.arange(index.shape[0], device=index.device)
        grid = self._grid_commands(ego)[rows, index.clamp(max=self.num_discrete_goals - 1)]
        goal = solve.problem.goals[rows, index]
        chosen = torch.stack([goal[:, 1], (goal[:, 0] - ego[:, EGO_X]) / self.horizon], dim=1)
        return torch.where((index < self.num_discrete_goals)[:, None], grid, chosen)

    def features(self, solve: DecisionSolve) -> np.ndarray:
        """How every discrete action's candidate fares at the solved states.

        Returns:
            (E, num_actions, 3) float32 numpy features in [0, 1] (the grid's goals, then the expert's
            choice with ``expert_action``): feasible flag, squashed meta cost
            ``m / (m + feature_cost_scale)`` with ``m`` the cost per trajectory sample, and
            clearance ``min(1, d / 3)`` with ``d`` the smallest normalised ellipse distance to
            an obstacle (1/3: touching).
        """
        result = solve.scored.result
        count, device = solve.problem.num_problems, solve.problem.ego.device
        columns = torch.arange(self.num_discrete_goals, device=device).expand(count, -1)
        if solve.expert is not None:
            columns = torch.cat([columns, solve.expert[:, None]], dim=1)
        rows = torch.arange(count, device=device)[:, None]
        feasible = result.feasible[rows, columns].to(torch.float32)
        samples = result.trajectories.x.shape[-1]
        cost = solve.scored.cost[rows, columns].to(torch.float32) / samples
        cost = torch.nan_to_num(cost, nan=math.inf, posinf=math.inf).clamp_min(0.0)
        squashed = torch.where(torch.isinf(cost), torch.ones_like(cost), cost / (cost + self.config.feature_cost_scale))
        distance = torch.nan_to_num(result.min_obstacle_distance[rows, columns].to(torch.float32), nan=0.0, posinf=3.0)
        clearance = (distance / 3.0).clamp(0.0, 1.0)
        return torch.stack([feasible, squashed, clearance], dim=-1).cpu().numpy()  # one copy to the host

    def decide(self, solve: DecisionSolve, actions: torch.Tensor) -> SafePlan:
        """Discrete actions executed from the candidates of a :meth:`decision_solve` at the same
        states (no new solve): the action's candidate where feasible, else as :func:`follow_agent`;
        ``commands`` are the goal commands of the actions' candidates.

        Args:
            solve: the decision solve of the E states the actions were chosen at.
            actions: (E,) long indices into the grid, or A for the expert's choice (``expert_action``).
        """
        index = self.agent_candidates(solve, actions)
        plan = self.mpc.choose(solve.problem, solve.scored, self._selector(index, solve.problem))
        return self._safe_plan(plan, index, self._decision_commands(solve, index))

    def frame(
        self,
        observation: Observation,
        commands: torch.Tensor,
        now: float,
        held: Optional[HeldPlan] = None,
        decided: Optional[SafePlan] = None,
        starts: Optional[FrameStarts] = None,
    ) -> FrameControl:
        """The commands of one frame of an agent step for E environments.

        At the decision (``held`` None) the plan is ``decided`` (:meth:`decide`) or solved now
        (:meth:`plan`). Later frames solve every row again with ``replan: frame``; with
        ``replan: decision`` they track the plan held (:func:`mmpc.tracking.track`) and solve
        only the rows whose plan is no longer safe to follow (:func:`mmpc.tracking.needs_replan`,
        or no feasible candidate), all in one call.

        Args:
            observation: the E environments' road-frame state now (any device).
            commands: (E, 2) the goal commands held over the agent step.
            now: time since the decision [s].
            held: the previous frame's :attr:`FrameControl.held`; ``None`` at the decision.
            decided: the decision's plan from :meth:`decide`, or ``None`` to solve it now.
            starts: the agent step's frame warm starts, its E rows' (:meth:`frame_starts`);
                ``None``: cold solves.
        """
        observation, commands = observation.to(self.device), torch.as_tensor(commands, device=self.device)
        if held is None or self.config.replan == "frame":
            safe = decided if held is None and decided is not None else self.plan(observation, commands, starts)
            control = self._control(safe, now)
        else:
            control = self._follow(observation, commands, now, held, starts)
        return control if self.guard is None else self._guarded(observation, control)

    # ------------------------------------------------------------------ frame pieces

    def _guarded(self, observation: Observation, control: FrameControl) -> FrameControl:
        """``control`` with each command taken only where it verifies (:func:`mmpc.drivers.verified.guarded_command`;
        a fresh plan's other feasible candidates are the alternatives); an override is an intervention."""
        plan = None if control.plan is None else control.plan.plan
        guarded = guarded_command(self.guard, observation, control.acceleration, control.steering, plan, self.mpc)
        return control._replace(acceleration=guarded.acceleration, steering=guarded.steering,
                                intervention=control.intervention | guarded.changed, verified=guarded.verified,
                                failsafe=guarded.failsafe)

    def _selector(self, agent_index: torch.Tensor, problem: ProblemBatch) -> Selector:
        return follow_agent(agent_index, problem.goals, self.config.intervention_speed_scale, self.horizon, self.road.lane_width)

    def _safe_plan(self, plan: Plan, agent_index: torch.Tensor, commands: torch.Tensor) -> SafePlan:
        agent_feasible = plan.selection.feasible & (plan.selection.index == agent_index)
        return SafePlan(plan=plan, agent_feasible=agent_feasible, intervention=~agent_feasible,
                        fallback=~plan.selection.feasible, feasible_goals=plan.result.feasible.sum(dim=1),
                        commands=commands, agent_index=agent_index)

    def _control(self, safe: SafePlan, now: float) -> FrameControl:
        """Execute a fresh plan in every row and hold it."""
        plan = safe.plan
        count, device = plan.acceleration.shape[0], plan.acceleration.device
        residuals = safe.residuals()
        held = HeldPlan(plan.trajectory, torch.full((count,), now, dtype=plan.acceleration.dtype, device=device),
                        plan.selection.feasible,
                        safe.intervention, safe.agent_feasible, safe.feasible_goals, residuals)
        return FrameControl(plan.acceleration, plan.steering, safe.intervention, safe.fallback, safe.agent_feasible,
                            safe.feasible_goals, residuals, torch.ones(count, dtype=torch.bool, device=device), plan.solve_ms, held,
                            safe)

    def _follow(self, observation: Observation, commands: torch.Tensor, now: float, held: HeldPlan,
                starts: Optional[FrameStarts]) -> FrameControl:
        """Track the held plans; solve again (one call) where they are no longer safe to follow."""
        mpc = self.mpc
        ego = observation.ego.to(mpc.optimizer.dtype)
        elapsed = now - held.planned_at
        acceleration, heading_rate, lateral, speed_error = track(
            held.trajectory, elapsed, ego, mpc.config.command_window, self.config.tracking)
        vehicles = observation.vehicles.to(ego.dtype)
        states, mask = mpc.nearest_obstacles(ego, vehicles, observation.vehicle_mask)
        axes = mpc.obstacle_axes(states)  # the ellipses the MPC plans around
        clearance = plan_clearance(held.trajectory, elapsed, states, mask, mpc.predict, mpc.ellipse if axes is None else axes)
        replan = ~held.valid | needs_replan(clearance, lateral, speed_error, mpc.optimizer.config.obstacle_tolerance,
                                            self.config.tracking)
        # fields 0-6 are what is executed; merged row-wise with the rows solved again below
        control = FrameControl(acceleration, mpc.steering(ego, heading_rate), held.intervention,
                               torch.zeros_like(held.valid), held.agent_feasible, held.feasible_goals, held.residuals,
                               replan, 0.0, held)
        rows = replan.nonzero()[:, 0]
        if rows.numel() == 0:
            if starts is not None:  # no solve at this frame: none one frame before the next
                starts.store.reset()
            return control
        fresh = self._control(self.plan(observation_rows(observation, rows), commands[rows],
                                        None if starts is None else starts.take(rows)), now)
        executed = [_scatter_rows(mine, rows, theirs) for mine, theirs in zip(control[:7], fresh[:7])]
        trajectory = Trajectories(held.trajectory.times, *(_scatter_rows(mine, rows, theirs)
                                                           for mine, theirs in zip(held.trajectory[1:], fresh.held.trajectory[1:])))
        kept = HeldPlan(trajectory, *(_scatter_rows(mine, rows, theirs) for mine, theirs in zip(held[1:], fresh.held[1:])))
        return FrameControl(*executed, replan, fresh.solve_ms, kept)


def _scatter_rows(base: torch.Tensor, rows: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """A copy of ``base`` with ``values`` in its rows ``rows``."""
    merged = base.clone()
    merged[rows] = values.to(base.dtype)
    return merged
