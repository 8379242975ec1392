"""Export a cloned policy as a stable-baselines3 ``ActorCriticPolicy`` (so PPO can start from it).

The SB3 policy sees the policy's road-frame feature vector
(:func:`mmpc.imitation.features.road_features`); :class:`RoadFeatureObservation` wraps a
highway-env environment to produce exactly that from the simulator's state, as
:class:`mmpc.imitation.policy.PolicyDriver` computes it. It acts in highway-env's
``ContinuousAction`` space ``[-1, 1]^2``. The cloned policy's standardisation and its output
scaling are folded into the first and last linear layers, so the Gaussian's mean equals the
cloned command (up to float rounding):

- first layer: ``W1 ((f - mu_f) / sigma_f) + b1 = W1' f + b1'`` with
  ``W1' = W1 diag(1 / sigma_f)`` and ``b1' = b1 - W1' mu_f``;
- action layer: the env action is ``(u - c) / r`` with ``c``, ``r`` the centre and half-width of
  highway-env's ranges and ``u = mu_u + sigma_u (W h + b)``, so ``W' = diag(sigma_u / r) W`` and
  ``b' = (mu_u + sigma_u b - c) / r``. SB3 clips actions to ``[-1, 1]``, as the cloned policy
  clips to the ranges.

A lane-mode policy (:data:`mmpc.imitation.policy.LANE_MODES`) becomes a
:class:`LaneModeActorCriticPolicy`: its actor network ends in the folded heads and picks the
command of the most probable mode, and the action layer only maps that command to
``[-1, 1]^2`` (``W' = diag(1 / r)``, ``b' = -c / r``). Load it with
``LaneModeActorCriticPolicy.load``; PPO fine-tunes its heads (the argmax over modes passes no
gradient to the classifier).

The value network is left at SB3's initialisation; the exploration noise starts at
``exp(log_std)``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3.common.policies import ActorCriticPolicy
from torch import nn

from mmpc.imitation.features import FeatureConfig, nearest_neighbours, road_features
from mmpc.imitation.policy import ACTIVATIONS, MLPPolicy, fold, load_policy, select_command
from mmpc.road import Road


class RoadFeatureObservation(gym.ObservationWrapper):
    """highway-env with the observation an exported policy reads: the road-frame features of the
    ego and its nearest vehicles, read from the simulator's true state
    (:func:`mmpc.highway.road_state`), float32 of length D.

    Args:
        env: a highway-env environment on a straight road.
        road: the road the features refer to (the policy's).
        config: which features (the policy's ``config.features``).
    """

    def __init__(self, env: gym.Env, road: Road, config: FeatureConfig) -> None:
        super().__init__(env)
        self.road, self.config = road, config
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(config.size,), dtype=np.float32)

    def observation(self, observation: np.ndarray) -> np.ndarray:
        from mmpc.highway import RoadFrame, road_state

        state = road_state(self.env.unwrapped, RoadFrame.of(self.env.unwrapped))
        ego = state.ego.numpy()
        neighbours = nearest_neighbours(ego, state.vehicles.numpy())  # all stored ones, as in training
        return road_features(ego, neighbours, self.road, self.config)[0]


class LaneModeExtractor(nn.Module):
    """SB3 ``mlp_extractor`` of a lane-mode policy: the actor is the cloned MLP up to its last
    layer and ends with the command of the most probable mode (latent width 2); the critic is a
    separate MLP (SB3's ``MlpExtractor`` value branch).

    Args:
        features_dim: D, the road-feature width.
        hidden: hidden widths of both networks.
        activation_fn: their activation class.
        modes: command heads of the actor.
    """

    def __init__(self, features_dim: int, hidden: list[int], activation_fn: type[nn.Module], modes: int) -> None:
        super().__init__()
        self.modes = modes

        def mlp(widths: list[int]) -> list[nn.Module]:
            layers: list[nn.Module] = []
            for size_in, size_out in zip([features_dim] + widths[:-1], widths):
                layers += [nn.Linear(size_in, size_out), activation_fn()]
            return layers

        self.policy_net = nn.Sequential(*mlp(hidden), nn.Linear(hidden[-1], modes + 2 * modes))
        self.value_net = nn.Sequential(*mlp(hidden))
        self.latent_dim_pi, self.latent_dim_vf = 2, hidden[-1]

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.forward_actor(features), self.forward_critic(features)

    def forward_actor(self, features: torch.Tensor) -> torch.Tensor:
        return select_command(self.policy_net(features), self.modes)

    def forward_critic(self, features: torch.Tensor) -> torch.Tensor:
        return self.value_net(features)


class LaneModeActorCriticPolicy(ActorCriticPolicy):
    """SB3 actor-critic whose actor is a lane-mode cloned policy (:class:`LaneModeExtractor`);
    ``net_arch`` is ``{"pi": hidden, "vf": hidden}``.

    Args:
        lane_modes: command heads of the actor (the rest as ``ActorCriticPolicy``).
    """

    def __init__(self, *args, lane_modes: int = 3, **kwargs) -> None:
        self.lane_modes = lane_modes
        super().__init__(*args, **kwargs)

    def _build_mlp_extractor(self) -> None:
        self.mlp_extractor = LaneModeExtractor(self.features_dim, list(self.net_arch["pi"]), self.activation_fn,
                                               self.lane_modes).to(self.device)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        return {**super()._get_constructor_parameters(), "lane_modes": self.lane_modes}


def sb3_policy_class(policy: MLPPolicy):
    """The SB3 policy class for ``policy``: ``ActorCriticPolicy`` (``"MlpPolicy"``), or
    :class:`LaneModeActorCriticPolicy` for a lane-mode policy."""
    return LaneModeActorCriticPolicy if policy.config.lane_modes else ActorCriticPolicy


def policy_kwargs(policy: MLPPolicy, log_std: float = math.log(0.1)) -> dict[str, Any]:
    """``policy_kwargs`` for ``PPO(sb3_policy_class(policy), env, policy_kwargs=...)`` matching
    ``policy``'s architecture (actor and critic the same widths)."""
    hidden = list(policy.config.hidden)
    kwargs = {"net_arch": {"pi": hidden, "vf": hidden}, "activation_fn": ACTIVATIONS[policy.config.activation],
              "log_std_init": float(log_std)}
    if policy.config.lane_modes:
        kwargs["lane_modes"] = policy.config.modes
    return kwargs


def copy_actor(policy: MLPPolicy, target) -> None:
    """Write ``policy``'s actor, folded as in the module docstring, into SB3 ``target``
    (built with :func:`sb3_policy_class` and :func:`policy_kwargs`)."""
    source_linears = [m for m in policy.body if isinstance(m, nn.Linear)]
    target_linears = [m for m in target.mlp_extractor.policy_net if isinstance(m, nn.Linear)]
    hidden = len(target_linears) - (1 if policy.config.lane_modes else 0)
    flat = policy.input_size
    if len(source_linears) != hidden or target_linears[0].in_features != flat \
            or (policy.config.lane_modes and target_linears[-1].out_features != policy.config.output_size):
        raise ValueError(f"SB3 policy does not match: {len(target_linears)} linear layers with {target_linears[0].in_features} "
                         f"inputs; expected {len(source_linears)} hidden ones with {flat} (build it with "
                         "sb3_policy_class(policy) and policy_kwargs(policy))")
    folded = [m for m in fold(policy) if isinstance(m, nn.Linear)]
    centre = (policy.act_high + policy.act_low) / 2
    half = (policy.act_high - policy.act_low) / 2
    with torch.no_grad():
        if policy.config.lane_modes:  # the heads stay in the actor; the action layer scales the command
            for source, destination in zip(folded, target_linears):
                destination.load_state_dict(source.state_dict())
            target.action_net.weight.copy_(torch.diag(1.0 / half))
            target.action_net.bias.copy_(-centre / half)
            return
        for source, destination in zip(folded[:-1], target_linears):
            destination.load_state_dict(source.state_dict())
        target.action_net.weight.copy_(folded[-1].weight / half[:, None])
        target.action_net.bias.copy_((folded[-1].bias - centre) / half)


def to_sb3(policy: MLPPolicy, log_std: float = math.log(0.1)):
    """A new SB3 policy acting like ``policy`` (observation: the (D,) road features, action Box
    [-1, 1]^2): an ``ActorCriticPolicy``, or a :class:`LaneModeActorCriticPolicy`."""
    from gymnasium import spaces

    observation_space = spaces.Box(-np.inf, np.inf, shape=(policy.input_size,), dtype=np.float32)
    action_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
    target = sb3_policy_class(policy)(observation_space, action_space, lambda _: 3e-4, **policy_kwargs(policy, log_std))
    copy_actor(policy, target)
    return target.eval()


def export_sb3(checkpoint: Path, out: Path, log_std: float = math.log(0.1)) -> Path:
    """Load a cloned policy and save it as an SB3 policy file (``ActorCriticPolicy.load(out)``,
    or ``LaneModeActorCriticPolicy.load(out)`` for a lane-mode policy).

    PPO starts from it with ``ppo_from_policy`` or by hand::

        cloned = load_policy("RUN/policy.pt")
        sb3 = sb3_policy_class(cloned).load("RUN/sb3_policy.zip")
        model = PPO(sb3_policy_class(cloned), env, policy_kwargs=policy_kwargs(cloned))
        model.policy.load_state_dict(sb3.state_dict())
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    to_sb3(load_policy(Path(checkpoint)), log_std).save(str(out))
    return out


def ppo_from_policy(checkpoint: Path, env: gym.Env, log_std: float = math.log(0.1), **ppo_kwargs):
    """A stable-baselines3 PPO whose actor starts as the cloned policy.

    Args:
        checkpoint: the cloned policy.
        env: a highway-env environment with ``ContinuousAction`` (e.g. ``gym.make(scenario.env_id,
            config=env_config(scenario))``); wrapped in :class:`RoadFeatureObservation` here
            unless it already produces the policy's features.
        log_std: initial log standard deviation of the Gaussian.
        ppo_kwargs: passed to ``PPO``.
    """
    from stable_baselines3 import PPO

    policy = load_policy(Path(checkpoint))
    if env.observation_space.shape != (policy.input_size,):
        env = RoadFeatureObservation(env, policy.road, policy.config.features)
    model = PPO(sb3_policy_class(policy), env, policy_kwargs=policy_kwargs(policy, log_std), **ppo_kwargs)
    copy_actor(policy, model.policy)
    return model
