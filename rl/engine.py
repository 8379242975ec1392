"""The safe environments' one engine: E environments of any world, stepped one agent step at a time.

:class:`SafeEnvs` runs the safe environments on the world of the scenario (``scenario.sim``:
highway-env's episodes or the batched simulator, :class:`mmpc.highway.worlds.World`): checked
actions -> one agent step (:class:`mmpc.rl.agent_step.AgentStep`: at every frame ONE safety-layer
call for the environments still running) -> the frame rewards tallied -> observations and
``info``. Every safe environment API is a view of it: the gymnasium environment
(:class:`mmpc.rl.envs.SafeHighwayEnv`, E = 1), the stable-baselines3 ``VecEnv`` and the gymnasium
``VectorEnv`` (:mod:`mmpc.rl.vec_env`).

Observations: highway-env's ``Kinematics`` rows (``kinematics_vehicles`` x presence, x, y, vx,
vy, normalised and clipped to [-1, 1]), flattened, then (``solver_features``) the goal features
of the decision solve at the state (:meth:`mmpc.rl.safety.SafetyLayer.features`). With discrete
goals and ``replan: decision`` that solve also holds the candidates of the agent's next decision,
so an agent step solves once.

The world, the layer and the tallies live on the layer's device (the run's,
:func:`mmpc.device.run_device`); observations, rewards and ``info`` come to the host once per
agent step, in a few bulk copies.
"""

from __future__ import annotations

from typing import Any, NamedTuple, Optional, Sequence

import numpy as np
import torch

from mmpc.config import require_int
from mmpc.drivers import Observation
from mmpc.highway.ego_terms import EgoTerms
from mmpc.highway.worlds import World, make_world
from mmpc.rl.agent_step import AgentStep, StepTally
from mmpc.rl.config import RewardConfig, SafeEnvConfig
from mmpc.rl.reward import task_rewards
from mmpc.rl.safety import DecisionSolve, SafetyLayer
from mmpc.rl.spaces import WallTime, action_space, action_tensor, check_action, observation_vectors
from mmpc.scenario import ScenarioConfig

#: Episode seeds drawn for resets without one lie in [0, SEED_RANGE).
SEED_RANGE = 2 ** 31 - 1


def draw_seeds(rng: np.random.Generator, seeds: Sequence[Optional[int]]) -> list[int]:
    """``seeds`` as ints, each ``None`` drawn from ``rng`` in [0, :data:`SEED_RANGE`)."""
    return [int(s) if s is not None else int(rng.integers(SEED_RANGE)) for s in seeds]


class BatchStep(NamedTuple):
    """One agent step of E environments (:meth:`SafeEnvs.advance`).

    Fields:
        observations: (E, size) float32: after the ended episodes were started again (auto-reset),
            else their last observation.
        rewards: (E,) float64.
        terminated: (E,) bool, the ego crashed.
        truncated: (E,) bool, time up.
        infos: one dict per environment about the step (see :class:`mmpc.rl.envs.SafeHighwayEnv`).
        final: environment -> the last observation of its ended episode (auto-reset only).
        reset_infos: environment -> the ``info`` of its new episode (``episode_seed``, ``solve_ms``; auto-reset only).
    """

    observations: np.ndarray
    rewards: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    infos: list[dict]
    final: dict[int, np.ndarray]
    reset_infos: dict[int, dict]


