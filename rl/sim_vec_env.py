"""The safe environments on the batched simulator (:mod:`mmpc.sim`): E environments in tensors,
one optimizer call per simulation frame for all of them, as a stable-baselines3 ``VecEnv``
(:class:`SafeSimVecEnv`) and a gymnasium 1.x ``VectorEnv`` (:class:`SafeSimVectorEnv`).

Observations, actions, rewards and ``info`` mean what they mean in :mod:`mmpc.rl.envs` (the
highway-env environments): highway-env's ``Kinematics`` rows and the solver features, the goal
grid or Box goals held for ``decision_frames`` frames (the safety layer replans at every frame or
at the decisions, :attr:`mmpc.rl.config.SafeEnvConfig.replan`), highway-env's reward summed over the frames minus the intervention penalty. Episodes that end
are started again at once from a new seed (SB3's auto-reset; gymnasium's ``SAME_STEP`` mode).

The simulator, the safety layer and the per-step tallies live on the run's device
(:func:`mmpc.device.run_device`, ``--device``); observations, rewards and ``info`` come to the
host once per agent step, in a few bulk copies.
"""

from __future__ import annotations

from typing import Any, NamedTuple, Optional, Sequence

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvObs, VecEnvStepReturn

from mmpc.config import require_int
from mmpc.highway.batched_world import BatchedWorld
from mmpc.rl.config import RewardConfig, SafeEnvConfig
from mmpc.rl.agent_step import AgentStep, StepTally, run_agent_step
from mmpc.rl.envs import WallTime, action_space, action_tensor, check_action, observation_space, observation_vectors
from mmpc.rl.safety import DecisionSolve, SafetyLayer
from mmpc.scenario import ScenarioConfig, batched_unsupported
from mmpc.sim import SimEpisodes
from mmpc.sim.observation import kinematics_observation
from mmpc.sim.reward import highway_reward
from mmpc.sim.state import on_road

#: Episode seeds drawn for resets without one lie in [0, SEED_RANGE).
SEED_RANGE = 2 ** 31 - 1


class BatchStep(NamedTuple):
    """One agent step of E environments (:meth:`SafeSimBatch.advance`).

    Fields:
        observations: (E, size) float32, after the ended episodes were started again.
        rewards: (E,) float64.
        terminated: (E,) bool, the ego crashed.
        truncated: (E,) bool, time up.
        infos: one dict per environment about the step (see :class:`mmpc.rl.envs.SafeHighwayEnv`;
            ``solved_frames`` counts the frames a solve served the environment).
        final: environment -> the last observation of its ended episode.
        reset_infos: environment -> the ``info`` of its new episode (``episode_seed``, ``solve_ms``).
    """

    observations: np.ndarray
    rewards: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    infos: list[dict]
    final: dict[int, np.ndarray]
    reset_infos: dict[int, dict]


