"""Any driver behind the verifier (spec ``verified:DRIVER``): a step is taken only if it keeps a
verified way out (:mod:`mmpc.verify`).

Each step the driver decides and :class:`mmpc.verify.Guard` drives, per environment, the first
command that verifies: the driver's own, its own steering braking harder, the driver's other
feasible candidates cheapest first (planning drivers: the MPC's goals), a fail-safe's first
command, else the fail-safe verified at the last step. By induction the ego never collides
while every car keeps :class:`mmpc.verify.TrafficAssumptions`.
"""

from __future__ import annotations

import time
from typing import Optional

import torch

from mmpc.drivers.base import Decision, Driver, Observation
from mmpc.drivers.registry import driver_files, make_driver
from mmpc.scenario import ScenarioConfig
from mmpc.verify import Guard, Verifier


class VerifiedDriver(Driver):
    """``driver``'s commands, each taken only if :class:`mmpc.verify.Verifier` verifies it.

    Args:
        driver: the driver whose commands are checked.
        verifier: the check.
        alternatives: at most this many of the driver's other feasible candidates are tried
            where its own command does not verify.
        name: the driver's name in tables; default ``verified:<driver's name>``.
    """

    def __init__(self, driver: Driver, verifier: Verifier, *, alternatives: int = 8, name: Optional[str] = None) -> None:
        if not (isinstance(alternatives, int) and alternatives >= 0):
            raise ValueError(f"`alternatives` must be an int >= 0; got {alternatives!r}")
        self.driver = driver
        self.guard = Guard(verifier)
        self.alternatives = alternatives
        self.name = name or f"verified:{driver.name}"

    @property
    def verifier(self) -> Verifier:
        return self.guard.verifier

    @property
    def device(self) -> torch.device:
        return self.driver.device

    def reset(self, num_envs: int) -> None:
        self.driver.reset(num_envs)
        self.guard.reset()

    def close(self) -> None:
        self.driver.close()

    def decide(self, observation: Observation) -> Decision:
        decision = self.driver.decide(observation)
        start = time.perf_counter()
        observation = observation.to("cpu")
        decision = decision.commands_to("cpu")
        plan, mpc = decision.plan, getattr(self.driver, "mpc", None)
        alternatives = None
        if plan is not None and mpc is not None and self.alternatives:
            alternatives = lambda rows: cheapest_goals(plan, mpc, rows, self.alternatives)  # noqa: E731
        guarded = self.guard.choose(observation.ego, observation.vehicles, observation.vehicle_mask, observation.ids().tolist(),
                                    decision.acceleration, decision.steering, alternatives)
        acceleration = guarded.acceleration.to(decision.acceleration.dtype)
        steering = guarded.steering.to(decision.steering.dtype)
        changed = (acceleration != decision.acceleration) | (steering != decision.steering)
        return decision._replace(
            acceleration=acceleration, steering=steering, verified=guarded.verified, failsafe=guarded.failsafe,
            solve_ms=decision.solve_ms + (time.perf_counter() - start) * 1e3,
            goal_index=torch.where(changed, -1, decision.goal_index),
        )


def cheapest_goals(plan, mpc, rows: torch.Tensor, count: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The first commands of the ``count`` cheapest feasible candidates of ``plan`` (an
    :class:`mmpc.mpc.Plan` of ``mpc``) in its ``rows`` (R,): (R, count) accelerations and
    steerings on the CPU, NaN where fewer are feasible."""
    result, device = plan.result, plan.cost.device
    rows = rows.to(device)
    cost = torch.where(result.feasible, plan.cost, torch.full_like(plan.cost, float("inf")))[rows]
    cheapest = cost.topk(min(count, cost.shape[1]), dim=1, largest=False)
    trajectories = result.trajectories
    picked = type(trajectories)(trajectories.times, *(field[rows[:, None], cheapest.indices] for field in trajectories[1:]))
    acceleration, steering = mpc.candidate_commands(plan.problem.ego[rows], picked)
    missing = ~cheapest.values.isfinite()
    nan = torch.full_like(acceleration, float("nan"))
    return torch.where(missing, nan, acceleration).cpu(), torch.where(missing, nan, steering).cpu()


def make_verified_driver(scenario: ScenarioConfig, argument: Optional[str]) -> Driver:
    """Driver factory of spec ``verified:DRIVER``: ``DRIVER``'s spec behind the scenario's verifier."""
    if not argument:
        raise ValueError("driver 'verified' needs the driver it checks, e.g. 'verified:mpc'; got none")
    return VerifiedDriver(make_driver(argument, scenario), Verifier.for_scenario(scenario))


make_verified_driver.files = lambda argument: driver_files(argument) if argument else ()
