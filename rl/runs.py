"""Trained runs read back: the model of a run folder written by ``mmpc rl train`` (or a shipped
agent, ``models/<name>/``) with the configuration it was trained with."""

from __future__ import annotations

import importlib
import logging
from pathlib import Path
from typing import Any, NamedTuple, Optional

import yaml

from mmpc.config import from_dict
from mmpc.rl.config import RLConfig

logger = logging.getLogger(__name__)

#: stable-baselines3 classes by algorithm name.
ALGORITHM_CLASSES = {"dqn": "DQN", "ppo": "PPO", "sac": "SAC"}


def algorithm_class(algo: str) -> type:
    """The stable-baselines3 class of ``algo`` (``dqn``, ``ppo``, ``sac``)."""
    if algo not in ALGORITHM_CLASSES:
        raise ValueError(f"unknown algorithm {algo!r}; expected one of {sorted(ALGORITHM_CLASSES)}")
    return getattr(importlib.import_module("stable_baselines3"), ALGORITHM_CLASSES[algo])


class TrainedRun(NamedTuple):
    """A trained run read back: the model and how it was trained."""

    model: Any
    algo: str
    env_kind: str
    continuous: bool
    config: RLConfig


#: Trained agents shipped with mmpc: ``models/<name>/`` beside this module (model.zip, config.yaml).
SHIPPED_MODELS = Path(__file__).resolve().parent / "models"


def shipped_models() -> list[str]:
    """Names of the shipped agents (``sb3:NAME`` drives one)."""
    return sorted(p.parent.name for p in SHIPPED_MODELS.glob("*/model.zip"))


def recorded_config(path: str | Path) -> Optional[RLConfig]:
    """The RL config a training run recorded, given its folder or its ``config.yaml``; ``None``
    where ``path`` is neither (e.g. a plain RL config file)."""
    path = Path(path)
    path = path / "config.yaml" if path.is_dir() else path
    record = run_record(path)
    return run_config(record["config"], path) if {"algo", "config"} <= set(record) else None


def run_record(path: Path) -> dict:
    """The mapping a run's ``config.yaml`` (``path``) holds; ``{}`` where the file is missing,
    not YAML or not a mapping."""
    try:
        record = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError):
        return {}
    return record if isinstance(record, dict) else {}


class RecordedRun(NamedTuple):
    """The settings a training run recorded in its ``config.yaml``."""

    algo: str
    env_kind: str
    seed: int
    config: RLConfig


def recorded_run(folder: str | Path) -> Optional[RecordedRun]:
    """The settings of the training run in ``folder``; ``None`` where it holds no readable record of one."""
    path = Path(folder) / "config.yaml"
    record = run_record(path)
    if not {"algo", "env", "seed", "config"} <= set(record):
        return None
    return RecordedRun(record["algo"], record["env"], int(record["seed"]), run_config(record["config"], path))


def run_config(values: Any, path: Path) -> RLConfig:
    """The RL config recorded in a run's ``config.yaml`` (``path``), read as the run was trained: a
    run recorded before ``env.verify`` existed trained without the check, so its ``verify`` is
    read ``false`` (and a warning says so; ``verified:sb3:RUN`` drives it behind the check)."""
    env = values.get("env") if isinstance(values, dict) else None
    if isinstance(env, dict) and "verify" not in env:
        logger.warning("%s: recorded before `env.verify` existed, so trained without the check; read as "
                       "`env.verify: false` (drive it behind the check with verified:sb3:...)", path)
        values = {**values, "env": {**env, "verify": False}}
    return from_dict(RLConfig, values, where=f"{path}: config")


def run_files(path: str | Path) -> tuple[Path, Path]:
    """The model file (``model.zip`` or a checkpoint; a shipped agent's by name, :func:`shipped_models`,
    where no such file exists) and the ``config.yaml`` of its run (the model's folder or the one above).

    Raises:
        FileNotFoundError: no such model or no config beside it.
    """
    path = Path(path)
    if not path.is_file() and str(path) in shipped_models():
        path = SHIPPED_MODELS / str(path) / "model.zip"
    if not path.is_file():
        raise FileNotFoundError(f"no model file {path} (shipped agents: {', '.join(shipped_models()) or 'none'})")
    for folder in (path.parent, path.parent.parent):
        if (folder / "config.yaml").is_file():
            return path, folder / "config.yaml"
    raise FileNotFoundError(f"no config.yaml next to {path} or in its parent folder; was it written by `mmpc rl train`?")


def load_run(path: str | Path) -> TrainedRun:
    """Load ``model.zip`` (or a checkpoint) of a run, with the ``config.yaml`` of its run directory
    (the model's folder or the one above, for checkpoints); or a shipped agent by name
    (:func:`shipped_models`) where no such file exists."""
    path, config_path = run_files(path)
    run = yaml.safe_load(config_path.read_text())
    config = run_config(run["config"], config_path)
    model = algorithm_class(run["algo"]).load(str(path), device="cpu")
    return TrainedRun(model, run["algo"], run["env"], run["action"] == "continuous", config)
