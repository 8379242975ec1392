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
from torch import nn

from mmpc.imitation.features import FeatureConfig, nearest_neighbours, road_features
from mmpc.imitation.policy import ACTIVATIONS, MLPPolicy, fold, load_policy
from mmpc.road import Road


class RoadFeatureObservation(gym.ObservationWrapper):
    """highway-env with the observation an exported policy reads: the road-frame features of the
    ego and its nearest vehicles, read from the simulator's true state
    (:func:`mmpc.highway.road_state`), float32 of length D.

    Args:
        env: a highway-env environment on a straight road.
        road: the road the features refer to (the policy's).
        config: which features (the policy's ``feature_config``).
    """

    def __init__(self, env: gym.Env, road: Road, config: FeatureConfig) -> None:
        super().__init__(env)
        self.road, self.config = road, config
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(config.size,), dtype=np.float32)

    def observation(self, observation: np.ndarray) -> np.ndarray:
        from mmpc.highway import RoadFrame, road_state

        state = road_state(self.env.unwrapped, RoadFrame.of(self.env.unwrapped))
        ego = state.ego.numpy()
        neighbours = nearest_neighbours(ego, state.vehicles.numpy(), ellipse=self.config.scene.ellipse)  # all stored ones
        return road_features(ego, neighbours, self.road, self.config)[0]


def _require_sb3():
    try:
        from stable_baselines3.common.policies import ActorCriticPolicy
    except ImportError as error:
        raise ImportError("exporting to stable-baselines3 needs it installed: pip install 'stable-baselines3>=2.3'") from error
    return ActorCriticPolicy


def policy_kwargs(policy: MLPPolicy, log_std: float = math.log(0.1)) -> dict[str, Any]:
    """``policy_kwargs`` for ``PPO("MlpPolicy", env, policy_kwargs=...)`` matching ``policy``'s
    architecture (actor and critic the same widths)."""
    hidden = list(policy.config.hidden)
    return {"net_arch": {"pi": hidden, "vf": hidden}, "activation_fn": ACTIVATIONS[policy.config.activation],
            "log_std_init": float(log_std)}


def copy_actor(policy: MLPPolicy, target) -> None:
    """Write ``policy``'s actor, folded as in the module docstring, into SB3 ``target``
    (an ``ActorCriticPolicy`` built with :func:`policy_kwargs`)."""
    source_linears = [m for m in policy.body if isinstance(m, nn.Linear)]
    target_linears = [m for m in target.mlp_extractor.policy_net if isinstance(m, nn.Linear)]
    flat = policy.input_size
    if len(source_linears) != len(target_linears) or target_linears[0].in_features != flat:
        raise ValueError(f"SB3 policy does not match: {len(target_linears)} hidden layers with {target_linears[0].in_features} "
                         f"inputs; expected {len(source_linears)} with {flat} (build it with policy_kwargs(policy))")
    folded = [m for m in fold(policy) if isinstance(m, nn.Linear)]
    with torch.no_grad():
        for source, destination in zip(folded[:-1], target_linears):
            destination.load_state_dict(source.state_dict())
        centre = (policy.act_high + policy.act_low) / 2
        half = (policy.act_high - policy.act_low) / 2
        target.action_net.weight.copy_(folded[-1].weight / half[:, None])
        target.action_net.bias.copy_((folded[-1].bias - centre) / half)


def to_sb3(policy: MLPPolicy, log_std: float = math.log(0.1)):
    """A new SB3 ``ActorCriticPolicy`` acting like ``policy`` (observation: the (D,) road features,
    action Box [-1, 1]^2)."""
    from gymnasium import spaces

    ActorCriticPolicy = _require_sb3()
    observation_space = spaces.Box(-np.inf, np.inf, shape=(policy.input_size,), dtype=np.float32)
    action_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
    target = ActorCriticPolicy(observation_space, action_space, lambda _: 3e-4, **policy_kwargs(policy, log_std))
    copy_actor(policy, target)
    return target.eval()


def export_sb3(checkpoint: Path, out: Path, log_std: float = math.log(0.1)) -> Path:
    """Load a cloned policy and save it as an SB3 policy file (``ActorCriticPolicy.load(out)``).

    PPO starts from it with ``ppo_from_policy`` or by hand::

        sb3 = ActorCriticPolicy.load("RUN/sb3_policy.zip")
        model = PPO("MlpPolicy", env, policy_kwargs=policy_kwargs(load_policy("RUN/policy.pt")))
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
        env = RoadFeatureObservation(env, policy.road, policy.feature_config)
    model = PPO("MlpPolicy", env, policy_kwargs=policy_kwargs(policy, log_std), **ppo_kwargs)
    copy_actor(policy, model.policy)
    return model
