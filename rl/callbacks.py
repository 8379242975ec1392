"""TensorBoard scalars of the safe layer, written next to stable-baselines3's own.

:class:`SafetyTensorboardCallback` reads the ``info`` dicts of every vectorized step and, every
``log_every`` environment steps, records through the model's logger (so the values land in the
same event files as SB3's ``rollout/`` and ``train/`` scalars):

- ``solver/solve_ms``: mean wall time of an optimizer call (one call serves all environments);
- ``safety/intervention_rate``: share of simulation frames on which the layer overrode the agent;
- ``safety/verified_share``, ``safety/failsafe_rate`` (a verifying layer, ``env.verify``): share of
  simulation frames whose command kept a verified way out, and of frames the stored fail-safe drove;
- ``safety/collision_rate``: share of the last 100 finished episodes that ended in a collision;
- ``safety/crashes``, ``safety/episodes``: collisions and finished episodes since the start of the
  run (crashes per 10^5 training steps = ``crashes`` / step x 10^5);
- ``driving/mean_speed``: mean ego speed over the frames since the last write [m/s].

Environments without a safety layer (plain highway-env) give no ``solve_ms`` or intervention
figures; those scalars are then not written.

Given a :class:`CrashLog`, the callback also writes every training episode that ended in a
collision as a CSV row with what replays it: its seed, where it ended and the agent's actions.
"""

from __future__ import annotations

import csv
import json
from collections import deque
from pathlib import Path
from typing import Any, Optional

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

#: The custom scalar tags.
SCALAR_TAGS = ("solver/solve_ms", "safety/intervention_rate", "safety/verified_share", "safety/failsafe_rate",
               "safety/collision_rate", "safety/crashes", "safety/episodes", "driving/mean_speed")
#: The columns of a :class:`CrashLog`.
CRASH_LOG_COLUMNS = ("timesteps", "env", "episode_seed", "step", "time_s", "actions")


class CrashLog:
    """The training episodes that ended in a collision, one CSV row each, appended as they end (a
    killed run keeps the rows so far; a run without collisions leaves the header alone).

    Columns (:data:`CRASH_LOG_COLUMNS`): ``timesteps`` (the run's environment steps when the
    episode ended), ``env`` (its environment in the vectorized batch), ``episode_seed`` (the seed
    its environment reset it with, which fixes its traffic; empty where the environment reports
    none), ``step`` (agent steps into the episode, the crashing one included), ``time_s``
    (simulated time into the episode [s]) and ``actions`` (the agent's actions, a JSON list).
    Resetting an environment of the run's settings with ``seed=episode_seed`` and stepping it with
    ``actions`` drives the episode again (up to the floating-point rounding of a batched solve).

    Args:
        path: the CSV file, created with its header.
        frequency: simulation frames per second [Hz], to turn frames into time.
        append: keep the rows of an existing log (a resumed run), adding the header only to a
            missing or empty file.
    """

    def __init__(self, path: Path, frequency: float, *, append: bool = False) -> None:
        if not frequency > 0:
            raise ValueError(f"`frequency` must be > 0 Hz; got {frequency}")
        self.path = Path(path)
        self.frequency = frequency
        if not (append and self.path.is_file() and self.path.stat().st_size > 0):
            with open(self.path, "w", newline="") as handle:
                csv.writer(handle).writerow(CRASH_LOG_COLUMNS)

    def add(self, timesteps: int, env: int, episode: "RunningEpisode") -> None:
        """Append the crashed ``episode`` of environment ``env``."""
        with open(self.path, "a", newline="") as handle:
            csv.writer(handle).writerow([timesteps, env, "" if episode.seed is None else episode.seed, episode.steps,
                                         round(episode.frames / self.frequency, 6), json.dumps(episode.actions)])


class RunningEpisode:
    """What the callback keeps of an environment's running episode for :class:`CrashLog`: its
    seed (``None``: not reported), agent steps, simulation frames and the agent's actions."""

    def __init__(self, seed: Optional[int]) -> None:
        self.seed = None if seed is None else int(seed)
        self.steps = 0
        self.frames = 0
        self.actions: list[Any] = []


