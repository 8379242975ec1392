"""Behaviour cloning: regress the expert's commands on the road-frame features of the states it
visited (``mmpc imitate bc``).

Loss: mean squared error between the policy's and the expert's standardised commands,
``L = mean_s || u_hat(o_s) - (u_s - mu_u) / sigma_u ||^2`` (see :mod:`mmpc.imitation.policy`),
minimised with Adam over mini-batches. A fraction of the *episodes* is held out (whole
episodes, so that consecutive, nearly identical states do not leak into validation); the
checkpoint keeps the weights of the epoch with the lowest held-out loss. Scalars go to
TensorBoard (``train/loss``, ``val/loss``, ``val/rmse_acceleration`` [m/s^2],
``val/rmse_steering`` [rad]) with the hyperparameters as text.
"""

from __future__ import annotations

import copy
import json
import logging
import math
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, NamedTuple, Optional

import numpy as np
import torch

from mmpc.imitation.dataset import Transitions
from mmpc.config import from_dict, require_int
from mmpc.imitation.features import SceneGeometry, road_features, scene_geometry
from mmpc.imitation.policy import MLPPolicy, PolicyConfig, save_policy
from mmpc.rl.folders import run_folder
from mmpc.road import Road
from mmpc.scenario import ScenarioConfig

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrainConfig:
    """Supervised training of :class:`MLPPolicy` (``mmpc imitate bc``; ``mmpc config show bc``).

    Attributes:
        epochs: passes over the training set [-].
        batch_size: samples per Adam step [-].
        learning_rate: Adam step size [-].
        weight_decay: Adam (L2) weight decay [-].
        validation_fraction: share of episodes held out for validation, in [0, 1) [-].
        seed: seeds the split, the initialisation and the batch order.
        policy: the architecture.
    """

    epochs: int = 30
    batch_size: int = 256
    learning_rate: float = 1e-3
    weight_decay: float = 1e-4
    validation_fraction: float = 0.2
    seed: int = 0
    policy: PolicyConfig = field(default_factory=PolicyConfig)

    def __post_init__(self) -> None:
        require_int("", low=1, epochs=self.epochs, batch_size=self.batch_size)
        require_int("", low=0, seed=self.seed)
        if not (self.learning_rate > 0 and math.isfinite(self.learning_rate)):
            raise ValueError(f"`learning_rate` must be a finite number > 0; got {self.learning_rate}")
        if not self.weight_decay >= 0:
            raise ValueError(f"`weight_decay` must be >= 0; got {self.weight_decay}")
        if not 0 <= self.validation_fraction < 1:
            raise ValueError(f"`validation_fraction` must be in [0, 1); got {self.validation_fraction}")


#: The lock file a behaviour cloning run holds in its folder (:func:`mmpc.rl.folders.run_folder`).
LOCK = ".bc.lock"


class TrainingDiverged(ValueError):
    """The training loss became NaN or infinite: the learning rate is too large for the data."""


class History(NamedTuple):
    """Per-epoch losses of one training run (``val_*`` NaN without a validation set)."""

    train_loss: list[float]
    val_loss: list[float]
    val_rmse: list[tuple[float, float]]
    best_epoch: int


