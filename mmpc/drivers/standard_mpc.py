"""Standard MPC baseline: ONE nonlinear program per MPC step with the meta cost in its objective.

No goals, no batch: the single trajectory minimises ``sum_k dt * stage(v_k, y_k)`` (the
scenario's meta-cost term, e.g. ``(v - v_cruise)^2``) plus the smoothness terms, subject to
the same kinematics, bounds and obstacle ellipses as the batch optimizer
(:class:`mmpc.drivers.nlp.TrajectoryNLP` in ``meta`` mode), solved by IPOPT and warm-started
from the previous step's solution shifted by one control period. Being a local method it can
only improve the trajectory it starts from: it does not jump to another lane's homotopy class
unless the gradient leads there, which is what the paper's comparison is about.
"""

from __future__ import annotations

import time
from typing import Optional

import numpy as np
import torch

from mmpc.drivers.common import checked_ego, obstacles_for, with_goal_axis
from mmpc.drivers.nlp import NLPConfig, NLPSolution, TrajectoryNLP, resample
from mmpc.drivers.base import Candidates, Decision, Driver, Observation
from mmpc.mpc import MPC


class StandardMPCDriver(Driver):
    """One warm-started IPOPT solve per environment and step.

    Args:
        mpc: the scenario's MPC (bounds, ellipse, obstacle set, meta cost, command extraction).
        stage_cost: ``stage(v, y)`` of the scenario's objective, in plain arithmetic.
        control_period: time between two calls [s] (the warm start is shifted by it).
        config: transcription and IPOPT settings.
        name: the driver's name in tables.
    """

    def __init__(self, mpc: MPC, stage_cost, control_period: float, config: Optional[NLPConfig] = None,
                 name: str = "standard-mpc") -> None:
        if not control_period > 0:
            raise ValueError(f"`control_period` must be > 0 s; got {control_period!r}")
        self.mpc = mpc
        self.name = name
        self.control_period = float(control_period)
        opt = mpc.optimizer.config
        self.nlp = TrajectoryNLP(opt, mpc.road, mpc.config.road_margin, mpc.config.num_obstacles, config, stage_cost)
        #: Per environment id: the last feasible solution and the calls since it was computed.
        self._previous: dict[int, tuple[NLPSolution, int]] = {}

    def reset(self, num_envs: int) -> None:
        self._previous.clear()

    def _warm_start(self, env_id: int) -> tuple[Optional[np.ndarray], Optional[np.ndarray]]:
        if env_id not in self._previous:
            return None, None
        solution, age = self._previous[env_id]
        return self.nlp.shift(solution, (age + 1) * self.control_period), solution.multipliers_g

    @torch.no_grad()
    def decide(self, observation: Observation) -> Decision:
        start = time.perf_counter()
        mpc = self.mpc
        ego = checked_ego(observation, torch.float64)
        knot_times = torch.as_tensor(self.nlp.times, dtype=torch.float64)
        obstacles, mask = obstacles_for(mpc, ego, observation.vehicles.to(torch.float64), observation.vehicle_mask, knot_times)
        solutions = []
        for row, env_id in enumerate(observation.ids().tolist()):
            initial, multipliers = self._warm_start(env_id)
            solution = self.nlp.solve(
                ego[row].numpy(), obstacles[row].numpy(), mask[row].numpy(), initial=initial, multipliers_g=multipliers,
            )
            if solution.feasible:
                self._previous[env_id] = (solution, 0)
            elif env_id in self._previous:
                kept, age = self._previous[env_id]
                self._previous[env_id] = (kept, age + 1)
            solutions.append(solution)
        times = mpc.optimizer.times.to(torch.float64)
        trajectory = resample(np.stack([s.states for s in solutions]), self.nlp.times, times)  # fields (E, N)
        feasible = torch.tensor([s.feasible for s in solutions])
        cost = mpc.meta_cost(with_goal_axis(trajectory), mpc.road)[:, 0]
        centres, present = obstacles_for(mpc, ego, observation.vehicles.to(torch.float64), observation.vehicle_mask, times)
        acceleration, steering, _ = mpc.command(ego, trajectory, feasible, obstacles=centres, mask=present)
        elapsed_ms = (time.perf_counter() - start) * 1e3
        count = ego.shape[0]
        return Decision(
            acceleration=acceleration.float(),
            steering=steering.float(),
            solve_ms=elapsed_ms,
            goal_index=torch.where(feasible, 0, -1).long(),
            feasible_goals=feasible.long(),
            fallback=~feasible,
            plan_cost=torch.where(feasible, cost, torch.full((count,), float("nan"), dtype=cost.dtype)).float(),
            candidates=Candidates(
                xy=torch.stack([trajectory.x, trajectory.y], dim=-1)[:, None].float(),
                feasible=feasible[:, None], best=torch.zeros(count, dtype=torch.long),
            ),
        )


def make_standard_mpc_driver(scenario, argument: Optional[str]) -> Driver:
    """Registry factory (``standard-mpc``; no argument)."""
    from mmpc.scenario import build_mpc

    if argument is not None:
        raise ValueError(f"driver 'standard-mpc' takes no argument; got 'standard-mpc:{argument}'")
    road = scenario.road
    objective = scenario.objective

    def stage(v, y):
        return objective.stage_cost(v, y, road)

    return StandardMPCDriver(build_mpc(scenario, device="cpu"), stage, scenario.period)
