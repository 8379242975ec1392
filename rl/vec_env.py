"""The safe environments as vector environments: E environments of one world (highway-env's
episodes or the batched simulator, ``scenario.sim``) with ONE optimizer call per simulation frame
for all of them, as a stable-baselines3 ``VecEnv`` (:class:`SafeVecEnv`) and a gymnasium 1.x
``VectorEnv`` (:class:`SafeVectorEnv`); both are views of :class:`mmpc.rl.engine.SafeEnvs`. The
plain environments (:class:`mmpc.rl.plain.PlainEnvs`, no layer) as a ``VecEnv``: :class:`PlainVecEnv`.

Observations, actions, rewards and ``info`` mean what they mean in :mod:`mmpc.rl.envs`.
Episodes that end are started again at once from a new seed (SB3's auto-reset; gymnasium's
``SAME_STEP`` mode).
"""

from __future__ import annotations

from typing import Any, Optional, Sequence

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvObs, VecEnvStepReturn

from mmpc.rl.config import RewardConfig, SafeEnvConfig
from mmpc.rl.engine import SafeEnvs
from mmpc.rl.plain import PlainEnvs, plain_action_space
from mmpc.rl.safety import SafetyLayer
from mmpc.rl.spaces import action_space, observation_space
from mmpc.scenario import ScenarioConfig


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


class EngineVecEnv(TensorVecEnv):
    """A stable-baselines3 ``VecEnv`` over an engine of E environments (``batch``: ``reset(seeds)``,
    ``advance(actions)``, ``close()``, as :class:`mmpc.rl.engine.SafeEnvs`). An environment whose
    episode ends is reset at once; its last observation is in ``info["terminal_observation"]`` and
    ``info["TimeLimit.truncated"]`` says whether time ran out."""

    def __init__(self, batch: Any, observation_space: gym.Space, action_space: gym.Space) -> None:
        self.batch = batch
        self.render_mode = None
        super().__init__(batch.num_envs, observation_space, action_space)
        self._actions: Sequence[Any] = ()

    def close(self) -> None:
        """Release the world (highway-env's episodes)."""
        self.batch.close()

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


class SafeVecEnv(EngineVecEnv):
    """E safe environments on the world of ``scenario.sim`` as a stable-baselines3 ``VecEnv``, ONE
    optimizer call per frame for all of them. Arguments as :class:`mmpc.rl.engine.SafeEnvs`."""

    def __init__(self, num_envs: int, scenario: ScenarioConfig, config: SafeEnvConfig, reward: RewardConfig, *,
                 continuous: bool = False, seed: Optional[int] = None) -> None:
        super().__init__(SafeEnvs(num_envs, scenario, config, reward, continuous=continuous, seed=seed),
                         observation_space(config), action_space(config, continuous))

    @property
    def layer(self) -> SafetyLayer:
        return self.batch.layer


class PlainVecEnv(EngineVecEnv):
    """E plain environments (no layer, highway-env's meta-actions) on the world of ``scenario.sim``
    as a stable-baselines3 ``VecEnv``. Arguments as :class:`mmpc.rl.plain.PlainEnvs`."""

    def __init__(self, num_envs: int, scenario: ScenarioConfig, config: SafeEnvConfig, reward: RewardConfig, *,
                 seed: Optional[int] = None) -> None:
        super().__init__(PlainEnvs(num_envs, scenario, config, reward, seed=seed), observation_space(config, layer=False),
                         plain_action_space())


class SafeVectorEnv(gym.vector.VectorEnv):
    """E safe environments on the world of ``scenario.sim`` as a gymnasium 1.x ``VectorEnv``
    (``SAME_STEP`` auto-reset: ``infos["final_obs"]`` / ``infos["final_info"]`` hold the
    ended episodes' last step). Arguments as :class:`mmpc.rl.engine.SafeEnvs`."""

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(self, num_envs: int, scenario: ScenarioConfig, config: SafeEnvConfig, reward: RewardConfig, *,
                 continuous: bool = False, seed: Optional[int] = None) -> None:
        self.batch = SafeEnvs(num_envs, scenario, config, reward, continuous=continuous, seed=seed)
        self.num_envs = num_envs
        self.single_observation_space = observation_space(config)
        self.single_action_space = action_space(config, continuous)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)

    def close_extras(self, **kwargs) -> None:
        """Release the world (highway-env's episodes)."""
        self.batch.close()

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