def split_by_episode(episodes: np.ndarray, fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Boolean (train, validation) masks over samples, holding out ``fraction`` of the distinct
    episodes (at least one when ``fraction > 0`` and there are two or more)."""
    unique = np.unique(episodes)
    held = int(round(fraction * len(unique)))
    if fraction > 0 and len(unique) >= 2:
        held = min(max(held, 1), len(unique) - 1)
    else:
        held = 0
    chosen = np.random.default_rng(seed).permutation(unique)[:held]
    validation = np.isin(episodes, chosen)
    return ~validation, validation


def _evaluate(policy: MLPPolicy, inputs: torch.Tensor, actions: torch.Tensor) -> tuple[float, tuple[float, float]]:
    with torch.no_grad():
        loss = torch.mean((policy.standardized(inputs) - policy.standardize_actions(actions)) ** 2)
        rmse = torch.sqrt(torch.mean((policy(inputs) - actions) ** 2, dim=0))
    return float(loss), (float(rmse[0]), float(rmse[1]))


def train_policy(
    data: Transitions,
    road: Road,
    config: TrainConfig = TrainConfig(),
    *,
    scene: Optional[SceneGeometry] = None,
    writer=None,
    tag: str = "",
    on_epoch: Optional[Callable[[int, float, float], None]] = None,
) -> tuple[MLPPolicy, History]:
    """Fit a new :class:`MLPPolicy` to ``data``.

    Args:
        data: (state, expert command) pairs with their episode ids.
        road: the road the states refer to.
        config: training settings.
        scene: the vehicle length and ellipse of the scenario the states come from
            (:func:`mmpc.imitation.features.scene_geometry`); ``None``: the default scenario's
            (:class:`mmpc.scenario.ScenarioConfig`, cruise).
        writer: a ``torch.utils.tensorboard.SummaryWriter`` (optional).
        tag: prefix of the scalar names (e.g. ``"round_2/"`` in DAgger).
        on_epoch: called as ``on_epoch(epoch, train_loss, val_loss)``.

    Returns:
        The policy with the weights of the best validation epoch (the last epoch without a
        validation set) and the :class:`History`.

    Raises:
        TrainingDiverged: an epoch's training or validation loss is NaN or infinite.
    """
    count = data.actions.shape[0]
    if data.actions.shape != (count, 2) or data.ego.shape != (count, 6) or data.neighbours.ndim != 3 \
            or data.neighbours.shape[0] != count or data.episodes.shape != (count,):
        raise ValueError(f"`data` must hold (S, 6) ego states, (S, K, 4) neighbours, (S, 2) actions and (S,) episode ids; "
                         f"got {data.ego.shape}, {data.neighbours.shape}, {data.actions.shape}, {data.episodes.shape}")
    if not (np.isfinite(data.ego).all() and np.isfinite(data.actions).all()):
        raise ValueError("`data` holds NaN or inf ego states or actions")
    scene = scene_geometry(ScenarioConfig()) if scene is None else scene
    inputs = torch.as_tensor(road_features(data.ego, data.neighbours, road, config.policy.feature_config(scene)))
    actions = torch.as_tensor(data.actions, dtype=torch.float32)
    train_mask, val_mask = split_by_episode(data.episodes, config.validation_fraction, config.seed)
    generator = torch.Generator().manual_seed(config.seed)
    torch.manual_seed(config.seed)
    policy = MLPPolicy(road, config.policy, scene=scene)
    train, val = torch.as_tensor(train_mask), torch.as_tensor(val_mask)
    train_in, train_act = inputs[train], actions[train]
    val_in, val_act = inputs[val], actions[val]
    policy.fit_normalization(train_in, train_act)
    optimizer = torch.optim.Adam(policy.parameters(), lr=config.learning_rate, weight_decay=config.weight_decay)
    targets = policy.standardize_actions(train_act)
    history = History([], [], [], -1)
    best_state, best_loss = None, math.inf
    count = train_in.shape[0]
    for epoch in range(config.epochs):
        policy.train()
        order = torch.randperm(count, generator=generator)
        total = 0.0
        for start in range(0, count, config.batch_size):
            index = order[start:start + config.batch_size]
            loss = torch.mean((policy.standardized(train_in[index]) - targets[index]) ** 2)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            total += float(loss.detach()) * index.numel()
        policy.eval()
        train_loss = total / count
        val_loss, rmse = _evaluate(policy, val_in, val_act) if val_in.shape[0] else (math.nan, (math.nan, math.nan))
        if not (math.isfinite(train_loss) and (math.isfinite(val_loss) or not val_in.shape[0])):
            where = f" in {tag.rstrip('/')}" if tag else ""
            raise TrainingDiverged(f"the training diverged{where}: loss {train_loss:.4g} (training), {val_loss:.4g} "
                                   f"(validation) at epoch {epoch + 1} of {config.epochs}; try a smaller learning_rate "
                                   f"(got {config.learning_rate:g})")
        history.train_loss.append(train_loss)
        history.val_loss.append(val_loss)
        history.val_rmse.append(rmse)
        score = val_loss if val_in.shape[0] else -epoch  # without validation: keep the last epoch
        if score < best_loss:
            best_loss, best_state = score, copy.deepcopy(policy.state_dict())
            history = history._replace(best_epoch=epoch)
        if writer is not None:
            writer.add_scalar(f"{tag}train/loss", train_loss, epoch)
            if val_in.shape[0]:
                writer.add_scalar(f"{tag}val/loss", val_loss, epoch)
                writer.add_scalar(f"{tag}val/rmse_acceleration", rmse[0], epoch)
                writer.add_scalar(f"{tag}val/rmse_steering", rmse[1], epoch)
        if on_epoch is not None:
            on_epoch(epoch, train_loss, val_loss)
    policy.load_state_dict(best_state)
    logger.info("trained on %d samples (%d held out): best epoch %d, val loss %.4g", count, val_in.shape[0],
                history.best_epoch, history.val_loss[history.best_epoch])
    return policy.eval(), history


def hyperparameters_text(config: Any) -> str:
    """A config as a markdown table row list for TensorBoard's text tab."""
    flat = json.loads(json.dumps(asdict(config), default=list))
    return "\n".join(["| key | value |", "|---|---|"] + [f"| {k} | {v} |" for k, v in flat.items()])


def run_bc(
    dataset_dir: Path,
    out: Path,
    config: TrainConfig = TrainConfig(),
    *,
    on_epoch: Optional[Callable[[int, float, float], None]] = None,
) -> dict:
    """Behaviour cloning from a demonstrations directory (``mmpc imitate demos --out``).

    Writes ``out/policy.pt`` (best validation epoch), ``out/train.json`` (per-epoch losses,
    the config, the dataset) and TensorBoard events under ``out/tb``, holding the folder's
    :data:`LOCK` meanwhile. A run gets a folder of its own (new, empty or missing): one holding
    anything is refused, since the run would replace or mix with it. A run that diverges writes
    no policy and takes its TensorBoard events back, so the folder takes the corrected command.

    Returns:
        The ``train.json`` content.

    Raises:
        mmpc.files.OutputFolderError: ``out`` cannot be written, another run holds it, or it
            holds files (:func:`mmpc.rl.folders.run_folder`).
        TrainingDiverged: the loss became NaN or infinite.
    """
    from torch.utils.tensorboard import SummaryWriter

    from mmpc.imitation.dataset import dataset_transitions, open_dataset

    dataset = open_dataset(Path(dataset_dir))
    data = dataset_transitions(dataset)
    scenario = from_dict(ScenarioConfig, dataset.storage.metadata["mmpc_scenario"], where=f"{dataset_dir}: mmpc_scenario")
    out = Path(out)
    with run_folder(out, LOCK, "another `mmpc imitate bc` run", describe=_held_run,
                    fresh="a behaviour cloning run neither resumes nor overwrites one"):
        try:
            with SummaryWriter(str(out / "tb")) as writer:
                writer.add_text("hyperparameters", hyperparameters_text(config))
                policy, history = train_policy(data, scenario.road, config, scene=scene_geometry(scenario),
                                               writer=writer, on_epoch=on_epoch)
        except TrainingDiverged:
            shutil.rmtree(out / "tb", ignore_errors=True)  # the folder held nothing else before this run
            raise
        report = {
            "dataset": str(dataset_dir),
            "dataset_id": dataset.spec.dataset_id,
            "episodes": int(dataset.total_episodes),
            "samples": int(data.actions.shape[0]),
            "config": json.loads(json.dumps(asdict(config), default=list)),
            "best_epoch": history.best_epoch,
            "val_loss": history.val_loss[history.best_epoch],
            "val_rmse_acceleration": history.val_rmse[history.best_epoch][0],
            "val_rmse_steering": history.val_rmse[history.best_epoch][1],
            "train_loss": history.train_loss,
            "val_loss_per_epoch": history.val_loss,
        }
        save_policy(out / "policy.pt", policy, scenario=scenario.name, info={k: report[k] for k in ("dataset_id", "samples", "best_epoch", "val_loss")})
        (out / "train.json").write_text(json.dumps(report, indent=2, default=float) + "\n")
    return report


def _held_run(out: Path) -> str:
    """What an occupied run folder holds, as words (the run its train.json records, or files)."""
    try:
        report = json.loads((out / "train.json").read_text())
        return f"a finished behaviour cloning run ({report['samples']} samples of {report['dataset']})"
    except (OSError, ValueError, TypeError, KeyError):
        return "files"
