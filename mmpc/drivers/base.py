"""The driver interface: anything that turns the state of E environments into E (acceleration,
steering) commands, so the episode runner and the evaluation run every method the same way.

A driver sees an :class:`Observation` (the road-frame state the MPC uses, plus highway-env's
kinematics observation for learned policies) and returns a :class:`Decision`. It is batched:
one :meth:`Driver.decide` call serves E environments stepped in lockstep, which is what lets
the multi-modal MPC solve all of their goal batches in one optimizer call.
"""

from __future__ import annotations

import abc
from typing import NamedTuple, Optional

import numpy as np
import torch

from mmpc.mpc import Plan


class Observation(NamedTuple):
    """What a driver sees of E environments at one control step.

    Fields:
        ego: (E, 6) ego state in the road frame, as :data:`mmpc.EGO_FIELDS` (x, y [m], psi
            [rad], v [m/s], a [m/s^2], psidot [rad/s]).
        vehicles: (E, V, 4) other vehicles' x, y [m], vx, vy [m/s] in the road frame.
        vehicle_mask: (E, V) bool, True for real vehicles (rows padded when environments have
            different vehicle counts); ``None``: all real.
        kinematics: (E, rows, features) float32, highway-env's ``Kinematics`` observation of
            each environment (what learned policies read); ``None`` where not available.
        env_ids: (E,) long, which environment each row is, stable over an episode (rows drop
            out of a lockstep batch as their episodes end); drivers with memory key it on
            these. ``None``: rows 0..E-1.
    """

    ego: torch.Tensor
    vehicles: torch.Tensor
    vehicle_mask: Optional[torch.Tensor] = None
    kinematics: Optional[np.ndarray] = None
    env_ids: Optional[torch.Tensor] = None

    def ids(self) -> torch.Tensor:
        """(E,) long environment ids (``env_ids`` or 0..E-1)."""
        return self.env_ids if self.env_ids is not None else torch.arange(self.num_envs, device=self.ego.device)

    def to(self, device: torch.device | str) -> "Observation":
        """The observation with its tensors on ``device`` (those there already are not copied)."""
        return self._replace(**{name: getattr(self, name).to(device) for name in ("ego", "vehicles", "vehicle_mask", "env_ids")
                                if getattr(self, name) is not None})

    @property
    def num_envs(self) -> int:
        return self.ego.shape[0]


class Candidates(NamedTuple):
    """The trajectories a planning driver considered (for drawing), environment-major.

    Fields:
        xy: (E, K, N, 2) road-frame positions of K candidates [m].
        feasible: (E, K) bool.
        best: (E,) index of the executed candidate.
        goals: (E, K, 2) the candidates' goals [m]; ``None`` for samplers without goals.
    """

    xy: torch.Tensor
    feasible: torch.Tensor
    best: torch.Tensor
    goals: Optional[torch.Tensor] = None


class Decision(NamedTuple):
    """E commands and what a step record needs from the driver.

    Fields:
        acceleration: (E,) longitudinal acceleration command [m/s^2].
        steering: (E,) steering angle command [rad].
        solve_ms: wall time of the whole :meth:`Driver.decide` call (all E) [ms].
        goal_index: (E,) long, index of the chosen goal/candidate; -1 where the driver has none.
        feasible_goals: (E,) long, number of feasible candidates; -1 where not applicable.
        fallback: (E,) bool, the driver executed its fallback (no feasible candidate).
        plan_cost: (E,) the chosen plan's meta cost as the driver ranked it (NaN: not applicable).
        candidates: what was considered, for videos; ``None`` when the driver plans nothing.
        plan: the MPC's full :class:`mmpc.Plan` (MPC drivers only).
        iterations: (E,) long, optimizer iterations run for each environment's solve, the mean over
            its candidates (warm starts and early exit run fewer); ``None``: not reported.
        verified: (E,) bool, the command kept a verified way out (:mod:`mmpc.verify`); ``None``:
            the driver is not verified.
        failsafe: (E,) bool, no candidate verified and a fail-safe drove; ``None``: not verified.
    """

    acceleration: torch.Tensor
    steering: torch.Tensor
    solve_ms: float
    goal_index: torch.Tensor
    feasible_goals: torch.Tensor
    fallback: torch.Tensor
    plan_cost: torch.Tensor
    candidates: Optional[Candidates] = None
    plan: Optional[Plan] = None
    iterations: Optional[torch.Tensor] = None
    verified: Optional[torch.Tensor] = None
    failsafe: Optional[torch.Tensor] = None

    def commands_to(self, device: torch.device | str) -> "Decision":
        """The decision with its per-environment fields (commands, goal, counts, fallback, cost,
        iterations, the candidates' goals and flags) on ``device``; the candidates' trajectories and the
        plan stay where the driver computed them (fields there already are not copied)."""
        fields = ("acceleration", "steering", "goal_index", "feasible_goals", "fallback", "plan_cost")
        moved = {name: getattr(self, name).to(device) for name in fields}
        for name in ("iterations", "verified", "failsafe"):
            if getattr(self, name) is not None:
                moved[name] = getattr(self, name).to(device)
        if self.candidates is not None:
            goals = None if self.candidates.goals is None else self.candidates.goals.to(device)
            moved["candidates"] = self.candidates._replace(feasible=self.candidates.feasible.to(device),
                                                           best=self.candidates.best.to(device), goals=goals)
        return self._replace(**moved)

    @classmethod
    def command_only(cls, acceleration: torch.Tensor, steering: torch.Tensor, solve_ms: float) -> "Decision":
        """A decision of a driver without candidates (e.g. a learned policy)."""
        count, device = acceleration.shape[0], acceleration.device
        return cls(
            acceleration, steering, solve_ms,
            goal_index=torch.full((count,), -1, dtype=torch.long, device=device),
            feasible_goals=torch.full((count,), -1, dtype=torch.long, device=device),
            fallback=torch.zeros(count, dtype=torch.bool, device=device),
            plan_cost=torch.full((count,), float("nan"), device=device),
        )


class Driver(abc.ABC):
    """Commands for E environments per call.

    Subclasses set :attr:`name` and implement :meth:`decide`; drivers with memory across steps
    (warm starts, recurrent policies) also override :meth:`reset`. A driver that computes on a
    GPU says so with :attr:`device`: the episode runner hands it observations there.
    """

    name: str = "driver"

    @property
    def device(self) -> torch.device:
        """Where :meth:`decide` wants its observations (the CPU unless a driver says otherwise)."""
        return torch.device("cpu")

    def reset(self, num_envs: int) -> None:
        """E new episodes start: forget anything carried from earlier steps."""

    def close(self) -> None:
        """Release what the driver holds beyond memory (worker processes); it is not used after."""

    @abc.abstractmethod
    def decide(self, observation: Observation) -> Decision:
        """Commands for the E environments of ``observation``."""
