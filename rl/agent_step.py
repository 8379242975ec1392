"""One agent step behind the safety layer, written once for every world that runs one.

An agent's decision (a goal command per environment) is held for ``decision_frames`` frames; at
each frame the safety layer executes it for the environments still running, in ONE call
(:meth:`mmpc.rl.safety.SafetyLayer.frame`), solving again or tracking the plan it holds.

- :class:`AgentStep` is that state: the commands, the plan decided at the decision, the plans
  held from frame to frame. The safe-agent driver (:class:`mmpc.rl.driver.SafeAgentDriver`) steps
  it one frame per runner call.
- :class:`mmpc.rl.engine.SafeEnvs` runs whole steps in any :class:`mmpc.highway.worlds.World`
  (the safe environments) and tallies what the environments' ``info`` reports (:class:`StepTally`).
"""

from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from mmpc.drivers import Observation
from mmpc.rl.safety import DecisionSolve, FrameControl, FrameStarts, HeldPlan, SafePlan, SafetyLayer


class AgentStep:
    """The agent step of E environments: their goal commands, held over ``decision_frames`` frames.

    Use :meth:`begin` to make one. Each :meth:`frame` executes the commands of the rows still
    running; after ``decision_frames`` of them the step is :attr:`over`.

    Attributes:
        commands: (E, 2) goal commands ``(y [m], v [m/s])`` on the layer's device.
        decided: the decision's plan (discrete goals: taken from the solve behind the
            observation, where there is one), or ``None`` (the layer plans at the first frame).
        starts: the frame solves' warm starts (:meth:`mmpc.rl.safety.SafetyLayer.frame_starts`),
            this step's own; ``None`` where the layer solves cold.
        frames_done: frames executed so far.
        frame_solved: the last frame called the optimizer (not only executed the decision's plan).
    """

    def __init__(self, layer: SafetyLayer, commands: torch.Tensor, decided: Optional[SafePlan], period: float,
                 starts: Optional[FrameStarts] = None) -> None:
        self.layer = layer
        self.commands = commands
        self.decided = decided
        self.starts = starts
        self.period = period
        self.frames_done = 0
        self.frame_solved = False
        self._held: Optional[HeldPlan] = None
        self._held_rows: Optional[torch.Tensor] = None

    @classmethod
    def begin(cls, layer: SafetyLayer, observation: Observation, actions: torch.Tensor, *, continuous: bool,
              period: float, solve: Optional[DecisionSolve] = None) -> "AgentStep":
        """The step of checked actions taken at the E states ``observation``.

        Args:
            layer: the safety layer.
            observation: the E environments' road-frame state at the decision (any device).
            actions: (E,) long goal indices (the expert's choice last, with ``expert_action``) or
                (E, 2) float continuous goals in [-1, 1] (clipped).
            continuous: ``actions`` are continuous goals.
            period: seconds per frame (1 / the scenario's frequency).
            solve: the :meth:`SafetyLayer.decision_solve` of the same states, or ``None``; discrete
                goals are then executed from its candidates at the first frame (no new solve).
        """
        if not continuous and solve is not None:
            decided = layer.decide(solve, actions)
            starts = layer.frame_starts(decided.commands.shape[0], solve, decided.agent_index)
            return cls(layer, decided.commands, decided, period, starts)
        if continuous:
            commands = layer.continuous_commands(observation.ego, actions)
        else:
            commands = layer.discrete_commands(observation.ego, actions)
        return cls(layer, commands, None, period, layer.frame_starts(commands.shape[0]))

    @property
    def over(self) -> bool:
        """Every frame of the step was executed."""
        return self.frames_done >= self.layer.config.decision_frames

    def frame(self, observation: Observation, rows: torch.Tensor) -> FrameControl:
        """Execute the next frame for the rows ``rows`` (long, into E) at their states
        ``observation`` (one row each): at the first frame every row in order, later the
        environments still running (rows of the last frame, in any order)."""
        if self.over:
            raise RuntimeError(f"the agent step is over: its {self.frames_done} frames were executed")
        rows = rows.to(self.commands.device)
        everyone = torch.arange(self.commands.shape[0], device=rows.device)
        if self.frames_done == 0 and not torch.equal(rows, everyone):
            raise ValueError(f"the first frame of an agent step executes every row in order, {everyone.tolist()}; "
                             f"got rows {rows.tolist()}")
        held = self._held
        if held is not None and not torch.equal(rows, self._held_rows):
            match = rows[:, None] == self._held_rows[None, :]
            if not bool(match.any(dim=1).all()):
                raise ValueError(f"rows {rows.tolist()} must be among the last frame's {self._held_rows.tolist()}")
            held = held.take(match.int().argmax(dim=1))
        first = self.frames_done == 0
        starts = None if self.starts is None else self.starts.take(rows)
        control = self.layer.frame(observation, self.commands[rows], self.frames_done * self.period, held,
                                   self.decided if first else None, starts)
        self._held, self._held_rows = control.held, rows
        self.frame_solved = bool(control.solved.any()) and not (first and self.decided is not None)
        self.frames_done += 1
        return control


