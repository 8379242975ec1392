"""The safe environments on the batched simulator (:mod:`mmpc.sim`): E environments in tensors,
one optimizer call per simulation frame for all of them, as a stable-baselines3 ``VecEnv``
(:class:`SafeSimVecEnv`) and a gymnasium 1.x ``VectorEnv`` (:class:`SafeSimVectorEnv`).

Observations, actions, rewards and ``info`` mean what they mean in :mod:`mmpc.rl.envs` (the
highway-env environments): highway-env's ``Kinematics`` rows and the solver features, the goal
grid or Box goals held for ``decision_frames`` frames while the safety layer replans every frame,
highway-env's reward summed over the frames minus the intervention penalty. Episodes that end
are started again at once from a new seed (SB3's auto-reset; gymnasium's ``SAME_STEP`` mode).
"""

from __future__ import annotations

from typing import Any, Optional, Sequence

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvObs, VecEnvStepReturn

from mmpc.drivers import Observation
from mmpc.rl.config import RewardConfig, SafeEnvConfig
from mmpc.rl.envs import WallTime, action_space, check_action, goal_commands, observation_space, observation_vectors
from mmpc.rl.safety import SafetyLayer
from mmpc.scenario import ScenarioConfig, batched_unsupported, build_mpc
from mmpc.sim import SimEpisodes
from mmpc.sim.observation import kinematics_observation
from mmpc.sim.reward import highway_reward

#: Episode seeds drawn for resets without one lie in [0, SEED_RANGE).
SEED_RANGE = 2 ** 31 - 1


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
    """

    def __init__(self, num_envs: int, scenario: ScenarioConfig, config: SafeEnvConfig, reward: RewardConfig, *,
                 continuous: bool = False, seed: Optional[int] = None) -> None:
        if not isinstance(num_envs, int) or isinstance(num_envs, bool) or num_envs < 1:
            raise ValueError(f"`num_envs` must be an int >= 1; got {num_envs!r}")
        reason = batched_unsupported(scenario)
        if reason is not None:
            raise ValueError(f"scenario {scenario.name!r}: {reason}")
        self.num_envs = num_envs
        self.scenario = scenario
        self.config = config
        self.reward = reward
        self.continuous = bool(continuous)
        self.layer = SafetyLayer(build_mpc(scenario), config)
        self.dtype = self.layer.mpc.optimizer.dtype
        self.rng = np.random.default_rng(seed)
        self.sim: Optional[SimEpisodes] = None

    def _seeds(self, seeds: Sequence[Optional[int]]) -> list[int]:
        return [int(s) if s is not None else int(self.rng.integers(SEED_RANGE)) for s in seeds]

    def _road_observation(self, rows: torch.Tensor) -> Observation:
        ego, vehicles, mask = self.sim.road_state()
        return Observation(ego[rows].to(self.dtype), vehicles[rows].to(self.dtype), mask[rows], None, rows)

    def _observations(self, rows: torch.Tensor) -> tuple[np.ndarray, float]:
        """(R, size) observations of environments ``rows`` and the ms of their features solve."""
        features, solve_ms = None, 0.0
        if self.config.solver_features:
            features, solve_ms = self.layer.goal_features(self._road_observation(rows))
        kinematics = kinematics_observation(self.sim.state, self.sim.config, vehicles_count=self.config.kinematics_vehicles)
        return observation_vectors(kinematics[rows].float().numpy(), features, self.config), solve_ms

    def reset(self, seeds: Sequence[Optional[int]]) -> tuple[np.ndarray, list[dict]]:
        """Start every environment (``None`` seeds drawn); ``(observations (E, size), infos)``."""
        if len(seeds) != self.num_envs:
            raise ValueError(f"`seeds` must hold one seed (or None) per environment ({self.num_envs}); got {len(seeds)}")
        episode_seeds = self._seeds(seeds)
        self.sim = SimEpisodes(self.scenario, episode_seeds)
        observations, solve_ms = self._observations(torch.arange(self.num_envs))
        return observations, [{"solve_ms": WallTime(solve_ms), "episode_seed": s} for s in episode_seeds]

    def reset_rows(self, rows: Sequence[int]) -> tuple[np.ndarray, list[dict]]:
        """Start new episodes (drawn seeds) in environments ``rows``; the others keep running."""
        rows = torch.as_tensor(list(rows), dtype=torch.long)
        episode_seeds = self._seeds([None] * rows.numel())
        self.sim.reset(rows, episode_seeds)
        observations, solve_ms = self._observations(rows)
        return observations, [{"solve_ms": WallTime(solve_ms), "episode_seed": s} for s in episode_seeds]

    def advance(self, actions: Sequence[Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[dict]]:
        """One agent step of every environment (:func:`mmpc.rl.envs.advance` on the batched simulator).

        Returns:
            observations (E, size) float32, rewards (E,) float64, terminated (E,) bool (the ego
            crashed), truncated (E,) bool (time up), one ``info`` dict per environment.
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
        count = self.num_envs
        commands = goal_commands(self.layer, self._road_observation(torch.arange(count)).ego, checked, self.continuous)
        rewards = torch.zeros(count, dtype=torch.float64)
        interventions = torch.zeros(count, dtype=torch.long)
        fallbacks = torch.zeros(count, dtype=torch.long)
        frames = torch.zeros(count, dtype=torch.long)
        speed_sum = torch.zeros(count, dtype=torch.float64)
        feasible_goals = torch.zeros(count, dtype=torch.long)
        agent_feasible = torch.zeros(count, dtype=torch.bool)
        residuals = torch.zeros(count, 3, dtype=torch.float64)
        solve_ms = []
        reward_weights = dict(collision_reward=self.reward.collision_reward, right_lane_reward=self.reward.right_lane_reward,
                              high_speed_reward=self.reward.high_speed_reward,
                              reward_speed_range=self.reward.reward_speed_range, normalize=self.reward.normalize)
        for _ in range(self.config.decision_frames):
            running = ~self.sim.done
            rows = running.nonzero()[:, 0]
            if rows.numel() == 0:
                break
            safe = self.layer.plan(self._road_observation(rows), commands[rows])
            solve_ms.append(safe.plan.solve_ms)
            command = torch.zeros(count, 2, dtype=self.sim.state.x.dtype)
            command[rows] = torch.stack([safe.plan.acceleration, safe.plan.steering], dim=1).to(command.dtype)
            self.sim.step(command, running)
            frame_reward = highway_reward(self.sim.state, self.sim.config, **reward_weights).double()
            rewards[rows] += frame_reward[rows] - self.config.intervention_penalty * safe.intervention.double()
            interventions[rows] += safe.intervention.long()
            fallbacks[rows] += safe.fallback.long()
            frames[rows] += 1
            speed_sum[rows] += self.sim.state.speed[rows, 0].double()
            feasible_goals[rows] = safe.feasible_goals
            agent_feasible[rows] = safe.agent_feasible
            result, executed, within = safe.plan.result, safe.plan.selection.index, torch.arange(rows.numel())
            residuals[rows] = torch.stack([result.residual_obstacle[within, executed], result.residual_acceleration[within, executed],
                                           result.residual_nonholonomic[within, executed]], dim=1).double()
        observations, features_ms = self._observations(torch.arange(count))
        if self.config.solver_features:
            solve_ms.append(features_ms)
        crashed = self.sim.crashed.clone()
        truncated = self.sim.done & ~crashed
        mean_ms = WallTime(float(np.mean(solve_ms)) if solve_ms else 0.0)
        speed = self.sim.state.speed[:, 0].tolist()
        columns = zip(interventions.tolist(), fallbacks.tolist(), frames.tolist(), speed, (speed_sum / frames.clamp(min=1)).tolist(),
                      crashed.tolist(), commands.tolist(), feasible_goals.tolist(), agent_feasible.tolist(), residuals.tolist())
        infos = [{
            "intervention": intervened > 0, "intervention_frames": intervened, "fallback_frames": fallback, "frames": frame,
            "solve_ms": mean_ms, "speed": end_speed, "mean_speed": mean_speed, "crashed": crash, "goal": tuple(goal),
            "feasible_goals": feasible, "agent_feasible": own,
            "residuals": {"obstacle": residual[0], "acceleration": residual[1], "nonholonomic": residual[2]},
        } for intervened, fallback, frame, end_speed, mean_speed, crash, goal, feasible, own, residual in columns]
        return observations, rewards.numpy(), crashed.numpy(), truncated.numpy(), infos


