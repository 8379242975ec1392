"""The multi-modal MPC as a driver (spec ``mpc``)."""

from __future__ import annotations

import time
from typing import Optional

import torch

from mmpc.drivers.base import Candidates, Decision, Driver, Observation
from mmpc.mpc import MPC
from mmpc.scenario import ScenarioConfig, build_mpc


class MPCDriver(Driver):
    """The multi-modal MPC (:class:`mmpc.MPC`): one batched optimizer call for all E environments.

    Args:
        mpc: the MPC (its goal sampler, meta cost and optimizer).
        name: the driver's name in tables.
    """

    def __init__(self, mpc: MPC, name: str = "mpc") -> None:
        self.mpc = mpc
        self.name = name

    @property
    def device(self) -> torch.device:
        return self.mpc.optimizer.device

    def decide(self, observation: Observation) -> Decision:
        start = time.perf_counter()
        plan = self.mpc.plan(observation.ego, observation.vehicles, observation.vehicle_mask)
        elapsed_ms = (time.perf_counter() - start) * 1e3 - plan.compile_ms
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
        )


def make_mpc_driver(scenario: ScenarioConfig, argument: Optional[str]) -> Driver:
    """Driver factory of spec ``mpc``: the scenario's multi-modal MPC (takes no argument)."""
    if argument is not None:
        raise ValueError(f"driver 'mpc' takes no argument; got 'mpc:{argument}'")
    return MPCDriver(build_mpc(scenario))
