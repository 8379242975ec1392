"""The cloned policy: an MLP from road-frame features to the (acceleration, steering) command,
its checkpoint file, and the driver that runs it (``bc:RUN/policy.pt``).

Inputs. :func:`mmpc.imitation.features.road_features` of the ego state and its K nearest
neighbours: the ego's lateral offsets from its lane centre and the road edges, heading and
speed (optionally the command it is executing), and each neighbour's presence, relative position
and relative velocity. The D inputs are standardised with the training set's mean and standard
deviation, ``z = (f - mu_f) / sigma_f``.

Outputs. The network predicts standardised commands ``u_hat``; the command is
``u = clip(mu_u + sigma_u * u_hat, low, high)`` with highway-env's acceleration and steering
ranges as bounds. Training minimises the mean squared error in standardised units, so
acceleration (m/s^2) and steering (rad) weigh alike. Every statistic is a buffer, and the road
the features refer to is part of the checkpoint, so a checkpoint alone maps states to commands.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from torch import nn

from mmpc.drivers import Decision, Driver, Observation
from mmpc.highway import ACCELERATION_RANGE, STEERING_RANGE
from mmpc.imitation.checkpoint import CheckpointKind, load_model, read_model, save_model
from mmpc.imitation.features import (
    LEGACY_SCENE, STORED_NEIGHBOURS, FeatureConfig, SceneGeometry, nearest_neighbours, road_features,
)
from mmpc.road import Road

logger = logging.getLogger(__name__)

ACTIVATIONS = {"tanh": nn.Tanh, "relu": nn.ReLU}


@dataclass(frozen=True)
class PolicyConfig:
    """Architecture and inputs of :class:`MLPPolicy`.

    Attributes:
        hidden: widths of the hidden layers [-].
        activation: ``tanh`` or ``relu``.
        neighbours: nearest other vehicles read (:class:`mmpc.imitation.features.FeatureConfig`) [-].
        ego_command: also read the ego's executing (a [m/s^2], psidot [rad/s]). Off by default:
            held-out loss 0.066 with it against 0.67 without, but the policy then copies the
            executing command in closed loop (causal confusion); DAgger leaves it off too.
        lane_slots: also read the nearest neighbour ahead and behind in the ego's and the
            adjacent lanes.
    """

    hidden: tuple[int, ...] = (256, 256)
    activation: str = "tanh"
    neighbours: int = STORED_NEIGHBOURS
    ego_command: bool = False
    lane_slots: bool = True

    def __post_init__(self) -> None:
        if isinstance(self.hidden, list):
            object.__setattr__(self, "hidden", tuple(self.hidden))
        if not self.hidden or not all(isinstance(h, int) and not isinstance(h, bool) and h > 0 for h in self.hidden):
            raise ValueError(f"`hidden` must be a non-empty list of positive ints; got {self.hidden!r}")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"`activation` must be one of {sorted(ACTIVATIONS)}; got {self.activation!r}")
        self.feature_config(LEGACY_SCENE)  # validates the feature settings

    def feature_config(self, scene: SceneGeometry) -> FeatureConfig:
        """The features this policy reads in a scene (the scenario's vehicle length and ellipse)."""
        return FeatureConfig(scene, self.neighbours, self.ego_command, self.lane_slots)


class MLPPolicy(nn.Module):
    """Road-frame features -> (acceleration [m/s^2], steering [rad]).

    Args:
        road: the road the features refer to (lane centres, edges).
        config: the architecture and inputs.
        scene: the vehicle length and ellipse the features use
            (:func:`mmpc.imitation.features.scene_geometry` of the training scenario).

    Shapes:
        forward: features (B, D) (:meth:`features`) -> (B, 2).

    Example:
        >>> from mmpc.imitation.features import SceneGeometry
        >>> policy = MLPPolicy(Road(), PolicyConfig(hidden=(32,), neighbours=2), scene=SceneGeometry(5.0, (8.0, 3.3)))
        >>> ego = np.array([[0.0, 8.0, 0.0, 14.0, 0.0, 0.0]])
        >>> neighbours = np.array([[[30.0, 8.0, 10.0, 0.0], [np.nan] * 4]])
        >>> policy(torch.as_tensor(policy.features(ego, neighbours))).shape
        torch.Size([1, 2])
    """

    def __init__(self, road: Road, config: PolicyConfig = PolicyConfig(), *, scene: SceneGeometry) -> None:
        super().__init__()
        self.road = road
        self.config = config
        self.scene = scene
        self.feature_config = config.feature_config(scene)
        width = self.feature_config.size
        self.register_buffer("in_mean", torch.zeros(width))
        self.register_buffer("in_std", torch.ones(width))
        self.register_buffer("act_mean", torch.zeros(2))
        self.register_buffer("act_std", torch.ones(2))
        self.register_buffer("act_low", torch.tensor([ACCELERATION_RANGE[0], STEERING_RANGE[0]], dtype=torch.float32))
        self.register_buffer("act_high", torch.tensor([ACCELERATION_RANGE[1], STEERING_RANGE[1]], dtype=torch.float32))
        layers: list[nn.Module] = []
        for size in config.hidden:
            layers += [nn.Linear(width, size), ACTIVATIONS[config.activation]()]
            width = size
        self.body = nn.Sequential(*layers)
        self.head = nn.Linear(width, 2)

    @property
    def input_size(self) -> int:
        """D, the number of features."""
        return self.feature_config.size

    def features(self, ego: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
        """(B, 6) ego states and (B, K', 4) nearest neighbours -> (B, D) float32 features."""
        return road_features(ego, neighbours, self.road, self.feature_config)

    def fit_normalization(self, inputs: np.ndarray | torch.Tensor, actions: np.ndarray | torch.Tensor) -> None:
        """Set the input and output statistics from training data ((S, D), (S, 2))."""
        inputs = torch.as_tensor(inputs, dtype=torch.float32)
        actions = torch.as_tensor(actions, dtype=torch.float32)
        self.in_mean.copy_(inputs.mean(dim=0))
        self.in_std.copy_(_spread(inputs))
        self.act_mean.copy_(actions.mean(dim=0))
        self.act_std.copy_(_spread(actions))

    def _check(self, inputs: torch.Tensor) -> None:
        if inputs.ndim != 2 or inputs.shape[1] != self.input_size:
            raise ValueError(f"`inputs` must have shape (B, {self.input_size}) (road features); got {tuple(inputs.shape)}")

    def standardized(self, inputs: torch.Tensor) -> torch.Tensor:
        """(B, D) features -> (B, 2) standardised command (what the loss compares)."""
        self._check(inputs)
        return self.head(self.body((inputs - self.in_mean) / self.in_std))

    def standardize_actions(self, actions: torch.Tensor) -> torch.Tensor:
        """(B, 2) commands -> standardised units."""
        return (actions - self.act_mean) / self.act_std

    def forward(self, inputs: torch.Tensor) -> torch.Tensor:
        command = self.act_mean + self.act_std * self.standardized(inputs)
        return torch.maximum(torch.minimum(command, self.act_high), self.act_low)


def _spread(values: torch.Tensor) -> torch.Tensor:
    """Per-column standard deviation of (S, D) data, 1 where a column is (nearly) constant
    (e.g. the ego's presence flag): such inputs stay 0 after centring, and no huge weights
    appear when the statistics are folded into a layer (:mod:`mmpc.imitation.export`)."""
    std = values.std(dim=0) if values.shape[0] > 1 else torch.zeros(values.shape[1])
    return torch.where(std > 1e-4, std, torch.ones_like(std))


def fold(policy: MLPPolicy) -> nn.Sequential:
    """The policy as one plain network from features (B, D) to the command (B, 2) before
    clipping, with the standardisation folded into the first layer and the output scaling into
    the last (computed in float64):

    ``W1 ((f - mu_f) / sigma_f) + b1 = W1' f + b1'`` with ``W1' = W1 diag(1 / sigma_f)``,
    ``b1' = b1 - W1' mu_f``; ``mu_u + sigma_u (W h + b) = W' h + b'`` with
    ``W' = diag(sigma_u) W``, ``b' = mu_u + sigma_u b``.

    It is what :class:`PolicyDriver` runs (in numpy) and what :mod:`mmpc.imitation.export`
    writes into stable-baselines3.
    """
    layers: list[nn.Module] = []
    linears = [m for m in policy.body if isinstance(m, nn.Linear)]
    with torch.no_grad():
        for index, source in enumerate(linears):
            layer = nn.Linear(source.in_features, source.out_features)
            if index == 0:
                weight = source.weight.double() / policy.in_std.double()
                layer.weight.copy_(weight)
                layer.bias.copy_(source.bias.double() - weight @ policy.in_mean.double())
            else:
                layer.load_state_dict(source.state_dict())
            layers += [layer, ACTIVATIONS[policy.config.activation]()]
        head = nn.Linear(policy.head.in_features, 2)
        head.weight.copy_(policy.act_std.double()[:, None] * policy.head.weight.double())
        head.bias.copy_(policy.act_mean.double() + policy.act_std.double() * policy.head.bias.double())
    return nn.Sequential(*layers, head).eval()


#: The policy's checkpoint (:mod:`mmpc.imitation.checkpoint`). Version 2: road-frame features
#: (version 1 read highway-env's Kinematics observation); a file without a scene has the legacy one.
POLICY_CHECKPOINT = CheckpointKind("mmpc-policy", 2, what="policy", hint="train one with `mmpc imitate bc` or `dagger`",
                                   config_type=PolicyConfig, legacy_scene=LEGACY_SCENE)


def save_policy(path: Path, policy: MLPPolicy, *, scenario: Optional[str] = None, info: Optional[dict] = None) -> Path:
    """Write a checkpoint (architecture, road, scene geometry, weights and statistics, plus
    JSON-able ``info``)."""
    return save_model(path, POLICY_CHECKPOINT, policy, scenario=scenario, info=info)


def load_policy_checkpoint(path: Path) -> dict:
    """Read a checkpoint written by :func:`save_policy`; a missing, foreign or damaged file raises."""
    return read_model(path, POLICY_CHECKPOINT)


def load_policy(path: Path) -> MLPPolicy:
    """The :class:`MLPPolicy` of a checkpoint file, in eval mode."""
    return policy_from_checkpoint(load_policy_checkpoint(path))


def policy_from_checkpoint(checkpoint: dict) -> MLPPolicy:
    """The :class:`MLPPolicy` of a checkpoint read by :func:`load_policy_checkpoint`, in eval mode. A
    checkpoint written before the features read the scenario has no ``scene``: its policy keeps
    the geometry it was trained with, :data:`mmpc.imitation.features.LEGACY_SCENE`."""
    return load_model(checkpoint, POLICY_CHECKPOINT, MLPPolicy)


class PolicyDriver(Driver):
    """Drives with a cloned policy: features and one forward pass for the E environments of a step.

    The forward pass is :func:`fold`'s network evaluated with numpy on its weights (float32): at
    E = 1 the per-step cost is dominated by call overhead, which numpy keeps to a few
    microseconds per layer.

    Args:
        policy: the policy.
        name: the driver's name in tables.
    """

    def __init__(self, policy: MLPPolicy, name: str = "bc") -> None:
        self.policy = policy.eval()
        linears = [m for m in fold(self.policy) if isinstance(m, nn.Linear)]
        self.layers = [(m.weight.detach().numpy().T.copy(), m.bias.detach().numpy().copy()) for m in linears]
        self.activation = {"tanh": np.tanh, "relu": lambda x: np.maximum(x, 0.0)}[policy.config.activation]
        self.low, self.high = policy.act_low.numpy(), policy.act_high.numpy()
        self.name = name

    def commands(self, features: np.ndarray) -> np.ndarray:
        """(B, D) features -> (B, 2) clipped commands (the folded network in numpy)."""
        hidden = features
        for weight, bias in self.layers[:-1]:
            hidden = self.activation(hidden @ weight + bias)
        weight, bias = self.layers[-1]
        return np.clip(hidden @ weight + bias, self.low, self.high)

    def decide(self, observation: Observation) -> Decision:
        start = time.perf_counter()
        mask = None if observation.vehicle_mask is None else observation.vehicle_mask.numpy()
        neighbours = nearest_neighbours(observation.ego.numpy(), observation.vehicles.numpy(), mask,  # all stored ones
                                        ellipse=self.policy.scene.ellipse)
        command = self.commands(self.policy.features(observation.ego.numpy(), neighbours))
        elapsed_ms = (time.perf_counter() - start) * 1e3
        return Decision.command_only(torch.from_numpy(command[:, 0].copy()), torch.from_numpy(command[:, 1].copy()), elapsed_ms)


def make_policy_driver(scenario, argument: Optional[str]) -> Driver:
    """Driver factory for the spec ``bc:PATH`` (a checkpoint of :func:`save_policy`)."""
    if not argument:
        raise ValueError("driver 'bc' needs a checkpoint path: 'bc:RUN/policy.pt'")
    checkpoint = load_policy_checkpoint(Path(argument))
    if checkpoint.get("scenario") not in (None, scenario.name):
        logger.warning("policy %s was trained on scenario %r; driving %r", argument, checkpoint["scenario"], scenario.name)
    policy = policy_from_checkpoint(checkpoint)
    if policy.road != scenario.road:
        raise ValueError(f"policy {argument} was trained on {policy.road}; scenario {scenario.name!r} has {scenario.road}")
    return PolicyDriver(policy, name=f"bc:{argument}")
