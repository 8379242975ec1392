"""Any driver behind the verifier (spec ``verified:DRIVER``): a step is taken only if it keeps a
verified way out (:mod:`mmpc.verify`).

Each step, per environment, the first command of this list that verifies is driven:

1. the driver's own command;
2. its own steering with braking of :data:`BRAKING` [m/s^2], mildest first (brake no more
   than needed, keep the plan's line: switching goals step by step zigzags);
3. its other feasible candidates, cheapest first (planning drivers: the MPC's goals);
4. the fail-safes' first commands from the present state (continuing one is a fail-safe from
   its end, so it verifies wherever the fail-safe stored last step still does).

Where none verifies, the fail-safe verified at the last step (from the state the ego is now in)
drives on; at an episode's first step without one, the strongest braking in the nearest lane.
By induction the ego never collides while every car keeps :class:`mmpc.verify.TrafficAssumptions`.
"""

from __future__ import annotations

import time
from typing import Optional

import torch

from mmpc.drivers.base import Decision, Driver, Observation
from mmpc.drivers.registry import driver_files, make_driver
from mmpc.scenario import ScenarioConfig
from mmpc.sim.traffic import sim_config
from mmpc.verify import Verifier


#: Decelerations tried with the driver's own steering where its command does not verify [m/s^2].
BRAKING = (1.0, 2.0, 3.0, 4.0)


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
        self.verifier = verifier
        self.alternatives = alternatives
        self.name = name or f"verified:{driver.name}"
        self._stored: dict[int, tuple[int, float]] = {}  # environment id -> (lane, deceleration) verified last step

    @property
    def device(self) -> torch.device:
        return self.driver.device

    def reset(self, num_envs: int) -> None:
        self.driver.reset(num_envs)
        self._stored = {}

    def decide(self, observation: Observation) -> Decision:
        decision = self.driver.decide(observation)
        start = time.perf_counter()
        observation = observation.to("cpu")
        decision = decision.commands_to("cpu")
        ego, vehicles = observation.ego, observation.vehicles
        mask = observation.vehicle_mask if observation.vehicle_mask is not None else \
            torch.ones(vehicles.shape[:2], dtype=torch.bool)
        first = self.verifier.check(ego, vehicles, mask, decision.acceleration[:, None].to(ego.dtype),
                                    decision.steering[:, None].to(ego.dtype))
        acceleration, steering = decision.acceleration.clone(), decision.steering.clone()
        verified = first.verified[:, 0].clone()
        lane, deceleration = first.lane[:, 0].clone(), first.deceleration[:, 0].clone()
        rows = (~verified).nonzero().squeeze(1)
        if rows.numel():
            candidates = self._candidates(decision, ego, rows)
            verdict = self.verifier.check(ego[rows], vehicles[rows], mask[rows], *candidates)
            found = verdict.verified.any(dim=1)
            pick = verdict.verified.int().argmax(dim=1, keepdim=True)
            chosen = rows[found]
            acceleration[chosen] = candidates[0].gather(1, pick)[found, 0].to(acceleration.dtype)
            steering[chosen] = candidates[1].gather(1, pick)[found, 0].to(steering.dtype)
            lane[chosen] = verdict.lane.gather(1, pick)[found, 0]
            deceleration[chosen] = verdict.deceleration.gather(1, pick)[found, 0]
            verified[chosen] = True
        failsafe = ~verified
        ids = observation.ids().tolist()
        if bool(failsafe.any()):
            stuck = failsafe.nonzero().squeeze(1)
            fallback = [self._stored.get(ids[row]) for row in stuck.tolist()]
            nearest = self.verifier.road.lane_index(ego[stuck, 1])
            strongest = max(self.verifier.failsafes.decelerations)
            lane[stuck] = torch.tensor([kept[0] if kept else int(near) for kept, near in zip(fallback, nearest)])
            deceleration[stuck] = torch.tensor([kept[1] if kept else strongest for kept in fallback], dtype=deceleration.dtype)
            command = self.verifier.failsafe_command(ego[stuck], lane[stuck], deceleration[stuck])
            acceleration[stuck] = command[0].to(acceleration.dtype)
            steering[stuck] = command[1].to(steering.dtype)
        for env, kept_lane, kept_deceleration in zip(ids, lane.tolist(), deceleration.tolist()):
            self._stored[env] = (kept_lane, kept_deceleration)
        changed = (acceleration != decision.acceleration) | (steering != decision.steering)
        return decision._replace(
            acceleration=acceleration, steering=steering, verified=verified, failsafe=failsafe,
            solve_ms=decision.solve_ms + (time.perf_counter() - start) * 1e3,
            goal_index=torch.where(changed, -1, decision.goal_index),
        )

    def _candidates(self, decision: Decision, ego: torch.Tensor, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(R, K) accelerations and steerings to try in the ``rows`` whose own command did not
        verify: its own steering with each of :data:`BRAKING`, the driver's cheapest other
        feasible candidates, then the fail-safes' first commands."""
        own_acceleration = decision.acceleration[rows, None].to(ego.dtype)
        own_steering = decision.steering[rows, None].to(ego.dtype)
        braking = torch.tensor(BRAKING, dtype=ego.dtype)
        failsafe_acceleration, failsafe_steering = self.verifier.failsafe_candidates(ego[rows])
        accelerations = [torch.minimum(own_acceleration, -braking), failsafe_acceleration]
        steerings = [own_steering.expand(-1, braking.numel()), failsafe_steering]
        plan, mpc = decision.plan, getattr(self.driver, "mpc", None)
        if plan is not None and mpc is not None and self.alternatives:
            goal_acceleration, goal_steering = self._cheapest_goals(plan, mpc, rows)
            usable = goal_acceleration.isfinite()  # an infeasible slot repeats the own command, which did not verify
            accelerations.insert(1, torch.where(usable, goal_acceleration.to(ego.dtype), own_acceleration))
            steerings.insert(1, torch.where(usable, goal_steering.to(ego.dtype), own_steering))
        return torch.cat(accelerations, dim=1), torch.cat(steerings, dim=1)

    def _cheapest_goals(self, plan, mpc, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The commands of the ``rows``' :attr:`alternatives` cheapest feasible goals of ``plan``
        (on the CPU; NaN where fewer are feasible)."""
        result, device = plan.result, plan.cost.device
        rows = rows.to(device)
        cost = torch.where(result.feasible, plan.cost, torch.full_like(plan.cost, float("inf")))[rows]
        cheapest = cost.topk(min(self.alternatives, cost.shape[1]), dim=1, largest=False)
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
    verifier = Verifier(scenario.road, sim_config(scenario), ego_size=scenario.vehicle)
    return VerifiedDriver(make_driver(argument, scenario), verifier)


make_verified_driver.files = lambda argument: driver_files(argument) if argument else ()
