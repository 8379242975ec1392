"""Any driver behind the verifier (spec ``verified:DRIVER``): a step is taken only if it keeps a
verified way out (:mod:`mmpc.verify`).

Each step the driver decides and :class:`mmpc.verify.Guard` drives, per environment, the first
command that verifies: the driver's own, its own steering braking harder, the driver's other
feasible candidates cheapest first (planning drivers: the MPC's goals), a fail-safe's first
command, else the fail-safe verified at the last step. By induction the ego never collides
while every car keeps :class:`mmpc.verify.TrafficAssumptions`.

:func:`guarded_command` is that guarded command, written once: the verified driver and the
RL safety layer (:class:`mmpc.rl.safety.SafetyLayer` with ``env.verify``) both take it.
"""

from __future__ import annotations

import time
from typing import NamedTuple, Optional

import torch

from mmpc.drivers.base import Decision, Driver, Observation
from mmpc.drivers.registry import driver_files, make_driver
from mmpc.scenario import ScenarioConfig
from mmpc.verify import Guard, Verifier

#: At most this many of a plan's other feasible candidates are tried where the asked command does not verify.
ALTERNATIVES = 8


class GuardedCommand(NamedTuple):
    """The commands driven in E environments (:func:`guarded_command`), on the device and in the
    dtype of the commands asked for.

    Fields:
        acceleration, steering: (E,) [m/s^2], [rad].
        verified: (E,) bool, the command driven verified.
        failsafe: (E,) bool, nothing verified and the stored fail-safe drove.
        changed: (E,) bool, the command driven is not the one asked for.
    """

    acceleration: torch.Tensor
    steering: torch.Tensor
    verified: torch.Tensor
    failsafe: torch.Tensor
    changed: torch.Tensor


def guarded_command(guard: Guard, observation: Observation, acceleration: torch.Tensor, steering: torch.Tensor,
                    plan=None, mpc=None, alternatives: int = ALTERNATIVES) -> GuardedCommand:
    """The command asked for where it keeps a verified way out; else braking, the plan's other
    feasible candidates, a fail-safe (:class:`mmpc.verify.Guard`). The check runs on the CPU, or
    on the observation's device where the verifier has fixed shapes (nothing read on the host).

    Args:
        guard: the check and the fail-safes it stored per environment id (``observation``'s ids).
        observation: the E environments' road-frame state (any device).
        acceleration, steering: (E,) the commands asked for [m/s^2], [rad].
        plan: the :class:`mmpc.mpc.Plan` of ``mpc`` that made them, whose cheapest other feasible
            candidates (at most ``alternatives``) are tried before the fail-safes; ``None``: none.
    """
    where = observation.ego.device if guard.verifier.fixed_shapes else torch.device("cpu")
    state = observation.to(where)
    asked = acceleration.to(where), steering.to(where)
    others = None
    if plan is not None and mpc is not None and alternatives:
        others = lambda rows: cheapest_goals(plan, mpc, rows, alternatives)  # noqa: E731
    chosen = guard.choose(state.ego, state.vehicles, state.vehicle_mask, state.ids(), *asked, others)
    driven = chosen.acceleration.to(asked[0].dtype), chosen.steering.to(asked[1].dtype)
    changed = (driven[0] != asked[0]) | (driven[1] != asked[1])
    device = acceleration.device
    return GuardedCommand(driven[0].to(device), driven[1].to(device), chosen.verified.to(device),
                          chosen.failsafe.to(device), changed.to(device))


class VerifiedDriver(Driver):
    """``driver``'s commands, each taken only if :class:`mmpc.verify.Verifier` verifies it.

    Args:
        driver: the driver whose commands are checked.
        verifier: the check.
        alternatives: at most this many of the driver's other feasible candidates are tried
            where its own command does not verify.
        name: the driver's name in tables; default ``verified:<driver's name>``.
    """

    def __init__(self, driver: Driver, verifier: Verifier, *, alternatives: int = ALTERNATIVES,
                 name: Optional[str] = None) -> None:
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
        fixed = self.verifier.fixed_shapes  # a graph's step: nothing moved to the host, nothing timed
        start = None if fixed else time.perf_counter()
        decision = decision if fixed else decision.commands_to("cpu")
        guarded = guarded_command(self.guard, observation, decision.acceleration, decision.steering, decision.plan,
                                  getattr(self.driver, "mpc", None), self.alternatives)
        solve_ms = decision.solve_ms + (float("nan") if fixed else (time.perf_counter() - start) * 1e3)
        return decision._replace(
            acceleration=guarded.acceleration, steering=guarded.steering, verified=guarded.verified,
            failsafe=guarded.failsafe, solve_ms=solve_ms, goal_index=torch.where(guarded.changed, -1, decision.goal_index),
        )


def cheapest_goals(plan, mpc, rows: torch.Tensor, count: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The first commands of the ``count`` cheapest feasible candidates of ``plan`` (an
    :class:`mmpc.mpc.Plan` of ``mpc``) in its ``rows`` (R,): (R, count) accelerations and
    steerings on the rows' device, NaN where fewer are feasible."""
    result, device, asked_on = plan.result, plan.cost.device, rows.device
    rows = rows.to(device)
    cost = torch.where(result.feasible, plan.cost, torch.full_like(plan.cost, float("inf")))[rows]
    cheapest = cost.topk(min(count, cost.shape[1]), dim=1, largest=False)
    trajectories = result.trajectories
    picked = type(trajectories)(trajectories.times, *(field[rows[:, None], cheapest.indices] for field in trajectories[1:]))
    acceleration, steering = mpc.candidate_commands(plan.problem.ego[rows], picked)
    missing = ~cheapest.values.isfinite()
    nan = torch.full_like(acceleration, float("nan"))
    return torch.where(missing, nan, acceleration).to(asked_on), torch.where(missing, nan, steering).to(asked_on)


def behind_check(driver: Driver, scenario: ScenarioConfig, verify: bool = True) -> Driver:
    """``driver`` behind the scenario's check (``verified:``) where ``verify`` asks for it, else itself."""
    return VerifiedDriver(driver, Verifier.for_scenario(scenario)) if verify else driver


def make_verified_driver(scenario: ScenarioConfig, argument: Optional[str]) -> Driver:
    """Driver factory of spec ``verified:DRIVER``: ``DRIVER``'s spec behind the scenario's verifier."""
    if not argument:
        raise ValueError("driver 'verified' needs the driver it checks, e.g. 'verified:mpc'; got none")
    return behind_check(make_driver(argument, scenario), scenario)


make_verified_driver.files = lambda argument: driver_files(argument) if argument else ()
