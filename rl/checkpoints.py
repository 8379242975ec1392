"""A training run's checkpoints: written every ``train.checkpoint_every`` steps, the latest read
back to resume a run that stopped (``mmpc rl train --resume``).

``checkpoints/<algo>_<steps>_steps.zip`` holds the model; for an off-policy algorithm (DQN, SAC)
``checkpoints/<algo>_replay_buffer_<steps>_steps.pkl`` its replay buffer, the latest only (a
buffer is tens of MB). A checkpoint is written to a temporary name and renamed, so a run killed
while writing leaves the one before whole.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Callable, NamedTuple, Optional

from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm


class Checkpoint(NamedTuple):
    """A checkpoint of a run: the agent steps it had trained, its model and (off-policy) replay buffer files."""

    steps: int
    model: Path
    replay_buffer: Optional[Path]


def latest_checkpoint(folder: Path, algo: str) -> Optional[Checkpoint]:
    """The checkpoint of ``algo`` with the most steps in ``folder`` (a run's ``checkpoints/``), ``None`` without one."""
    pattern = re.compile(rf"{re.escape(algo)}_(\d+)_steps\.zip")
    found = [(int(match.group(1)), path) for path in Path(folder).glob(f"{algo}_*_steps.zip")
             if (match := pattern.fullmatch(path.name))]
    if not found:
        return None
    steps, model = max(found)
    replay = Path(folder) / f"{algo}_replay_buffer_{steps}_steps.pkl"
    return Checkpoint(steps, model, replay if replay.is_file() else None)


class Checkpoints(BaseCallback):
    """Save the model every ``every`` agent steps (counted over the vectorized environments) and at
    the end of training into ``folder`` as ``<algo>_<steps>_steps.zip``; an off-policy model's
    replay buffer beside it, the previous buffer removed."""

    def __init__(self, every: int, folder: Path, algo: str) -> None:
        super().__init__()
        self.every = every
        self.folder = Path(folder)
        self.algo = algo
        self.next_save = 0

    def _init_callback(self) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        self.next_save = (self.model.num_timesteps // self.every + 1) * self.every

    def _on_step(self) -> bool:
        if self.num_timesteps >= self.next_save:
            self.save()
            self.next_save = (self.num_timesteps // self.every + 1) * self.every
        return True

    def _on_training_end(self) -> None:
        if self.num_timesteps > 0 and not (self.folder / f"{self.algo}_{self.num_timesteps}_steps.zip").is_file():
            self.save()  # the latest checkpoint is the run's last state: a finished run resumes to a larger budget

    def save(self) -> Checkpoint:
        """Write the model (and replay buffer) at the current step count."""
        steps = self.num_timesteps
        model = self.folder / f"{self.algo}_{steps}_steps.zip"
        _save_atomic(model, self.model.save)
        replay = None
        if isinstance(self.model, OffPolicyAlgorithm):
            replay = self.folder / f"{self.algo}_replay_buffer_{steps}_steps.pkl"
            _save_atomic(replay, self.model.save_replay_buffer)
            for older in self.folder.glob(f"{self.algo}_replay_buffer_*_steps.pkl"):
                if older != replay:
                    older.unlink()
        return Checkpoint(steps, model, replay)


def _save_atomic(path: Path, save: Callable[[Path], None]) -> None:
    partial = path.with_name(path.name + ".partial")
    save(partial)
    os.replace(partial, path)
