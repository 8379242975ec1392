"""TensorBoard scalars of the safe layer, written next to stable-baselines3's own.

:class:`SafetyTensorboardCallback` reads the ``info`` dicts of every vectorized step and, every
``log_every`` environment steps, records through the model's logger (so the values land in the
same event files as SB3's ``rollout/`` and ``train/`` scalars):

- ``solver/solve_ms``: mean wall time of an optimizer call (one call serves all environments);
- ``safety/intervention_rate``: share of simulation frames on which the layer overrode the agent;
- ``safety/collision_rate``: share of the last 100 finished episodes that ended in a collision;
- ``safety/crashes``, ``safety/episodes``: collisions and finished episodes since the start of the
  run (crashes per 10^5 training steps = ``crashes`` / step x 10^5);
- ``driving/mean_speed``: mean ego speed over the frames since the last write [m/s].

Environments without a safety layer (plain highway-env) give no ``solve_ms`` or intervention
figures; those scalars are then not written.
"""

from __future__ import annotations

from collections import deque

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

#: The custom scalar tags.
SCALAR_TAGS = ("solver/solve_ms", "safety/intervention_rate", "safety/collision_rate", "safety/crashes",
               "safety/episodes", "driving/mean_speed")


class SafetyTensorboardCallback(BaseCallback):
    """Record the safe layer's scalars every ``log_every`` environment steps.

    Args:
        log_every: environment steps (summed over the vectorized environments) between writes.
        window: finished episodes the collision rate is taken over.
    """

    def __init__(self, log_every: int = 500, window: int = 100) -> None:
        super().__init__()
        if log_every < 1 or window < 1:
            raise ValueError(f"`log_every` and `window` must be >= 1; got {log_every}, {window}")
        self.log_every = log_every
        self.crashes: deque[bool] = deque(maxlen=window)
        self.total_crashes = 0
        self.total_episodes = 0
        self._reset_window()
        self._last_write = 0

    def _reset_window(self) -> None:
        self.solve_ms: list[float] = []
        self.frames = 0
        self.intervened = 0
        self.speed_sum = 0.0
        self.speed_count = 0

    def _on_step(self) -> bool:
        infos = self.locals.get("infos", [])
        dones = self.locals.get("dones", np.zeros(len(infos), dtype=bool))
        for info, done in zip(infos, dones):
            frames = int(info.get("frames", 1))
            if "solve_ms" in info:
                self.solve_ms.append(float(info["solve_ms"]))
            if "intervention_frames" in info:
                self.frames += frames
                self.intervened += int(info["intervention_frames"])
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

    def _on_training_end(self) -> None:
        self.write()

    def write(self) -> None:
        """Record what was gathered since the last write and dump the logger."""
        if self.solve_ms:
            self.logger.record("solver/solve_ms", float(np.mean(self.solve_ms)))
        if self.frames:
            self.logger.record("safety/intervention_rate", self.intervened / self.frames)
        if self.crashes:
            self.logger.record("safety/collision_rate", float(np.mean(self.crashes)))
        self.logger.record("safety/crashes", self.total_crashes)
        self.logger.record("safety/episodes", self.total_episodes)
        if self.speed_count:
            self.logger.record("driving/mean_speed", self.speed_sum / self.speed_count)
        self.logger.dump(self.num_timesteps)
        self._last_write = self.num_timesteps
        self._reset_window()