class SafeEnvs:
    """E safe environments on the world of ``scenario.sim``; the engine of every safe environment API.

    Args:
        num_envs: E.
        scenario: the driving scenario (its ``sim`` chooses the world; its ``duration`` is the
            episode length).
        config: environment settings.
        reward: reward settings.
        continuous: Box goal actions instead of the discrete grid.
        seed: seeds the draws of episode seeds for resets that get none.
        layer: a safety layer to share with other engines (its config must be ``config``);
            default: the scenario's (:meth:`SafetyLayer.for_scenario`).
        render: highway-env draws frames (``rgb_array``).

    Every environment gets an id from the layer (:meth:`SafetyLayer.new_env_id`): its warm starts
    and stored fail-safe are kept under it and dropped when its episode starts again.
    """

    def __init__(self, num_envs: int, scenario: ScenarioConfig, config: SafeEnvConfig, reward: RewardConfig, *,
                 continuous: bool = False, seed: Optional[int] = None, layer: Optional[SafetyLayer] = None,
                 render: bool = False) -> None:
        require_int("", low=1, num_envs=num_envs)
        self.num_envs = num_envs
        self.scenario = scenario
        self.config = config
        self.reward = reward
        self.continuous = bool(continuous)
        self.render = render
        action_space(config, self.continuous)  # refuses settings the action type cannot have
        self.layer = layer if layer is not None else SafetyLayer.for_scenario(scenario, config)
        if self.layer.config != config:
            raise ValueError("`layer` was built for other environment settings than `config`")
        if self.layer.road != scenario.road:
            raise ValueError(f"`layer` plans on {self.layer.road}, the scenario's road is {scenario.road}")
        self.device = self.layer.device
        self.dtype = self.layer.mpc.optimizer.dtype
        self.ids = torch.tensor([self.layer.new_env_id() for _ in range(num_envs)], dtype=torch.long, device=self.device)
        self.rng = np.random.default_rng(seed)
        self.world: Optional[World] = None
        self.seeds: list[int] = []
        self._decision: Optional[DecisionSolve] = None

    # ------------------------------------------------------------------ state

    def observe(self, rows: torch.Tensor) -> Observation:
        """The road-frame state of the environments ``rows`` (R,) for the layer (its dtype and
        device), under the environments' ids."""
        observation = self.world.observe(rows)[0].to(self.device)
        return observation._replace(env_ids=self.ids[rows.to(self.device)])

    def ego_terms(self, rows: torch.Tensor) -> EgoTerms:
        """What the reward reads of the egos of environments ``rows``, on the layer's device."""
        return EgoTerms(*(term.to(self.device) for term in self.world.ego_terms(rows)))

    def task_rewards(self, rows: torch.Tensor) -> torch.Tensor:
        """(R,) float64 rewards of the current states of environments ``rows`` on the layer's device."""
        return task_rewards(self.ego_terms(rows), self.reward, self.scenario)

    def _observations(self, rows: torch.Tensor, *, last: bool = False) -> tuple[np.ndarray, Optional[DecisionSolve]]:
        """(R, size) observations of environments ``rows`` and the decision solve behind their
        solver features (``None`` when neither the features nor the decision need one); ``last``:
        the last states of episodes that ended (their solve is not a decision's, :meth:`SafetyLayer.decision_solve`)."""
        solve = None
        if self.layer.needs_decision_solve(self.continuous):
            solve = self.layer.decision_solve(self.observe(rows), warm=not last)
        features = self.layer.features(solve) if self.config.solver_features else None
        kinematics = self.world.kinematics_rows(rows, self.config.kinematics_vehicles)
        return observation_vectors(kinematics, features, self.config), solve

    # ------------------------------------------------------------------ the API

    def reset(self, seeds: Sequence[Optional[int]]) -> tuple[np.ndarray, list[dict]]:
        """Start every environment (``None`` seeds drawn); ``(observations (E, size), infos)``."""
        if len(seeds) != self.num_envs:
            raise ValueError(f"`seeds` must hold one seed (or None) per environment ({self.num_envs}); got {len(seeds)}")
        self.seeds = draw_seeds(self.rng, seeds)
        if self.world is not None:
            self.world.close()
            self.world = None
        self.world = make_world(self.scenario, self.seeds, render=self.render, dtype=self.dtype, kinematics=False,
                                device=self.device)
        self.layer.forget(self.ids)
        observations, self._decision = self._observations(torch.arange(self.num_envs, device=self.device))
        solve_ms = WallTime(self._decision.scored.solve_ms if self._decision is not None else 0.0)
        return observations, [{"solve_ms": solve_ms, "episode_seed": s} for s in self.seeds]

    def check_actions(self, actions: Sequence[Any]) -> list[Any]:
        """``actions`` checked against the action space, one per environment (:func:`mmpc.rl.spaces.check_action`);
        a refusal names the environment (where there are several)."""
        if len(actions) != self.num_envs:
            raise ValueError(f"`actions` must hold one action per environment ({self.num_envs}); got {len(actions)}")
        checked = []
        for index, action in enumerate(actions):
            try:
                checked.append(check_action(action, self.config, self.continuous))
            except ValueError as error:
                if self.num_envs == 1:
                    raise
                raise ValueError(f"environment {index}: {error}") from None
        return checked

    def advance(self, actions: Sequence[Any], *, auto_reset: bool = True) -> BatchStep:
        """One agent step of every environment; with ``auto_reset`` a new episode (drawn seed) in
        every one that ended (both vector APIs), else the ended ones wait for :meth:`reset`.

        Every environment turns its action into a goal command at its current state and holds it
        for ``decision_frames`` frames (fewer where its episode ends); each frame is ONE
        safety-layer call for all running environments (:meth:`mmpc.rl.safety.SafetyLayer.frame`)
        and one world step. The observations after the step come from one more solve (the decision
        solve of the next step), plus one for the last states of the episodes that ended.

        Raises:
            ValueError: an action its environment refuses, before any environment moves.
            RuntimeError: not reset, or an episode is over (reset it first).
        """
        if self.world is None:
            raise RuntimeError("call reset() before step()")
        checked = self.check_actions(actions)
        done = self.world.done()
        if bool(done.any()):
            raise RuntimeError(f"environments {done.nonzero()[:, 0].tolist()} are over: call reset() first")
        everyone = torch.arange(self.num_envs, device=self.device)
        step = AgentStep.begin(self.layer, self.observe(everyone), action_tensor(checked, self.continuous),
                               continuous=self.continuous, period=1.0 / self.scenario.frequency,
                               solve=self._decision)
        tally = StepTally(self.num_envs, self.device, self.config.intervention_penalty)
        self._run(step, tally)  # the decision's solve was timed at the end of the step before
        terms = self.ego_terms(everyone)  # before the resets
        crashed, speed = terms.crashed.bool(), terms.speed
        ended = self.world.done().to(self.device)
        truncated = (ended & ~crashed).cpu().numpy()
        finished = ended.nonzero()[:, 0]
        final: dict[int, np.ndarray] = {}
        reset_infos: dict[int, dict] = {}
        solve_ms = tally.solve_ms
        if finished.numel():
            last, last_solve = self._observations(finished, last=True)
            final = dict(zip(finished.tolist(), last))
            if last_solve is not None:
                solve_ms.append(last_solve.scored.solve_ms)
        if finished.numel() and auto_reset:
            episode_seeds = draw_seeds(self.rng, [None] * finished.numel())
            self.world.restart(finished, episode_seeds)
            for row, seed in zip(finished.tolist(), episode_seeds):
                self.seeds[row] = seed
            self.layer.forget(self.ids[finished])
            reset_infos = {row: {"episode_seed": seed} for row, seed in zip(finished.tolist(), episode_seeds)}
        if finished.numel() and not auto_reset:  # the ended episodes show their last observation until reset()
            observations = np.zeros((self.num_envs, last.shape[1]), dtype=np.float32)
            observations[finished.cpu().numpy()] = last
            running = (~ended).nonzero()[:, 0]
            if running.numel():
                vectors, solve = self._observations(running)
                observations[running.cpu().numpy()] = vectors
                solve_ms += [] if solve is None else [solve.scored.solve_ms]
            final, self._decision = {}, None
        else:
            observations, self._decision = self._observations(everyone)
            if self._decision is not None:
                solve_ms.append(self._decision.scored.solve_ms)
        for info in reset_infos.values():
            info["solve_ms"] = WallTime(self._decision.scored.solve_ms if self._decision is not None else 0.0)
        rewards, infos = tally.infos(step.commands, speed, crashed, WallTime(float(np.mean(solve_ms)) if solve_ms else 0.0))
        return BatchStep(observations, rewards, crashed.cpu().numpy(), truncated, infos, final, reset_infos)

    def _run(self, step: AgentStep, tally: StepTally) -> None:
        """Run ``step`` to its end: at every frame ONE layer call for the environments still running,
        their commands applied, the frame tallied with the rewards of the states reached. Stops
        early when every episode ended."""
        while not step.over:
            rows = (~self.world.done()).nonzero()[:, 0].to(self.device)
            if rows.numel() == 0:
                return
            control = step.frame(self.observe(rows), rows)
            if step.frame_solved:
                tally.solve_ms.append(control.solve_ms)
            self.world.apply(rows, control.acceleration, control.steering)
            terms = self.ego_terms(rows)  # one read of the egos for the reward and the speed
            tally.add(rows, control, task_rewards(terms, self.reward, self.scenario), terms.speed)

    def close(self) -> None:
        """Release the world."""
        if self.world is not None:
            self.world.close()
            self.world = None