class StepTally:
    """What E environments' agent step adds up, on one device: the reward, less the intervention
    penalty per overridden frame, and the counts and last values ``info`` reports (with a
    verifying layer also the frames whose command verified and those the stored fail-safe drove)."""

    def __init__(self, count: int, device: torch.device, intervention_penalty: float) -> None:
        self.penalty = intervention_penalty
        self.rewards = torch.zeros(count, dtype=torch.float64, device=device)
        self.interventions = torch.zeros(count, dtype=torch.long, device=device)
        self.fallbacks = torch.zeros(count, dtype=torch.long, device=device)
        self.solved = torch.zeros(count, dtype=torch.long, device=device)
        self.frames = torch.zeros(count, dtype=torch.long, device=device)
        self.speed_sum = torch.zeros(count, dtype=torch.float64, device=device)
        self.feasible_goals = torch.zeros(count, dtype=torch.long, device=device)
        self.agent_feasible = torch.zeros(count, dtype=torch.bool, device=device)
        self.residuals = torch.zeros(count, 3, dtype=torch.float64, device=device)
        self.verified = torch.zeros(count, dtype=torch.long, device=device)
        self.failsafes = torch.zeros(count, dtype=torch.long, device=device)
        self.checked = False
        self.solve_ms: list[float] = []

    def add(self, rows: torch.Tensor, control: FrameControl, rewards: torch.Tensor, speeds: torch.Tensor) -> None:
        """One frame of the rows ``rows``: the layer's ``control`` and, after it, the states'
        ``rewards`` (R,) and ``speeds`` (R,)."""
        self.rewards[rows] += rewards.to(self.rewards) - self.penalty * control.intervention.double()
        self.interventions[rows] += control.intervention.long()
        self.fallbacks[rows] += control.fallback.long()
        self.solved[rows] += control.solved.long()
        self.frames[rows] += 1
        self.speed_sum[rows] += speeds.to(self.speed_sum)
        self.feasible_goals[rows] = control.feasible_goals
        self.agent_feasible[rows] = control.agent_feasible
        self.residuals[rows] = control.residuals.double()
        if control.verified is not None:
            self.checked = True
            self.verified[rows] += control.verified.long()
            self.failsafes[rows] += control.failsafe.long()

    def infos(self, commands: torch.Tensor, speed: torch.Tensor, crashed: torch.Tensor,
              solve_ms: float) -> tuple[np.ndarray, list[dict]]:
        """(E,) float64 rewards and one ``info`` dict per environment (:class:`mmpc.rl.envs.SafeHighwayEnv`),
        from two copies to the host.

        Args:
            commands: (E, 2) the goal commands held.
            speed: (E,) the egos' speeds at the end of the step [m/s].
            crashed: (E,) bool, the ego crashed.
            solve_ms: the ``solve_ms`` every info reports (a :class:`mmpc.rl.spaces.WallTime`).
        """
        counts = torch.stack([self.interventions, self.fallbacks, self.solved, self.frames, self.feasible_goals,
                              self.agent_feasible.long(), crashed.long().to(self.frames.device), self.verified,
                              self.failsafes], dim=1).cpu().numpy()
        mean_speed = self.speed_sum / self.frames.clamp(min=1)
        reals = torch.cat([self.rewards[:, None], speed.double().to(self.rewards.device)[:, None], mean_speed[:, None],
                           commands.double().to(self.rewards.device), self.residuals], dim=1).cpu().numpy()
        infos = [{
            "intervention": count[0] > 0, "intervention_frames": int(count[0]), "fallback_frames": int(count[1]),
            "solved_frames": int(count[2]), "frames": int(count[3]), "solve_ms": solve_ms, "speed": float(real[1]),
            "mean_speed": float(real[2]), "crashed": bool(count[6]), "goal": (float(real[3]), float(real[4])),
            "feasible_goals": int(count[4]), "agent_feasible": bool(count[5]),
            "residuals": {"obstacle": float(real[5]), "acceleration": float(real[6]), "nonholonomic": float(real[7])},
        } for count, real in zip(counts.tolist(), reals.tolist())]
        if self.checked:
            for info, count in zip(infos, counts.tolist()):
                info.update(verified_frames=int(count[7]), failsafe_frames=int(count[8]))
        return reals[:, 0].copy(), infos
