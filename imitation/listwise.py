"""Training the mode proposer on the expert's full ranking, not only its winner.

Every labelled state carries, for each of the G goals of the MPC's goal set, the meta cost of
its solved plan and whether the optimizer found it feasible, and the goal the expert drove
(:mod:`mmpc.imitation.labels`). The proposer is trained with two terms:

- **ListMLE, truncated to the top ``depth``** (Xia et al., 2008): the expert's order pi of a
  state is its chosen goal first, then its other feasible goals by increasing meta cost; with
  scores s, ``L_rank = sum_{i <= depth} ( logsumexp_{j not in pi_1..pi_{i-1}} s_j - s_{pi_i} )``,
  the negative log-likelihood of that order's first ``depth`` places under the Plackett-Luce
  model. Infeasible goals never take a place but stay in every denominator, so they are pushed
  below the feasible ones. A state without a feasible goal contributes its first place only (the
  candidate the expert's fallback drove).
- **feasibility**: binary cross-entropy of the feasibility logits against the optimizer's flags.

``L = L_rank + feasibility_weight L_feasible``, minimised with Adam. Whole episodes are held out
for validation; the checkpoint keeps the epoch of the best held-out top-k agreement (the share of
states whose expert goal is among the proposer's ``keep`` highest scores).
"""

from __future__ import annotations

import copy
import logging
import math
from dataclasses import dataclass, field
from typing import Callable, NamedTuple, Optional

import numpy as np
import torch
import torch.nn.functional as F

from mmpc.config import require_int
from mmpc.imitation.bc import split_by_episode
from mmpc.imitation.features import SceneGeometry
from mmpc.imitation.proposer import ModeProposer, ProposerConfig
from mmpc.road import Road

logger = logging.getLogger(__name__)


class RankingLabels(NamedTuple):
    """S labelled states.

    Fields:
        ego: (S, 6) road-frame ego states (:data:`mmpc.EGO_FIELDS`).
        neighbours: (S, K, 4) nearest other vehicles (x, y, vx, vy; NaN rows: none).
        cost: (S, G) meta cost of each goal's plan (NaN where the label has none).
        feasible: (S, G) bool, the optimizer found the goal feasible.
        expert: (S,) long, the goal the expert drives (its fallback's candidate when none is feasible).
        episodes: (S,) long episode ids (the validation split holds out whole episodes).
    """

    ego: np.ndarray
    neighbours: np.ndarray
    cost: np.ndarray
    feasible: np.ndarray
    expert: np.ndarray
    episodes: np.ndarray

    @property
    def num_states(self) -> int:
        return int(self.expert.shape[0])

    @property
    def num_goals(self) -> int:
        return int(self.cost.shape[1])

    @classmethod
    def concatenate(cls, parts: list["RankingLabels"]) -> "RankingLabels":
        if not parts:
            raise ValueError("no labelled states to concatenate")
        return cls(*(np.concatenate(column) for column in zip(*parts)))

    def take(self, rows: np.ndarray) -> "RankingLabels":
        """The states of ``rows`` (indices or a bool mask)."""
        return RankingLabels(*(column[rows] for column in self))

    def check(self) -> None:
        """Raise ``ValueError`` naming what is wrong with the shapes, types or values."""
        count, goals = self.num_states, self.cost.shape[1] if self.cost.ndim == 2 else -1
        shapes = {"ego": (count, 6), "cost": (count, goals), "feasible": (count, goals), "expert": (count,),
                  "episodes": (count,)}
        for name, shape in shapes.items():
            if getattr(self, name).shape != shape:
                raise ValueError(f"labels: `{name}` must have shape {shape}; got {getattr(self, name).shape}")
        if self.neighbours.ndim != 3 or self.neighbours.shape[0] != count or self.neighbours.shape[2] != 4:
            raise ValueError(f"labels: `neighbours` must have shape ({count}, K, 4); got {self.neighbours.shape}")
        if self.feasible.dtype != np.bool_:
            raise ValueError(f"labels: `feasible` must be bool; got {self.feasible.dtype}")
        if count and (self.expert.min() < 0 or self.expert.max() >= goals):
            raise ValueError(f"labels: `expert` must be goal slots in [0, {goals}); got {self.expert.min()} .. {self.expert.max()}")
        if not np.isfinite(self.ego).all():
            raise ValueError("labels: `ego` holds NaN or inf")
        if not np.isfinite(self.cost[self.feasible]).all():
            raise ValueError("labels: a feasible goal has a NaN or infinite meta cost")