class SafetyTensorboardCallback(BaseCallback):
    """Record the safe layer's scalars every ``log_every`` environment steps.

    Args:
        log_every: environment steps (summed over the vectorized environments) between writes.
        window: finished episodes the collision rate is taken over.
        crash_log: where the episodes that ended in a collision are written (optional). The
            episodes' seeds are read from the training environment's ``reset_infos``
            (``info["episode_seed"]`` of its resets).
        totals: the collisions and finished episodes counted before this process (a resumed
            run's at its checkpoint), so ``safety/crashes`` and ``safety/episodes`` go on from them.
    """

    def __init__(self, log_every: int = 500, window: int = 100, *, crash_log: Optional[CrashLog] = None,
                 totals: tuple[int, int] = (0, 0)) -> None:
        super().__init__()
        if log_every < 1 or window < 1:
            raise ValueError(f"`log_every` and `window` must be >= 1; got {log_every}, {window}")
        self.log_every = log_every
        self.crashes: deque[bool] = deque(maxlen=window)
        self.total_crashes, self.total_episodes = (int(count) for count in totals)
        self.crash_log = crash_log
        self.episodes: list[RunningEpisode] = []
        self._reset_window()
        self._last_write = 0

    def _reset_window(self) -> None:
        self.solve_ms: list[float] = []
        self.frames = 0
        self.intervened = 0
        self.checked_frames = 0
        self.verified = 0
        self.failsafes = 0
        self.speed_sum = 0.0
        self.speed_count = 0

    def _on_training_start(self) -> None:
        self._last_write = self.num_timesteps
        if self.crash_log is not None:
            self.episodes = [RunningEpisode(info.get("episode_seed")) for info in self.training_env.unwrapped.reset_infos]

    def _on_step(self) -> bool:
        infos = self.locals.get("infos", [])
        dones = self.locals.get("dones", np.zeros(len(infos), dtype=bool))
        if self.crash_log is not None:
            self._follow_episodes(infos, dones)
        for info, done in zip(infos, dones):
            frames = int(info.get("frames", 1))
            if "solve_ms" in info:
                self.solve_ms.append(float(info["solve_ms"]))
            if "intervention_frames" in info:
                self.frames += frames
                self.intervened += int(info["intervention_frames"])
            if "verified_frames" in info:
                self.checked_frames += frames
                self.verified += int(info["verified_frames"])
                self.failsafes += int(info["failsafe_frames"])
            speed = info.get("mean_speed", info.get("speed"))
            if speed is not None and np.isfinite(speed):
                self.speed_sum += float(speed) * frames
                self.speed_count += frames
            if done:
                crashed = bool(info.get("crashed", False))
                self.crashes.append(crashed)
                self.total_crashes += crashed
                self.total_episodes += 1
        if self.num_timesteps - self._last_write >= self.log_every:
            self.write()
        return True

    def _follow_episodes(self, infos: list[dict], dones: np.ndarray) -> None:
        """Add the step to every environment's running episode; write the crashed ones that ended
        and start following the episodes their resets began."""
        # the actions the environments were given: on-policy algorithms step with the Box actions clipped
        actions = np.asarray(self.locals.get("clipped_actions", self.locals.get("actions"))).tolist()
        reset_infos = self.training_env.unwrapped.reset_infos
        for index, (info, done) in enumerate(zip(infos, dones)):
            episode = self.episodes[index]
            episode.steps += 1
            episode.frames += int(info.get("frames", 1))
            episode.actions.append(actions[index])
            if done:
                if info.get("crashed", False):
                    self.crash_log.add(self.num_timesteps, index, episode)
                self.episodes[index] = RunningEpisode(reset_infos[index].get("episode_seed"))

    def _on_training_end(self) -> None:
        self.write()

    def write(self) -> None:
        """Record what was gathered since the last write and dump the logger."""
        if self.solve_ms:
            self.logger.record("solver/solve_ms", float(np.mean(self.solve_ms)))
        if self.frames:
            self.logger.record("safety/intervention_rate", self.intervened / self.frames)
        if self.checked_frames:
            self.logger.record("safety/verified_share", self.verified / self.checked_frames)
            self.logger.record("safety/failsafe_rate", self.failsafes / self.checked_frames)
        if self.crashes:
            self.logger.record("safety/collision_rate", float(np.mean(self.crashes)))
        self.logger.record("safety/crashes", self.total_crashes)
        self.logger.record("safety/episodes", self.total_episodes)
        if self.speed_count:
            self.logger.record("driving/mean_speed", self.speed_sum / self.speed_count)
        self.logger.dump(self.num_timesteps)
        self._last_write = self.num_timesteps
        self._reset_window()