class SafeSimBatch:
    """E safe environments on one :class:`mmpc.sim.SimEpisodes`; the engine of both vector APIs.

    Args:
        num_envs: E.
        scenario: an IDM-traffic scenario the batched simulator runs (else ``ValueError`` naming
            ``--sim highway-env``); its ``duration`` is the episode length.
        config: environment settings.
        reward: reward settings.
        continuous: Box goal actions instead of the discrete grid.
        seed: seeds the draws of episode seeds for resets that get none.

    The simulator runs where the layer's MPC computes (:func:`mmpc.scenario.build_mpc`: the run's
    device, :func:`mmpc.device.run_device`).
    """

    def __init__(self, num_envs: int, scenario: ScenarioConfig, config: SafeEnvConfig, reward: RewardConfig, *,
                 continuous: bool = False, seed: Optional[int] = None) -> None:
        require_int("", low=1, num_envs=num_envs)
        reason = batched_unsupported(scenario)
        if reason is not None:
            raise ValueError(f"scenario {scenario.name!r}: {reason}")
        self.num_envs = num_envs
        self.scenario = scenario
        self.config = config
        self.reward = reward
        self.continuous = bool(continuous)
        action_space(config, self.continuous)  # refuses settings the action type cannot have
        self.layer = SafetyLayer.for_scenario(scenario, config)
        self.dtype = self.layer.mpc.optimizer.dtype
        self.device = self.layer.device
        self.rng = np.random.default_rng(seed)
        self.world: Optional[BatchedWorld] = None
        self._decision: Optional[DecisionSolve] = None

    def _seeds(self, seeds: Sequence[Optional[int]]) -> list[int]:
        return [int(s) if s is not None else int(self.rng.integers(SEED_RANGE)) for s in seeds]

    @property
    def sim(self) -> Optional[SimEpisodes]:
        """The simulator's episodes (``None`` before :meth:`reset`)."""
        return None if self.world is None else self.world.sim

    @property
    def _decides_from_features_solve(self) -> bool:
        """Discrete decisions at the decision rate are taken from the solve behind the observation."""
        return self.config.replan == "decision" and not self.continuous

    def _observations(self, rows: torch.Tensor, *, last: bool = False) -> tuple[np.ndarray, Optional[DecisionSolve]]:
        """(R, size) observations of environments ``rows`` and the decision solve behind their
        solver features (``None`` when neither the features nor the decision need one); ``last``:
        the last states of episodes that ended (their solve is not a decision's, :meth:`SafetyLayer.decision_solve`)."""
        solve = None
        if self.config.solver_features or self._decides_from_features_solve:
            solve = self.layer.decision_solve(self.world.observe(rows)[0], warm=not last)
        features = self.layer.features(solve) if self.config.solver_features else None
        kinematics = kinematics_observation(self.sim.state, self.sim.config, vehicles_count=self.config.kinematics_vehicles,
                                            check=False)
        return observation_vectors(kinematics[rows].float().cpu().numpy(), features, self.config), solve

    def _frame_rewards(self) -> torch.Tensor:
        """(E,) float64 rewards of the current states (:class:`mmpc.rl.config.RewardConfig`)."""
        state, reward = self.sim.state, self.reward
        if reward.source == "meta_cost":
            ego_speed, ego_y = state.speed[:, 0].double(), state.y[:, 0].double()
            cost = self.scenario.objective.stage_cost(ego_speed, ego_y, self.scenario.road)
            return reward.meta_cost_reward(cost, state.crashed[:, 0].double(), on_road(state.y[:, 0], self.sim.config).double())
        return highway_reward(state, self.sim.config, reward.highway_terms()).double()

    def reset(self, seeds: Sequence[Optional[int]]) -> tuple[np.ndarray, list[dict]]:
        """Start every environment (``None`` seeds drawn); ``(observations (E, size), infos)``."""
        if len(seeds) != self.num_envs:
            raise ValueError(f"`seeds` must hold one seed (or None) per environment ({self.num_envs}); got {len(seeds)}")
        episode_seeds = self._seeds(seeds)
        self.world = BatchedWorld(SimEpisodes(self.scenario, episode_seeds, device=self.device), dtype=self.dtype,
                                  kinematics=False)
        self.layer.forget()
        observations, self._decision = self._observations(torch.arange(self.num_envs, device=self.device))
        solve_ms = WallTime(self._decision.scored.solve_ms if self._decision is not None else 0.0)
        return observations, [{"solve_ms": solve_ms, "episode_seed": s} for s in episode_seeds]

    def advance(self, actions: Sequence[Any]) -> BatchStep:
        """One agent step of every environment, then a new episode (drawn seed) in every one that
        ended (the auto-reset of both vector APIs).

        Every environment turns its action into a goal command at its current state and holds it
        for ``decision_frames`` frames; each frame is ONE safety-layer call for all running
        environments (:meth:`mmpc.rl.safety.SafetyLayer.frame`) and one simulator step. The
        observations after the step come from one more solve (the decision solve of the next
        step), plus one for the last states of the episodes that ended.
        """
        if self.sim is None:
            raise RuntimeError("call reset() before step()")
        if len(actions) != self.num_envs:
            raise ValueError(f"`actions` must hold one action per environment ({self.num_envs}); got {len(actions)}")
        checked = []
        for index, action in enumerate(actions):
            try:
                checked.append(check_action(action, self.config, self.continuous))
            except ValueError as error:
                raise ValueError(f"environment {index}: {error}") from None
        if bool(self.sim.done.any()):
            raise RuntimeError(f"environments {self.sim.done.nonzero()[:, 0].tolist()} are over: reset them first")
        everyone = torch.arange(self.num_envs, device=self.device)
        step = AgentStep.begin(self.layer, self.world.observe(everyone)[0], action_tensor(checked, self.continuous),
                               continuous=self.continuous, period=1.0 / self.scenario.frequency,
                               solve=self._decision if self._decides_from_features_solve else None)
        tally = StepTally(self.num_envs, self.device, self.config.intervention_penalty)
        # the decision's solve was timed at the end of the step before
        run_agent_step(step, self.world, tally, lambda rows: self._frame_rewards()[rows])
        solve_ms = tally.solve_ms
        ended_crashed, speed = self.sim.crashed.clone(), self.sim.state.speed[:, 0].clone()  # before the resets
        truncated = (self.sim.done & ~ended_crashed).cpu().numpy()
        finished = self.sim.done.nonzero()[:, 0]
        final: dict[int, np.ndarray] = {}
        reset_infos: dict[int, dict] = {}
        if finished.numel():
            last, last_solve = self._observations(finished, last=True)
            final = dict(zip(finished.tolist(), last))
            if last_solve is not None:
                solve_ms.append(last_solve.scored.solve_ms)
            episode_seeds = self._seeds([None] * finished.numel())
            self.world.restart(finished, episode_seeds)
            self.layer.forget(finished)
            reset_infos = {row: {"episode_seed": seed} for row, seed in zip(finished.tolist(), episode_seeds)}
        observations, self._decision = self._observations(everyone)
        if self._decision is not None:
            solve_ms.append(self._decision.scored.solve_ms)
        for info in reset_infos.values():
            info["solve_ms"] = WallTime(self._decision.scored.solve_ms if self._decision is not None else 0.0)
        rewards, infos = tally.infos(step.commands, speed, ended_crashed,
                                     WallTime(float(np.mean(solve_ms)) if solve_ms else 0.0))
        crashed = np.array([info["crashed"] for info in infos], dtype=np.bool_)
        return BatchStep(observations, rewards, crashed, truncated, infos, final, reset_infos)


