"""The multi-modal MPC as a driver (spec ``mpc``)."""

from __future__ import annotations

import time
from typing import Optional

import torch

from mmpc.drivers.base import Candidates, Decision, Driver, Observation
from mmpc.mpc import MPC
from mmpc.scenario import ScenarioConfig, build_mpc
from mmpc.warm import WarmStarts


class MPCDriver(Driver):
    """The multi-modal MPC (:class:`mmpc.MPC`): one batched optimizer call for all E environments.

    With :attr:`mmpc.MPCConfig.warm_iterations` > 0 each environment's solve starts from its
    last one's iterates, moved one control step on, under the rules of :mod:`mmpc.warm`.

    Args:
        mpc: the MPC (its goal sampler, meta cost and optimizer).
        name: the driver's name in tables.
        period: the control period [s] for warm starts; default: the MPC's (:attr:`mmpc.MPC.control_period`).
    """

    def __init__(self, mpc: MPC, name: str = "mpc", period: Optional[float] = None) -> None:
        self.mpc = mpc
        self.name = name
        self.period = period
        self.warm_starts = WarmStarts(mpc, period)

    def reset(self, num_envs: int) -> None:
        self.warm_starts.reset()

    @property
    def device(self) -> torch.device:
        return self.mpc.optimizer.device

    def decide(self, observation: Observation) -> Decision:
        start = None if self.mpc.fixed_shapes else time.perf_counter()  # one graph: timed from outside
        problem = self.mpc.build_problem(observation.ego, observation.vehicles, observation.vehicle_mask)
        plan = self.mpc.choose(problem, self.warm_starts.score(observation.ids(), observation.ego, problem))
        elapsed_ms = float("nan") if self.mpc.fixed_shapes else (time.perf_counter() - start) * 1e3 - plan.compile_ms
        trajectories = plan.result.trajectories
        candidates = Candidates(
            xy=torch.stack([trajectories.x, trajectories.y], dim=-1),
            feasible=plan.result.feasible,
            best=plan.selection.index,
            goals=plan.problem.goals,
        )
        return Decision(
            acceleration=plan.acceleration,
            steering=plan.steering,
            solve_ms=elapsed_ms,
            goal_index=plan.selection.index,
            feasible_goals=plan.result.feasible.sum(dim=1),
            fallback=~plan.selection.feasible,
            plan_cost=plan.selection.cost,
            candidates=candidates,
            plan=plan,
            iterations=plan.result.problem_iterations(),
        )


def make_mpc_driver(scenario: ScenarioConfig, argument: Optional[str]) -> Driver:
    """Driver factory of spec ``mpc``: the scenario's multi-modal MPC (takes no argument)."""
    if argument is not None:
        raise ValueError(f"driver 'mpc' takes no argument; got 'mpc:{argument}'")
    return MPCDriver(build_mpc(scenario), period=scenario.period)
