"""A stable-baselines3 ``VecEnv`` of safe environments that solves them all in one optimizer call.

:class:`SafeHighwayVecEnv` holds E :class:`mmpc.rl.envs.SafeHighwayEnv` sharing one safety
layer. Its ``step`` advances them together (:func:`mmpc.rl.envs.advance`): at every simulation
frame the problems of all E environments (each its agent's goal plus the standard goals) go to
the optimizer as ONE (E, 1 + G0) batch. With ``batched=False`` each environment is solved on its
own instead (E calls per frame), the reference the benchmark (:mod:`mmpc.rl.bench`) compares with.
The shared layer's MPC computes on the run's device (:func:`mmpc.device.run_device`); it moves
highway-env's CPU states there itself.
"""

from __future__ import annotations

from typing import Optional

import numpy as np
from stable_baselines3.common.vec_env import DummyVecEnv
from stable_baselines3.common.vec_env.base_vec_env import VecEnvObs, VecEnvStepReturn

from mmpc.config import require_int
from mmpc.rl.config import RewardConfig, SafeEnvConfig
from mmpc.rl.envs import SafeHighwayEnv, advance, reset_many
from mmpc.rl.safety import SafetyLayer
from mmpc.scenario import ScenarioConfig


class SafeHighwayVecEnv(DummyVecEnv):
    """E safe environments stepped in lockstep with one batched solve per frame.

    Args:
        num_envs: E.
        scenario: the driving scenario.
        config: environment settings.
        reward: reward settings.
        continuous: Box goal actions instead of the discrete grid.
        batched: solve all environments in one call per frame (``False``: one call each).

    Auto-reset follows SB3: an environment whose episode ends is reset at once; its last
    observation is in ``info["terminal_observation"]``.
    """

    def __init__(
        self,
        num_envs: int,
        scenario: ScenarioConfig,
        config: SafeEnvConfig,
        reward: RewardConfig,
        *,
        continuous: bool = False,
        batched: bool = True,
    ) -> None:
        require_int("", low=1, num_envs=num_envs)
        layer = SafetyLayer.for_scenario(scenario, config, warm_starts=False)  # as SafeHighwayEnv's own (mmpc.rl.envs)
        self.batched = batched

        def make() -> SafeHighwayEnv:
            return SafeHighwayEnv(scenario, config, reward, continuous=continuous, layer=layer)

        super().__init__([make for _ in range(num_envs)])
        self.layer = layer

    @property
    def safe_envs(self) -> list[SafeHighwayEnv]:
        return [env.unwrapped for env in self.envs]  # type: ignore[misc]

    def step_wait(self) -> VecEnvStepReturn:
        envs = self.safe_envs
        actions = list(self.actions)
        if self.batched:
            outcomes = advance(envs, actions)
        else:
            outcomes = [advance([env], [action])[0] for env, action in zip(envs, actions)]
        finished = []
        for index, (observation, reward, terminated, truncated, info) in enumerate(outcomes):
            self.buf_rews[index] = reward
            self.buf_dones[index] = terminated or truncated
            info["TimeLimit.truncated"] = truncated and not terminated
            if self.buf_dones[index]:
                info["terminal_observation"] = observation
                finished.append(index)
            self.buf_infos[index] = info
            self._save_obs(index, observation)
        self._reset_envs(finished)
        return self._obs_from_buf(), np.copy(self.buf_rews), np.copy(self.buf_dones), list(self.buf_infos)

    def reset(self) -> VecEnvObs:
        self._reset_envs(list(range(self.num_envs)), [self._seeds[i] for i in range(self.num_envs)])
        self._reset_seeds()
        self._reset_options()
        return self._obs_from_buf()

    def _reset_envs(self, indices: list[int], seeds: Optional[list[Optional[int]]] = None) -> None:
        """Reset the environments ``indices`` (one features solve for all of them, or one each
        when not ``batched``)."""
        if not indices:
            return
        envs = self.safe_envs
        seeds = seeds if seeds is not None else [None] * len(indices)
        if self.batched:
            results = reset_many([envs[i] for i in indices], seeds)
        else:
            results = [reset_many([envs[i]], [seed])[0] for i, seed in zip(indices, seeds)]
        for index, (observation, info) in zip(indices, results):
            self.reset_infos[index] = info
            self._save_obs(index, observation)
