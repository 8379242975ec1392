"""The plain environments: the safe environments' world, traffic, episodes and reward, with no
safety layer; the agent drives with highway-env's ``DiscreteMetaAction``.

The unprotected baseline of a recipe, measured on the ground the safe agents stand on: the
scenario's world (``scenario.sim``: highway-env's episodes or the batched simulator, so a plain
agent trains as fast as the world steps), its traffic (re-spawned around the ego), the same car
(the world's command limits) and the same reward summed over the frames. Each agent step is
``decision_frames`` frames: the meta-action moves the targets at the first, the lane and speed
controller of :mod:`mmpc.rl.meta_actions` commands every frame, as highway-env's ``MDPVehicle``.

Observation: highway-env's ``Kinematics`` rows (``kinematics_vehicles`` x presence, x, y, vx, vy,
normalised and clipped to [-1, 1]), flattened. ``info``: ``speed`` (end) and ``mean_speed`` (over
the frames) [m/s], ``crashed``, ``frames``; a reset's ``episode_seed``.
"""

from __future__ import annotations

from typing import Any, Optional, Sequence

import numpy as np
import torch
from gymnasium import spaces

from mmpc.config import require_int
from mmpc.highway.worlds import World, make_world
from mmpc.rl.config import RewardConfig, SafeEnvConfig
from mmpc.rl.engine import BatchStep, draw_seeds
from mmpc.rl.meta_actions import META_ACTIONS, MetaActions, MetaTargets
from mmpc.rl.reward import task_rewards
from mmpc.rl.spaces import check_index, observation_vectors
from mmpc.scenario import ScenarioConfig


def plain_action_space() -> spaces.Discrete:
    """highway-env's ``DiscreteMetaAction`` (:data:`mmpc.rl.meta_actions.META_ACTIONS`)."""
    return spaces.Discrete(len(META_ACTIONS))