class TensorVecEnv(VecEnv):
    """A stable-baselines3 ``VecEnv`` whose environments are rows of tensors, not objects: nothing to
    close, attributes are the whole batch's, no per-environment setters or methods."""

    def close(self) -> None:
        """Nothing to release (tensors only)."""

    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        return [getattr(self, attr_name) for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        raise AttributeError(f"{type(self).__name__} holds its environments as tensors; `{attr_name}` cannot be set per "
                             "environment")

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list[Any]:
        raise AttributeError(f"{type(self).__name__} holds its environments as tensors; they have no method `{method_name}`")

    def env_is_wrapped(self, wrapper_class: type, indices=None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]


class SafeSimVecEnv(TensorVecEnv):
    """The safe environments on the batched simulator as a stable-baselines3 ``VecEnv``.

    Arguments as :class:`SafeSimBatch`. An environment whose episode ends is reset at once; its
    last observation is in ``info["terminal_observation"]`` and ``info["TimeLimit.truncated"]``
    says whether time ran out.
    """

    def __init__(self, num_envs: int, scenario: ScenarioConfig, config: SafeEnvConfig, reward: RewardConfig, *,
                 continuous: bool = False, seed: Optional[int] = None) -> None:
        self.batch = SafeSimBatch(num_envs, scenario, config, reward, continuous=continuous, seed=seed)
        self.render_mode = None
        super().__init__(num_envs, observation_space(config), action_space(config, continuous))
        self._actions: Sequence[Any] = ()

    @property
    def layer(self) -> SafetyLayer:
        return self.batch.layer

    def reset(self) -> VecEnvObs:
        observations, infos = self.batch.reset(list(self._seeds))
        self.reset_infos = infos
        self._reset_seeds()
        self._reset_options()
        return observations

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = list(actions)

    def step_wait(self) -> VecEnvStepReturn:
        step = self.batch.advance(self._actions)
        dones = step.terminated | step.truncated
        for index, info in enumerate(step.infos):
            info["TimeLimit.truncated"] = bool(step.truncated[index])
            if index in step.final:
                info["terminal_observation"] = step.final[index]
                self.reset_infos[index] = step.reset_infos[index]
        return step.observations, step.rewards.astype(np.float32), dones, step.infos


class SafeSimVectorEnv(gym.vector.VectorEnv):
    """The safe environments on the batched simulator as a gymnasium 1.x ``VectorEnv``
    (``SAME_STEP`` auto-reset: ``infos["final_obs"]`` / ``infos["final_info"]`` hold the
    ended episodes' last step). Arguments as :class:`SafeSimBatch`."""

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(self, num_envs: int, scenario: ScenarioConfig, config: SafeEnvConfig, reward: RewardConfig, *,
                 continuous: bool = False, seed: Optional[int] = None) -> None:
        self.batch = SafeSimBatch(num_envs, scenario, config, reward, continuous=continuous, seed=seed)
        self.num_envs = num_envs
        self.single_observation_space = observation_space(config)
        self.single_action_space = action_space(config, continuous)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)

    def reset(self, *, seed: int | Sequence[Optional[int]] | None = None, options: Optional[dict] = None):
        if seed is None:
            seeds: list[Optional[int]] = [None] * self.num_envs
        elif isinstance(seed, (int, np.integer)):
            self.batch.rng = np.random.default_rng(int(seed))
            seeds = [int(seed) + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
        observations, env_infos = self.batch.reset(seeds)
        infos: dict = {}
        for index, info in enumerate(env_infos):
            infos = self._add_info(infos, info, index)
        return observations, infos

    def step(self, actions):
        step = self.batch.advance(list(actions))
        infos: dict = {}
        for index, info in enumerate(step.infos):
            if index in step.final:
                infos = self._add_info(infos, {"final_obs": step.final[index], "final_info": info}, index)
                info = step.reset_infos[index]
            infos = self._add_info(infos, info, index)
        return step.observations, step.rewards, step.terminated, step.truncated, infos
