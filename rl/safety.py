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
current state (:meth:`SafetyLayer.goal_features`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch

from mmpc.drivers import Observation
from mmpc.mpc import MPC, Plan, Selector
from mmpc.problem import EGO_X, EGO_Y
from mmpc.ranking import Selection
from mmpc.result import SolveResult
from mmpc.rl.config import SafeEnvConfig

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
    """

    plan: Plan
    agent_feasible: torch.Tensor
    intervention: torch.Tensor
    fallback: torch.Tensor
    feasible_goals: torch.Tensor


class SafetyLayer:
    """Goal commands of E agents -> safe plans, one optimizer call per frame for all of them.

    Args:
        mpc: the scenario's MPC (optimizer, standard goals, meta cost, road).
        config: the environment settings (goal grid, action ranges, intervention distance).

    Example:
        >>> import torch
        >>> from mmpc.rl.config import RL_SCENARIO, SafeEnvConfig
        >>> from mmpc.scenario import build_mpc, load_scenario
        >>> from mmpc.drivers import Observation
        >>> from mmpc.problem import ego_state
        >>> layer = SafetyLayer(build_mpc(load_scenario(RL_SCENARIO)), SafeEnvConfig())
        >>> ego = ego_state(0.0, 4.0, 0.0, 25.0)
        >>> observation = Observation(ego, torch.tensor([[[60.0, 4.0, 20.0, 0.0]]]))
        >>> commands = layer.discrete_commands(ego, torch.tensor([8]))  # right lane at 15 m/s
        >>> safe = layer.plan(observation, commands)
        >>> bool(safe.agent_feasible[0]), tuple(commands[0].tolist())
        (True, (8.0, 15.0))
    """

    def __init__(self, mpc: MPC, config: SafeEnvConfig) -> None:
        self.mpc = mpc
        self.config = config
        self.road = mpc.road
        self.horizon = mpc.optimizer.config.horizon
        offsets, speeds = np.meshgrid(np.asarray(config.lane_offsets), np.asarray(config.speeds), indexing="ij")
        self._grid_offsets = torch.as_tensor(offsets.reshape(-1), dtype=torch.long)  # (A,)
        self._grid_speeds = torch.as_tensor(speeds.reshape(-1), dtype=mpc.optimizer.dtype)  # (A,)

    @property
    def num_discrete_goals(self) -> int:
        """A, the size of the discrete goal grid."""
        return self._grid_offsets.numel()

    # ------------------------------------------------------------------ actions -> goal commands

    def discrete_commands(self, ego: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Discrete actions -> goal commands.

        Args:
            ego: (E, 6) ego states at decision time.
            actions: (E,) indices into the grid ``lane_offsets x speeds`` (offset-major).

        Returns:
            (E, 2) commands: target lane centre y [m] (the ego's nearest lane plus the offset,
            clamped to the road) and target average speed [m/s].
        """
        actions = torch.as_tensor(actions, dtype=torch.long).reshape(-1)
        if actions.shape[0] != ego.shape[0]:
            raise ValueError(f"`actions` must have shape ({ego.shape[0]},); got {tuple(actions.shape)}")
        if bool(((actions < 0) | (actions >= self.num_discrete_goals)).any()):
            raise ValueError(f"discrete actions must lie in [0, {self.num_discrete_goals}); got {actions.tolist()}")
        return self._grid_commands(ego)[torch.arange(ego.shape[0]), actions]

    def continuous_commands(self, ego: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Continuous actions in [-1, 1]^2 (clipped) -> goal commands (E, 2).

        ``a[0]``: lateral target, the ego lane's centre plus ``a[0] * lateral_range`` lane
        widths, clamped to the road's lane centres; ``a[1]``: speed, linear onto ``speed_range``.
        """
        actions = torch.as_tensor(actions, dtype=ego.dtype).reshape(-1, 2)
        if actions.shape[0] != ego.shape[0]:
            raise ValueError(f"`actions` must have shape ({ego.shape[0]}, 2); got {tuple(actions.shape)}")
        if not bool(torch.isfinite(actions).all()):
            raise ValueError(f"continuous actions must be finite; got {actions.tolist()}")
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

    def plan(self, observation: Observation, commands: torch.Tensor) -> SafePlan:
        """One frame for E environments: the agents' goals plus the standard goals, one solve.

        Args:
            observation: the E environments' road-frame state.
            commands: (E, 2) goal commands ``(y [m], v [m/s])``.

        Returns:
            A :class:`SafePlan`; ``plan.acceleration`` / ``plan.steering`` are the commands to apply.
        """
        commands = torch.as_tensor(commands, dtype=self.mpc.optimizer.dtype)
        if commands.shape != (observation.num_envs, 2):
            raise ValueError(f"`commands` must have shape ({observation.num_envs}, 2); got {tuple(commands.shape)}")
        problem = self.mpc.build_problem(observation.ego, observation.vehicles, observation.vehicle_mask)
        goals = torch.cat([self.goals(problem.ego, commands[:, None]), problem.goals], dim=1)
        problem = problem._replace(goals=goals)
        agent = torch.zeros(observation.num_envs, dtype=torch.long)
        selector = follow_agent(agent, goals, self.config.intervention_speed_scale, self.horizon, self.road.lane_width)
        plan = self.mpc.plan_problem(problem, selector)
        agent_feasible = plan.result.feasible[:, 0]
        return SafePlan(
            plan=plan,
            agent_feasible=agent_feasible,
            intervention=~agent_feasible,
            fallback=~plan.selection.feasible,
            feasible_goals=plan.result.feasible.sum(dim=1),
        )

    def goal_features(self, observation: Observation) -> tuple[np.ndarray, float]:
        """How every goal of the discrete grid fares at the current state (one solve for all E).

        Returns:
            (E, A, 3) float32 features in [0, 1]: feasible flag, squashed meta cost
            ``m / (m + feature_cost_scale)`` with ``m`` the cost per trajectory sample, and
            clearance ``min(1, d / 3)`` with ``d`` the smallest normalised ellipse distance to
            an obstacle (1/3: touching); and the solve's wall time [ms].
        """
        problem = self.mpc.build_problem(observation.ego, observation.vehicles, observation.vehicle_mask)
        grid = self.goals(problem.ego, self._grid_commands(problem.ego))
        problem = problem._replace(goals=torch.cat([grid, problem.goals], dim=1))
        plan = self.mpc.plan_problem(problem)
        count = grid.shape[1]
        feasible = plan.result.feasible[:, :count].to(torch.float32)
        samples = plan.result.trajectories.x.shape[-1]
        cost = torch.nan_to_num(plan.cost[:, :count].to(torch.float32) / samples, nan=math.inf, posinf=math.inf).clamp_min(0.0)
        squashed = torch.where(torch.isinf(cost), torch.ones_like(cost), cost / (cost + self.config.feature_cost_scale))
        distance = torch.nan_to_num(plan.result.min_obstacle_distance[:, :count].to(torch.float32), nan=0.0, posinf=3.0)
        clearance = (distance / 3.0).clamp(0.0, 1.0)
        return torch.stack([feasible, squashed, clearance], dim=-1).numpy(), plan.solve_ms