class PlainEnvs:
    """E plain environments on the world of ``scenario.sim``; the engine of :class:`mmpc.rl.vec_env.PlainVecEnv`.

    Args:
        num_envs: E.
        scenario: the driving scenario (its ``sim`` chooses the world, its ``duration`` is the
            episode length, its ``device`` where the batched world runs).
        config: the environment settings of the recipe; the plain agent reads ``decision_frames``,
            ``kinematics_vehicles`` and ``meta_speeds`` (the goal settings are the layer's).
        reward: reward settings (``intervention_penalty`` never applies: nothing intervenes).
        seed: seeds the draws of episode seeds for resets that get none.
        device: where the batched world runs; default the run's (:func:`mmpc.device.run_device`).
    """

    def __init__(self, num_envs: int, scenario: ScenarioConfig, config: SafeEnvConfig, reward: RewardConfig, *,
                 seed: Optional[int] = None, device: torch.device | str | None = None) -> None:
        require_int("", low=1, num_envs=num_envs)
        self.num_envs = num_envs
        self.scenario = scenario
        self.config = config
        self.reward = reward
        self.device = device
        self.meta = MetaActions(scenario.road, scenario.vehicle[0], config.meta_speeds)
        self.rng = np.random.default_rng(seed)
        self.world: Optional[World] = None
        self.seeds: list[int] = []
        self.targets: Optional[MetaTargets] = None

    def _egos(self, rows: torch.Tensor) -> torch.Tensor:
        """(R, 6) float64 road-frame ego states of environments ``rows``, on the host."""
        return self.world.observe(rows.to(self.world.device))[0].ego.to(device="cpu", dtype=torch.float64)

    def _observations(self, rows: torch.Tensor) -> np.ndarray:
        return observation_vectors(self.world.kinematics_rows(rows.to(self.world.device), self.config.kinematics_vehicles),
                                   None, self.config)

    def _start_targets(self, rows: torch.Tensor) -> None:
        started = self.meta.start(self._egos(rows))
        self.targets.lane[rows], self.targets.speed_index[rows] = started.lane, started.speed_index

    def reset(self, seeds: Sequence[Optional[int]]) -> tuple[np.ndarray, list[dict]]:
        """Start every environment (``None`` seeds drawn); ``(observations (E, size), infos)``."""
        if len(seeds) != self.num_envs:
            raise ValueError(f"`seeds` must hold one seed (or None) per environment ({self.num_envs}); got {len(seeds)}")
        self.seeds = draw_seeds(self.rng, seeds)
        self.close()
        self.world = make_world(self.scenario, self.seeds, kinematics=False, device=self.device)
        everyone = torch.arange(self.num_envs)
        self.targets = MetaTargets(torch.zeros(self.num_envs, dtype=torch.int64), torch.zeros(self.num_envs, dtype=torch.int64))
        self._start_targets(everyone)
        return self._observations(everyone), [{"episode_seed": s} for s in self.seeds]

    def check_actions(self, actions: Sequence[Any]) -> torch.Tensor:
        """(E,) int64 meta-actions, each checked (:func:`mmpc.rl.spaces.check_index`); a refusal names the environment."""
        if len(actions) != self.num_envs:
            raise ValueError(f"`actions` must hold one action per environment ({self.num_envs}); got {len(actions)}")
        meaning = "a meta-action: " + ", ".join(f"{index} {name}" for index, name in enumerate(META_ACTIONS))
        checked = []
        for index, action in enumerate(actions):
            try:
                checked.append(check_index(action, len(META_ACTIONS), meaning))
            except ValueError as error:
                raise ValueError(str(error) if self.num_envs == 1 else f"environment {index}: {error}") from None
        return torch.tensor(checked, dtype=torch.int64)

    def advance(self, actions: Sequence[Any], *, auto_reset: bool = True) -> BatchStep:
        """One agent step of every environment: each meta-action moves its targets, then
        ``decision_frames`` frames (fewer where the episode ends) of the controller's commands.
        With ``auto_reset`` a new episode (drawn seed) starts in every one that ended.

        Raises:
            ValueError: an action outside the meta-actions, before any environment moves.
            RuntimeError: not reset, or an episode is over (reset it first).
        """
        if self.world is None:
            raise RuntimeError("call reset() before step()")
        checked = self.check_actions(actions)
        done = self.world.done().cpu()
        if bool(done.any()):
            raise RuntimeError(f"environments {done.nonzero()[:, 0].tolist()} are over: call reset() first")
        everyone = torch.arange(self.num_envs)
        self.targets = self.meta.apply(self.targets, checked, self._egos(everyone))
        rewards = torch.zeros(self.num_envs, dtype=torch.float64)
        speed_sum = torch.zeros(self.num_envs, dtype=torch.float64)
        frames = torch.zeros(self.num_envs, dtype=torch.int64)
        for _ in range(self.config.decision_frames):
            rows = (~self.world.done().cpu()).nonzero()[:, 0]
            if rows.numel() == 0:
                break
            acceleration, steering = self.meta.command(self.targets.select(rows), self._egos(rows))
            world_rows = rows.to(self.world.device)
            self.world.apply(world_rows, acceleration.to(self.world.device, self.world.dtype),
                             steering.to(self.world.device, self.world.dtype))
            terms = self.world.ego_terms(world_rows)
            rewards[rows] += task_rewards(terms, self.reward, self.scenario).to("cpu", torch.float64)
            speed_sum[rows] += terms.speed.to("cpu", torch.float64)
            frames[rows] += 1
        terms = self.world.ego_terms(everyone.to(self.world.device))
        crashed, speed = terms.crashed.bool().cpu(), terms.speed.to("cpu", torch.float64)
        ended = self.world.done().cpu()
        mean_speed = speed_sum / frames.clamp(min=1)
        infos = [{"speed": float(v), "mean_speed": float(m), "crashed": bool(c), "frames": int(f)}
                 for v, m, c, f in zip(speed.tolist(), mean_speed.tolist(), crashed.tolist(), frames.tolist())]
        finished = ended.nonzero()[:, 0] if auto_reset else torch.zeros(0, dtype=torch.int64)
        final = dict(zip(finished.tolist(), self._observations(finished))) if finished.numel() else {}
        reset_infos: dict[int, dict] = {}
        if finished.numel():  # the ended episodes start again; without auto-reset they show their last observation
            episode_seeds = draw_seeds(self.rng, [None] * finished.numel())
            self.world.restart(finished.to(self.world.device), episode_seeds)
            for row, seed in zip(finished.tolist(), episode_seeds):
                self.seeds[row] = seed
            self._start_targets(finished)
            reset_infos = {row: {"episode_seed": seed} for row, seed in zip(finished.tolist(), episode_seeds)}
        return BatchStep(self._observations(everyone), rewards.numpy(), crashed.numpy(), (ended & ~crashed).numpy(),
                         infos, final, reset_infos)

    def close(self) -> None:
        """Release the world."""
        if self.world is not None:
            self.world.close()
            self.world = None
