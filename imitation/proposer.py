"""The mode proposer: a network that scores the expert's goal set from the road-frame scene, so
the optimizer solves only the few goals worth solving (``proposer:RUN/proposer.pt``).

The MPC's goal set has a fixed layout per scenario (the goal sampler's goals, then the stop
goals; :meth:`mmpc.MPC.build_problem`), so goal slot g means the same manoeuvre in every state
(e.g. "ego's lane at 16 m/s", "right lane, 160 m ahead"). The proposer maps the road features
of :mod:`mmpc.imitation.features` to two numbers per slot:

- a **score** s_g, trained listwise on the expert's ranking of its feasible goals
  (:mod:`mmpc.imitation.listwise`): the best k goals of a state are the k highest scores;
- a **feasibility logit** f_g, trained on whether the optimizer found goal g feasible.

The inputs are standardised with the training set's statistics (buffers), and the road, the
scene geometry and the goal count are part of the checkpoint, so a checkpoint alone scores states.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from torch import nn

from mmpc.config import require_int
from mmpc.imitation.checkpoint import CheckpointKind, load_model, read_model, save_model
from mmpc.imitation.features import STORED_NEIGHBOURS, FeatureConfig, SceneGeometry, road_features
from mmpc.road import Road


@dataclass(frozen=True)
class ProposerConfig:
    """Architecture and inputs of :class:`ModeProposer`.

    Attributes:
        hidden: widths of the hidden ReLU layers [-].
        neighbours: nearest other vehicles read (:class:`mmpc.imitation.features.FeatureConfig`) [-].
        ego_command: also read the command being executed (a [m/s^2], psidot [rad/s]): every
            plan starts from it, so it decides which goals are reachable.
        lane_slots: also read the nearest vehicle ahead and behind in the ego's and the
            adjacent lanes.
    """

    hidden: tuple[int, ...] = (256, 256)
    neighbours: int = STORED_NEIGHBOURS
    ego_command: bool = True
    lane_slots: bool = True

    def __post_init__(self) -> None:
        if isinstance(self.hidden, list):
            object.__setattr__(self, "hidden", tuple(self.hidden))
        if not self.hidden or not all(isinstance(h, int) and not isinstance(h, bool) and h > 0 for h in self.hidden):
            raise ValueError(f"`hidden` must be a non-empty list of positive ints; got {self.hidden!r}")
        self.feature_config(SceneGeometry(5.0, (8.0, 3.0)))  # validates the feature settings

    def feature_config(self, scene: SceneGeometry) -> FeatureConfig:
        """The features the proposer reads in a scene."""
        return FeatureConfig(scene, self.neighbours, self.ego_command, self.lane_slots)


class ModeProposer(nn.Module):
    """Road-frame features -> a score and a feasibility logit per goal slot.

    Args:
        road: the road the features refer to.
        num_goals: G, the size of the scenario's goal set (goal sampler and stop goals).
        config: architecture and inputs.
        scene: the scenario's vehicle length and obstacle ellipse
            (:func:`mmpc.imitation.features.scene_geometry`).

    Shapes:
        forward: features (B, D) -> scores (B, G), feasibility logits (B, G).

    Example:
        >>> proposer = ModeProposer(Road(), 5, ProposerConfig(hidden=(16,), neighbours=2),
        ...                         scene=SceneGeometry(5.0, (8.0, 3.0)))
        >>> ego = np.array([[0.0, 8.0, 0.0, 14.0, 0.0, 0.0]])
        >>> neighbours = np.array([[[30.0, 8.0, 10.0, 0.0], [np.nan] * 4]])
        >>> proposer.top_goals(proposer.features(ego, neighbours), 3).shape
        torch.Size([1, 3])
    """

    def __init__(self, road: Road, num_goals: int, config: ProposerConfig = ProposerConfig(), *,
                 scene: SceneGeometry) -> None:
        super().__init__()
        require_int("", low=1, num_goals=num_goals)
        self.road = road
        self.num_goals = num_goals
        self.config = config
        self.scene = scene
        self.feature_config = config.feature_config(scene)
        width = self.feature_config.size
        self.register_buffer("in_mean", torch.zeros(width))
        self.register_buffer("in_std", torch.ones(width))
        layers: list[nn.Module] = []
        for size in config.hidden:
            layers += [nn.Linear(width, size), nn.ReLU()]
            width = size
        self.body = nn.Sequential(*layers)
        self.head = nn.Linear(width, 2 * num_goals)

    @property
    def input_size(self) -> int:
        """D, the number of features."""
        return self.feature_config.size

    def features(self, ego: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
        """(B, 6) ego states and (B, K', 4) nearest neighbours -> (B, D) float32 features."""
        return road_features(ego, neighbours, self.road, self.feature_config)

    def fit_normalization(self, inputs: torch.Tensor) -> None:
        """Set the input statistics from (S, D) training features (constant columns keep std 1)."""
        std = inputs.std(dim=0) if inputs.shape[0] > 1 else torch.zeros(inputs.shape[1])
        self.in_mean.copy_(inputs.mean(dim=0))
        self.in_std.copy_(torch.where(std > 1e-4, std, torch.ones_like(std)))

    def forward(self, inputs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if inputs.ndim != 2 or inputs.shape[1] != self.input_size:
            raise ValueError(f"`inputs` must have shape (B, {self.input_size}) (road features); got {tuple(inputs.shape)}")
        out = self.head(self.body((inputs - self.in_mean) / self.in_std))
        return out[:, :self.num_goals], out[:, self.num_goals:]

    @torch.no_grad()
    def top_goals(self, features: np.ndarray | torch.Tensor, count: int, *, forced: Optional[torch.Tensor] = None) -> torch.Tensor:
        """(B, count) goal slots of the highest scores, best first.

        Args:
            features: (B, D) road features.
            count: goals to keep, 1 <= count <= G.
            forced: (B,) or (B, F) long slots that are always kept (first), e.g. the stop goal on
                the ego's lane; -1: none. A slot forced twice in a row (or -1) frees a place for
                one more proposal.
        """
        if not 1 <= count <= self.num_goals:
            raise ValueError(f"`count` must be in [1, {self.num_goals}] (the goal set); got {count}")
        scores, _ = self(torch.as_tensor(features, dtype=torch.float32))
        if forced is not None:
            forced = forced[:, None] if forced.ndim == 1 else forced
            best = scores.argmax(dim=1, keepdim=True)  # kept anyway: forcing it changes nothing
            scores = scores.scatter(1, torch.where(forced >= 0, forced, best), torch.inf)
        return scores.topk(count, dim=1).indices


#: The proposer's checkpoint (:mod:`mmpc.imitation.checkpoint`): the goal count is its own entry.
PROPOSER_CHECKPOINT = CheckpointKind("mmpc-proposer", 1, what="proposer", hint="train one with `mmpc imitate proposer`",
                                     config_type=ProposerConfig, extra=("num_goals",))


def save_proposer(path: Path, proposer: ModeProposer, *, scenario: Optional[str] = None, info: Optional[dict] = None) -> Path:
    """Write a checkpoint (architecture, goal count, road, scene, weights, statistics, JSON-able ``info``)."""
    return save_model(path, PROPOSER_CHECKPOINT, proposer, scenario=scenario, info=info, num_goals=proposer.num_goals)


def load_proposer_checkpoint(path: Path) -> dict:
    """Read a checkpoint written by :func:`save_proposer`; a missing, foreign or damaged file raises."""
    return read_model(path, PROPOSER_CHECKPOINT)


def load_proposer(path: Path) -> ModeProposer:
    """The :class:`ModeProposer` of a checkpoint file, in eval mode."""
    return proposer_from_checkpoint(load_proposer_checkpoint(path))


def proposer_from_checkpoint(checkpoint: dict) -> ModeProposer:
    """The :class:`ModeProposer` of a checkpoint read by :func:`load_proposer_checkpoint`, in eval mode."""
    return load_model(checkpoint, PROPOSER_CHECKPOINT,
                      lambda road, config, scene, num_goals: ModeProposer(road, int(num_goals), config, scene=scene))
