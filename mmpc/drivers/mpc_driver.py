"""The multi-modal MPC as a driver (spec ``mpc``)."""

from __future__ import annotations

import time
from typing import Optional

import torch

from mmpc.drivers.base import Candidates, Decision, Driver, Observation
from mmpc.mpc import MPC
from mmpc.result import WarmStart
from mmpc.scenario import ScenarioConfig, build_mpc


class MPCDriver(Driver):
    """The multi-modal MPC (:class:`mmpc.MPC`): one batched optimizer call for all E environments.

    With :attr:`mmpc.MPCConfig.warm_iterations` > 0 it keeps each environment's final iterates
    and starts its next solve from them, moved one control step on; every
    :attr:`mmpc.MPCConfig.warm_cold_every`-th step, a step after any row's fallback, and a step
    with an environment it has no iterates for (the first, or one that newly joined the batch)
    solve every row cold.

    Args:
        mpc: the MPC (its goal sampler, meta cost and optimizer).
        name: the driver's name in tables.
        period: the control period [s] (a scenario's ``1 / frequency``); needed for warm starts.
    """

    def __init__(self, mpc: MPC, name: str = "mpc", period: Optional[float] = None) -> None:
        if mpc.config.warm_iterations and not (period is not None and period > 0):
            raise ValueError(f"warm starts (MPCConfig.warm_iterations={mpc.config.warm_iterations}) need the control "
                             f"`period` > 0 s; got {period!r}")
        self.mpc = mpc
        self.name = name
        self.period = period
        self._last: Optional[tuple[torch.Tensor, torch.Tensor, WarmStart]] = None  # env ids, (E, 2) starts, iterates
        self._steps = 0  # decisions since the reset
        self._fell_back = False  # some row of the last decision fell back

    def reset(self, num_envs: int) -> None:
        self._last = None
        self._steps = 0
        self._fell_back = False

    def _warm(self, observation: Observation) -> Optional[WarmStart]:
        """The last step's iterates of every environment of ``observation``, moved to this step;
        ``None`` when one has none."""
        if self._last is None or self._fell_back or self._steps % self.mpc.config.warm_cold_every == 0:
            return None
        ids, starts, warm = self._last
        match = observation.ids()[:, None] == ids[None, :]  # (E, E_last)
        if not bool(match.any(dim=1).all()):
            return None
        rows = match.int().argmax(dim=1)
        offset = observation.ego[:, :2] - starts[rows]
        return self.mpc.optimizer.shifted(warm.take(rows), self.period, offset)

    @property
    def device(self) -> torch.device:
        return self.mpc.optimizer.device

    def decide(self, observation: Observation) -> Decision:
        start = time.perf_counter()
        warm = self._warm(observation) if self.mpc.config.warm_iterations else None
        plan = self.mpc.plan(observation.ego, observation.vehicles, observation.vehicle_mask, warm=warm)
        if self.mpc.config.warm_iterations:
            self._last = (observation.ids(), observation.ego[:, :2], plan.result.warm)
            self._fell_back = bool((~plan.selection.feasible).any())
            self._steps += 1
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
    return MPCDriver(build_mpc(scenario), period=1.0 / scenario.frequency)
