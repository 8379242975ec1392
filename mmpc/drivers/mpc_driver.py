"""The multi-modal MPC as a driver (spec ``mpc``)."""

from __future__ import annotations

import time
from typing import NamedTuple, Optional

import torch

from mmpc.drivers.base import Candidates, Decision, Driver, Observation
from mmpc.mpc import MPC
from mmpc.result import WarmStart
from mmpc.scenario import ScenarioConfig, build_mpc


class MPCDriver(Driver):
    """The multi-modal MPC (:class:`mmpc.MPC`): one batched optimizer call for all E environments.

    With :attr:`mmpc.MPCConfig.warm_iterations` > 0 it keeps each environment's final iterates
    and starts its next solve from them, moved one control step on. An environment solves cold
    at its first step (or when it newly joins the batch), at the step after its own fallback, at
    the step after a warm solve that kept fewer than :attr:`mmpc.MPCConfig.warm_keep_share` of its
    last cold solve's feasible goals, and every :attr:`mmpc.MPCConfig.warm_cold_every`-th step
    since its last cold solve: chains of warm solves drift to costlier plans.

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
        self._last: Optional[_LastSolve] = None

    def reset(self, num_envs: int) -> None:
        self._last = None

    def _warm(self, observation: Observation) -> tuple[Optional[WarmStart], torch.Tensor, torch.Tensor]:
        """The last step's iterates of every environment of ``observation`` moved to this step,
        NaN for those that solve cold (``None``: all of them); (E,) long each environment's warm
        solves since its last cold one, this step's included (0: it solves cold); (E,) long the
        feasible goals of its last cold solve (0 where it solves cold)."""
        steps = torch.zeros(observation.ego.shape[0], dtype=torch.long, device=observation.ego.device)
        if self._last is None:
            return None, steps, steps
        last, config = self._last, self.mpc.config
        match = observation.ids()[:, None] == last.ids[None, :]  # (E, E_last)
        rows = match.int().argmax(dim=1)
        steps = last.warm_steps[rows] + 1
        decayed = last.feasible_goals[rows] < config.warm_keep_share * last.cold_feasible_goals[rows]
        cold = ~match.any(dim=1) | last.fell_back[rows] | decayed | (steps >= config.warm_cold_every)
        steps = torch.where(cold, 0, steps)
        cold_feasible_goals = torch.where(cold, 0, last.cold_feasible_goals[rows])
        if bool(cold.all()):
            return None, steps, cold_feasible_goals
        warm = self.mpc.optimizer.shifted(last.warm.take(rows), self.period, observation.ego[:, :2] - last.starts[rows])
        restart = torch.full((), float("nan"), dtype=warm.position.dtype, device=warm.position.device)
        warm = WarmStart(*(torch.where(cold.view(-1, *[1] * (field.dim() - 1)), restart, field) for field in warm))
        return warm, steps, cold_feasible_goals

    @property
    def device(self) -> torch.device:
        return self.mpc.optimizer.device

    def decide(self, observation: Observation) -> Decision:
        start = time.perf_counter()
        warm = None
        if self.mpc.config.warm_iterations:
            warm, warm_steps, cold_feasible_goals = self._warm(observation)
        plan = self.mpc.plan(observation.ego, observation.vehicles, observation.vehicle_mask, warm=warm)
        feasible_goals = plan.result.feasible.sum(dim=1)
        if self.mpc.config.warm_iterations:
            self._last = _LastSolve(observation.ids(), observation.ego[:, :2], plan.result.warm, warm_steps,
                                    ~plan.selection.feasible, feasible_goals,
                                    torch.where(warm_steps > 0, cold_feasible_goals, feasible_goals))
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
            feasible_goals=feasible_goals,
            fallback=~plan.selection.feasible,
            plan_cost=plan.selection.cost,
            candidates=candidates,
            plan=plan,
            iterations=plan.result.problem_iterations(),
        )


class _LastSolve(NamedTuple):
    """What :class:`MPCDriver` keeps of its last decision, per environment row (E)."""

    ids: torch.Tensor  # (E,) environment ids
    starts: torch.Tensor  # (E, 2) ego positions the iterates are relative to [m]
    warm: WarmStart  # the final iterates, (E, G, ...)
    warm_steps: torch.Tensor  # (E,) long, warm solves since the environment's last cold one
    fell_back: torch.Tensor  # (E,) bool, the decision fell back
    feasible_goals: torch.Tensor  # (E,) long, goals the solve found feasible
    cold_feasible_goals: torch.Tensor  # (E,) long, goals the environment's last cold solve found feasible


def make_mpc_driver(scenario: ScenarioConfig, argument: Optional[str]) -> Driver:
    """Driver factory of spec ``mpc``: the scenario's multi-modal MPC (takes no argument)."""
    if argument is not None:
        raise ValueError(f"driver 'mpc' takes no argument; got 'mpc:{argument}'")
    return MPCDriver(build_mpc(scenario), period=scenario.period)