def ranking_targets(cost: torch.Tensor, feasible: torch.Tensor, expert: torch.Tensor, depth: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The expert's first ``depth`` places (see the module docstring).

    Args:
        cost: (B, G) meta costs; feasible: (B, G) bool; expert: (B,) long chosen slots.

    Returns:
        places (B, depth) long goal slots and valid (B, depth) bool (False past the last feasible goal).
    """
    others = feasible.clone()
    others.scatter_(1, expert[:, None], False)
    key = torch.where(others, torch.nan_to_num(cost, nan=math.inf), torch.full_like(cost, math.inf))
    rest = key.argsort(dim=1, stable=True)[:, :max(depth - 1, 0)]
    places = torch.cat([expert[:, None], rest], dim=1)[:, :depth]
    count = others.sum(dim=1, keepdim=True)
    valid = torch.arange(depth, device=cost.device)[None] <= count
    expert_feasible = feasible.gather(1, expert[:, None])
    valid = valid & (expert_feasible | (torch.arange(depth, device=cost.device)[None] == 0))
    return places, valid


def listmle_loss(scores: torch.Tensor, places: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Mean over states of the truncated ListMLE loss (module docstring) of (B, G) scores."""
    taken = torch.zeros_like(scores, dtype=torch.bool)
    total = scores.new_zeros(scores.shape[0])
    for place in range(places.shape[1]):
        slot = places[:, place:place + 1]
        available = scores.masked_fill(taken, -math.inf)
        term = torch.logsumexp(available, dim=1) - scores.gather(1, slot).squeeze(1)
        total = total + torch.where(valid[:, place], term, torch.zeros_like(term))
        taken = taken | (F.one_hot(slot.squeeze(1), scores.shape[1]).bool() & valid[:, place:place + 1])
    return total.mean()


def top_k_agreement(scores: torch.Tensor, expert: torch.Tensor, keep: int) -> float:
    """Share of states whose expert goal is among the ``keep`` highest of (B, G) ``scores``."""
    top = scores.topk(min(keep, scores.shape[1]), dim=1).indices
    return float((top == expert[:, None]).any(dim=1).float().mean()) if scores.shape[0] else math.nan


def feasible_recall(scores: torch.Tensor, feasible: torch.Tensor, keep: int) -> float:
    """Among states with a feasible goal, the share whose top ``keep`` holds one."""
    some = feasible.any(dim=1)
    if not bool(some.any()):
        return math.nan
    top = scores[some].topk(min(keep, scores.shape[1]), dim=1).indices
    return float(feasible[some].gather(1, top).any(dim=1).float().mean())


@dataclass(frozen=True)
class ProposerTrainConfig:
    """Training of the :class:`ModeProposer` (``mmpc imitate proposer``).

    Attributes:
        epochs: passes over the training set [-].
        batch_size: states per Adam step [-].
        learning_rate: Adam step size [-].
        weight_decay: Adam (L2) weight decay [-].
        depth: places of the expert's ranking the loss reads [-].
        feasibility_weight: weight of the feasibility term [-].
        keep: goals the driver keeps per step besides the stop goal (the agreement metric's k) [-].
        validation_fraction: share of episodes held out, in [0, 1) [-].
        seed: seeds the split, the initialisation and the batch order.
        proposer: the architecture.
    """

    epochs: int = 15
    batch_size: int = 512
    learning_rate: float = 1e-3
    weight_decay: float = 1e-5
    depth: int = 4
    feasibility_weight: float = 0.5
    keep: int = 4
    validation_fraction: float = 0.1
    seed: int = 0
    proposer: ProposerConfig = field(default_factory=ProposerConfig)

    def __post_init__(self) -> None:
        require_int("", low=1, epochs=self.epochs, batch_size=self.batch_size, depth=self.depth, keep=self.keep)
        require_int("", seed=self.seed)
        for name in ("learning_rate", "weight_decay", "feasibility_weight"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0 <= value < math.inf) or (name == "learning_rate" and value == 0):
                raise ValueError(f"`{name}` must be a finite number {'> 0' if name == 'learning_rate' else '>= 0'}; got {value!r}")
        if not 0 <= self.validation_fraction < 1:
            raise ValueError(f"`validation_fraction` must be in [0, 1); got {self.validation_fraction!r}")


class ProposerHistory(NamedTuple):
    """Per epoch: training loss, held-out top-k agreement and feasible recall; the epoch kept."""

    train_loss: list[float]
    val_agreement: list[float]
    val_recall: list[float]
    best_epoch: int


def train_proposer(
    labels: RankingLabels,
    road: Road,
    config: ProposerTrainConfig = ProposerTrainConfig(),
    *,
    scene: SceneGeometry,
    writer=None,
    tag: str = "",
    on_epoch: Optional[Callable[[int, float, float], None]] = None,
) -> tuple[ModeProposer, ProposerHistory]:
    """Fit a new :class:`ModeProposer` to ``labels`` (see the module docstring).

    Args:
        labels: the labelled states (checked with :meth:`RankingLabels.check`).
        road: the road the states refer to.
        config: training settings.
        scene: the scenario's vehicle length and ellipse (:func:`mmpc.imitation.features.scene_geometry`).
        writer: a ``torch.utils.tensorboard.SummaryWriter`` (optional).
        tag: prefix of the scalar names.
        on_epoch: called as ``on_epoch(epoch, train_loss, val_agreement)``.

    Returns:
        The proposer of the best held-out epoch (the last without a validation set) and its history.
    """
    labels.check()
    if labels.num_states == 0:
        raise ValueError("no labelled states to train on")
    torch.manual_seed(config.seed)
    proposer = ModeProposer(road, labels.num_goals, config.proposer, scene=scene)
    inputs = torch.as_tensor(proposer.features(labels.ego, labels.neighbours))
    cost = torch.as_tensor(labels.cost, dtype=torch.float32)
    feasible = torch.as_tensor(labels.feasible)
    expert = torch.as_tensor(labels.expert, dtype=torch.long)
    places, valid = ranking_targets(cost, feasible, expert, config.depth)
    train_mask, val_mask = (torch.as_tensor(m) for m in split_by_episode(labels.episodes, config.validation_fraction, config.seed))
    proposer.fit_normalization(inputs[train_mask])
    optimizer = torch.optim.Adam(proposer.parameters(), lr=config.learning_rate, weight_decay=config.weight_decay)
    generator = torch.Generator().manual_seed(config.seed)
    train_rows = train_mask.nonzero().flatten()
    history = ProposerHistory([], [], [], -1)
    best_state, best_score = None, -math.inf
    for epoch in range(config.epochs):
        proposer.train()
        order = train_rows[torch.randperm(train_rows.numel(), generator=generator)]
        total = 0.0
        for start in range(0, order.numel(), config.batch_size):
            rows = order[start:start + config.batch_size]
            scores, logits = proposer(inputs[rows])
            loss = listmle_loss(scores, places[rows], valid[rows]) \
                + config.feasibility_weight * F.binary_cross_entropy_with_logits(logits, feasible[rows].float())
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            total += float(loss.detach()) * rows.numel()
        proposer.eval()
        train_loss = total / max(train_rows.numel(), 1)
        with torch.no_grad():
            scores, _ = proposer(inputs[val_mask])
        agreement = top_k_agreement(scores, expert[val_mask], config.keep)
        recall = feasible_recall(scores, feasible[val_mask], config.keep)
        history.train_loss.append(train_loss)
        history.val_agreement.append(agreement)
        history.val_recall.append(recall)
        score = agreement if not math.isnan(agreement) else epoch  # without validation: keep the last epoch
        if score >= best_score:
            best_score, best_state = score, copy.deepcopy(proposer.state_dict())
            history = history._replace(best_epoch=epoch)
        if writer is not None:
            writer.add_scalar(f"{tag}train/loss", train_loss, epoch)
            if not math.isnan(agreement):
                writer.add_scalar(f"{tag}val/top_k_agreement", agreement, epoch)
                writer.add_scalar(f"{tag}val/feasible_recall", recall, epoch)
        if on_epoch is not None:
            on_epoch(epoch, train_loss, agreement)
    proposer.load_state_dict(best_state)
    logger.info("proposer trained on %d states (%d held out): best epoch %d, top-%d agreement %.3f",
                int(train_mask.sum()), int(val_mask.sum()), history.best_epoch, config.keep,
                history.val_agreement[history.best_epoch])
    return proposer.eval(), history
