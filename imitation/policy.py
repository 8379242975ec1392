"""The cloned policy: an MLP from highway-env's kinematics observation to the (acceleration,
steering) command, its checkpoint file, and the driver that runs it (``bc:RUN/policy.pt``).

Inputs. The (R, F) kinematics observation is flattened; the ego's absolute x (row 0, feature
``x``) is dropped by default: on an endless straight road it only encodes the distance driven
(and it saturates at 200 m), so keeping it invites the policy to key on elapsed time. By
default the command the ego is executing -- its acceleration a [m/s^2] and heading rate psidot
[rad/s], ``Observation.ego[:, 4:6]``, part of the vehicle's state in highway-env but not of the
kinematics observation -- is appended: the expert plans from it (its plans start at the current
acceleration), and it alone explains 91 % / 98 % of the variance of the expert's next
acceleration / steering in the cruise demonstrations, against a held-out loss of 0.69 (31 %
explained) for the kinematics observation alone. The D inputs are standardised with the
training set's mean and standard deviation, ``z = (o - mu_o) / sigma_o``.

Outputs. The network predicts standardised commands ``u_hat``; the command is
``u = clip(mu_u + sigma_u * u_hat, low, high)`` with highway-env's acceleration and steering
ranges as bounds. Training minimises the mean squared error in standardised units, so
acceleration (m/s^2) and steering (rad) weigh alike. Every statistic is a buffer, so the
module alone maps observations to commands.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from torch import nn

from mmpc.config import dataclass_from_dict
from mmpc.drivers import Decision, Driver, Observation
from mmpc.highway import ACCELERATION_RANGE, STEERING_RANGE
from mmpc.problem import EGO_A, EGO_PSIDOT

logger = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "mmpc-policy"
CHECKPOINT_VERSION = 1
ACTIVATIONS = {"tanh": nn.Tanh, "relu": nn.ReLU}


@dataclass(frozen=True)
class PolicyConfig:
    """Architecture of :class:`MLPPolicy`.

    Attributes:
        hidden: widths of the hidden layers [-].
        activation: ``tanh`` or ``relu``.
        drop_ego_x: leave out the ego's absolute x position (row 0, column 1 of the observation).
        ego_command: append the ego's executing (a [m/s^2], psidot [rad/s]) to the inputs.
    """

    hidden: tuple[int, ...] = (256, 256)
    activation: str = "tanh"
    drop_ego_x: bool = True
    ego_command: bool = True

    def __post_init__(self) -> None:
        if isinstance(self.hidden, list):
            object.__setattr__(self, "hidden", tuple(self.hidden))
        if not self.hidden or not all(isinstance(h, int) and not isinstance(h, bool) and h > 0 for h in self.hidden):
            raise ValueError(f"`hidden` must be a non-empty list of positive ints; got {self.hidden!r}")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"`activation` must be one of {sorted(ACTIVATIONS)}; got {self.activation!r}")

    @classmethod
    def from_dict(cls, values: dict) -> "PolicyConfig":
        return dataclass_from_dict(cls, values, where="policy config")


class MLPPolicy(nn.Module):
    """Kinematics observation (and the ego's executing command) -> (acceleration [m/s^2],
    steering [rad]).

    Args:
        observation_shape: (R, F) of the kinematics observation.
        config: the architecture.

    Shapes:
        forward: kinematics (B, R, F), ego_command (B, 2) (a [m/s^2], psidot [rad/s]; required
        when ``config.ego_command``) -> (B, 2).

    Example:
        >>> policy = MLPPolicy((5, 5), PolicyConfig(hidden=(32,)))
        >>> policy(torch.zeros(3, 5, 5), torch.zeros(3, 2)).shape
        torch.Size([3, 2])
    """

    def __init__(self, observation_shape: tuple[int, int], config: PolicyConfig = PolicyConfig()) -> None:
        super().__init__()
        rows, features = (int(v) for v in observation_shape)
        if rows < 1 or features < 2:
            raise ValueError(f"`observation_shape` must be (rows >= 1, features >= 2); got {observation_shape}")
        self.observation_shape = (rows, features)
        self.config = config
        raw = rows * features + (2 if config.ego_command else 0)  # the flat vector :meth:`raw_inputs` builds
        keep = [i for i in range(raw) if not (config.drop_ego_x and i == 1)]
        self.register_buffer("keep", torch.tensor(keep, dtype=torch.long))
        width = len(keep)
        self.register_buffer("obs_mean", torch.zeros(width))
        self.register_buffer("obs_std", torch.ones(width))
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
        return int(self.keep.numel())

    def fit_normalization(self, observations: np.ndarray | torch.Tensor, commands: Optional[np.ndarray | torch.Tensor],
                          actions: np.ndarray | torch.Tensor) -> None:
        """Set the input and output statistics from training data ((S, R, F), (S, 2) or None, (S, 2))."""
        inputs = self.select(torch.as_tensor(observations, dtype=torch.float32),
                             None if commands is None else torch.as_tensor(commands, dtype=torch.float32))
        actions = torch.as_tensor(actions, dtype=torch.float32)
        self.obs_mean.copy_(inputs.mean(dim=0))
        self.obs_std.copy_(_spread(inputs))
        self.act_mean.copy_(actions.mean(dim=0))
        self.act_std.copy_(_spread(actions))

    @property
    def raw_size(self) -> int:
        """Length of the flat vector of :meth:`raw_inputs`: R * F (+ 2 with the ego command)."""
        return self.observation_shape[0] * self.observation_shape[1] + (2 if self.config.ego_command else 0)

    def raw_inputs(self, observations: torch.Tensor, ego_command: Optional[torch.Tensor] = None) -> torch.Tensor:
        """(B, R, F) and (B, 2) -> (B, R * F [+ 2]): the flattened observation, then the command."""
        if observations.ndim != 3 or tuple(observations.shape[1:]) != self.observation_shape:
            raise ValueError(f"observations must have shape (B, {self.observation_shape[0]}, {self.observation_shape[1]}); "
                             f"got {tuple(observations.shape)}")
        flat = observations.reshape(observations.shape[0], -1)
        if not self.config.ego_command:
            return flat
        if ego_command is None or ego_command.shape != (observations.shape[0], 2):
            raise ValueError(f"this policy reads the ego's executing command: `ego_command` must have shape "
                             f"({observations.shape[0]}, 2); got {None if ego_command is None else tuple(ego_command.shape)}")
        return torch.cat([flat, ego_command.to(flat.dtype)], dim=1)

    def select(self, observations: torch.Tensor, ego_command: Optional[torch.Tensor] = None) -> torch.Tensor:
        """(B, R, F) [and (B, 2)] -> (B, D) inputs (flattened, ego x dropped)."""
        return self.raw_inputs(observations, ego_command).index_select(1, self.keep)

    def standardized(self, observations: torch.Tensor, ego_command: Optional[torch.Tensor] = None) -> torch.Tensor:
        """(B, R, F) [and (B, 2)] -> (B, 2) standardised command (what the loss compares)."""
        return self.head(self.body((self.select(observations, ego_command) - self.obs_mean) / self.obs_std))

    def standardize_actions(self, actions: torch.Tensor) -> torch.Tensor:
        """(B, 2) commands -> standardised units."""
        return (actions - self.act_mean) / self.act_std

    def forward(self, observations: torch.Tensor, ego_command: Optional[torch.Tensor] = None) -> torch.Tensor:
        command = self.act_mean + self.act_std * self.standardized(observations, ego_command)
        return torch.maximum(torch.minimum(command, self.act_high), self.act_low)


def _spread(values: torch.Tensor) -> torch.Tensor:
    """Per-column standard deviation of (S, D) data, 1 where a column is (nearly) constant
    (e.g. the ego's presence flag): such inputs stay 0 after centring, and no huge weights
    appear when the statistics are folded into a layer (:mod:`mmpc.imitation.export`)."""
    std = values.std(dim=0) if values.shape[0] > 1 else torch.zeros(values.shape[1])
    return torch.where(std > 1e-4, std, torch.ones_like(std))


def fold(policy: MLPPolicy) -> nn.Sequential:
    """The policy as one plain network from :meth:`MLPPolicy.raw_inputs` (B, R * F [+ 2]) to the
    command (B, 2) before clipping, with the input selection and standardisation folded into the
    first layer and the output scaling into the last (computed in float64):

    ``W1 ((S o - mu_o) / sigma_o) + b1 = W1' o + b1'`` with ``W1'[:, keep] = W1 / sigma_o`` (zero
    columns for dropped inputs), ``b1' = b1 - W1 (mu_o / sigma_o)``; ``mu_u + sigma_u (W h + b) =
    W' h + b'`` with ``W' = diag(sigma_u) W``, ``b' = mu_u + sigma_u b``.

    It has fewer operations than :meth:`MLPPolicy.forward` (the driver's per-step cost) and is
    what :mod:`mmpc.imitation.export` writes into stable-baselines3.
    """
    layers: list[nn.Module] = []
    linears = [m for m in policy.body if isinstance(m, nn.Linear)]
    with torch.no_grad():
        for index, source in enumerate(linears):
            layer = nn.Linear(policy.raw_size if index == 0 else source.in_features, source.out_features)
            if index == 0:
                weight = source.weight.double() / policy.obs_std.double()
                layer.weight.zero_()
                layer.weight[:, policy.keep] = weight.float()
                layer.bias.copy_(source.bias.double() - weight @ policy.obs_mean.double())
            else:
                layer.load_state_dict(source.state_dict())
            layers += [layer, ACTIVATIONS[policy.config.activation]()]
        head = nn.Linear(policy.head.in_features, 2)
        head.weight.copy_(policy.act_std.double()[:, None] * policy.head.weight.double())
        head.bias.copy_(policy.act_mean.double() + policy.act_std.double() * policy.head.bias.double())
    return nn.Sequential(*layers, head).eval()


def save_policy(path: Path, policy: MLPPolicy, *, scenario: Optional[str] = None, info: Optional[dict] = None) -> Path:
    """Write a checkpoint (architecture, weights and statistics, plus JSON-able ``info``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    config = asdict(policy.config)
    config["hidden"] = list(config["hidden"])
    temporary = path.with_name(f".tmp-{path.name}")
    torch.save({
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "config": config,
        "observation_shape": list(policy.observation_shape),
        "state_dict": policy.state_dict(),
        "scenario": scenario,
        "info": info or {},
    }, temporary)
    temporary.replace(path)
    return path


def load_checkpoint(path: Path) -> dict:
    """Read a checkpoint written by :func:`save_policy` (tensors and plain data only)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"policy checkpoint {path} does not exist (train one with `mmpc imitate bc` or `dagger`)")
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises several types for a file that is not a checkpoint
        raise ValueError(f"{path} is not a readable torch checkpoint ({type(error).__name__}: {error})") from error
    if not isinstance(checkpoint, dict) or checkpoint.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path} is not an mmpc policy checkpoint (format {CHECKPOINT_FORMAT!r} expected)")
    if checkpoint.get("version") != CHECKPOINT_VERSION:
        raise ValueError(f"{path}: checkpoint version {checkpoint.get('version')!r}; this mmpc reads {CHECKPOINT_VERSION}")
    return checkpoint


def load_policy(path: Path) -> MLPPolicy:
    """The :class:`MLPPolicy` of a checkpoint, in eval mode."""
    checkpoint = load_checkpoint(path)
    policy = MLPPolicy(tuple(checkpoint["observation_shape"]), PolicyConfig.from_dict(checkpoint["config"]))
    policy.load_state_dict(checkpoint["state_dict"])
    return policy.eval()


class PolicyDriver(Driver):
    """Drives with a cloned policy: one forward pass for the E environments of a step.

    Args:
        policy: the policy.
        name: the driver's name in tables.
    """

    def __init__(self, policy: MLPPolicy, name: str = "bc") -> None:
        self.policy = policy.eval()
        self.network = fold(self.policy)  # the same map in fewer operations
        self.name = name

    def decide(self, observation: Observation) -> Decision:
        if observation.kinematics is None:
            raise ValueError("a policy driver needs `observation.kinematics` (highway-env's Kinematics observation); got None")
        start = time.perf_counter()
        with torch.inference_mode():
            kinematics = torch.as_tensor(observation.kinematics, dtype=torch.float32)
            raw = self.policy.raw_inputs(kinematics, observation.ego[:, EGO_A:EGO_PSIDOT + 1].float())
            command = torch.clamp(self.network(raw), self.policy.act_low, self.policy.act_high)
        elapsed_ms = (time.perf_counter() - start) * 1e3
        return Decision.command_only(command[:, 0].clone(), command[:, 1].clone(), elapsed_ms)


def make_policy_driver(scenario, argument: Optional[str]) -> Driver:
    """Driver factory for the spec ``bc:PATH`` (a checkpoint of :func:`save_policy`)."""
    if not argument:
        raise ValueError("driver 'bc' needs a checkpoint path: 'bc:RUN/policy.pt'")
    checkpoint = load_checkpoint(Path(argument))
    if checkpoint.get("scenario") not in (None, scenario.name):
        logger.warning("policy %s was trained on scenario %r; driving %r", argument, checkpoint["scenario"], scenario.name)
    return PolicyDriver(load_policy(Path(argument)), name=f"bc:{argument}")