class SafeSimVecEnv(VecEnv):
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
        observations, rewards, terminated, truncated, infos = self.batch.advance(self._actions)
        dones = terminated | truncated
        for index, info in enumerate(infos):
            info["TimeLimit.truncated"] = bool(truncated[index])
        finished = dones.nonzero()[0].tolist()
        if finished:
            for index in finished:
                infos[index]["terminal_observation"] = observations[index].copy()
            fresh, reset_infos = self.batch.reset_rows(finished)
            observations[finished] = fresh
            for index, info in zip(finished, reset_infos):
                self.reset_infos[index] = info
        return observations, rewards.astype(np.float32), dones, infos

    def close(self) -> None:
        """Nothing to release (tensors only)."""

    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        return [getattr(self, attr_name) for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        raise AttributeError(f"SafeSimVecEnv holds its environments as tensors; `{attr_name}` cannot be set per environment")

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list[Any]:
        raise AttributeError(f"SafeSimVecEnv holds its environments as tensors; they have no method `{method_name}`")

    def env_is_wrapped(self, wrapper_class: type, indices=None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]


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
        observations, rewards, terminated, truncated, env_infos = self.batch.advance(list(actions))
        infos: dict = {}
        finished = (terminated | truncated).nonzero()[0].tolist()
        for index in finished:
            infos = self._add_info(infos, {"final_obs": observations[index].copy(), "final_info": env_infos[index]}, index)
        if finished:
            fresh, reset_infos = self.batch.reset_rows(finished)
            observations[finished] = fresh
            for index, info in zip(finished, reset_infos):
                env_infos[index] = info
        for index, info in enumerate(env_infos):
            infos = self._add_info(infos, info, index)
        return observations, rewards, terminated, truncated, infos
