"""Gymnasium environments in which an RL agent chooses goals and the batch optimizer drives.

``mmpc/SafeHighway-v0`` (discrete goals: lane offset x target speed) and
``mmpc/SafeHighwayContinuous-v0`` (Box goals for SAC / PPO), registered by :mod:`mmpc.rl`.

One agent step lasts ``k = decision_frames`` simulation frames: the agent's goal command is held
for the k frames while the safety layer (:class:`mmpc.rl.safety.SafetyLayer`) replans at every
frame, or at the decision only and tracks the plan in between (``SafeEnvConfig.replan``), and
(``SafeEnvConfig.verify``, the default) takes each frame's command only where it keeps a
verified way out. Rewards are summed over the frames; the step ends early at a collision.

A :class:`SafeHighwayEnv` is the engine :class:`mmpc.rl.engine.SafeEnvs` with one environment, in
the scenario's world (highway-env unless ``scenario.sim`` says ``batched``). For throughput,
step many at once: :class:`mmpc.rl.vec_env.SafeVecEnv` (stable-baselines3) or
:class:`mmpc.rl.vec_env.SafeVectorEnv` (gymnasium) solve all of them in ONE optimizer call per
frame. Observations and actions: :mod:`mmpc.rl.spaces`.
"""

from __future__ import annotations

from typing import Any, Optional

import gymnasium as gym
import numpy as np

from mmpc.config import from_dict
from mmpc.rl.config import RL_SCENARIO, RewardConfig, SafeEnvConfig
from mmpc.rl.engine import SEED_RANGE, SafeEnvs
from mmpc.rl.safety import SafetyLayer
from mmpc.rl.spaces import action_space, check_action, observation_space
from mmpc.scenario import ScenarioConfig, load_scenario


class SafeHighwayEnv(gym.Env):
    """highway-env with the batch optimizer as a safe action layer; the agent picks goals.

    Args:
        scenario: the driving scenario, a :class:`mmpc.ScenarioConfig` or the name / path of
            one (default :data:`mmpc.rl.config.RL_SCENARIO`); its ``duration`` is the episode
            length, its ``sim`` the world.
        config: environment settings (a :class:`SafeEnvConfig` or a mapping of its fields).
        reward: reward settings (a :class:`RewardConfig` or a mapping of its fields).
        continuous: Box actions ``[-1, 1]^2`` (lateral target, speed) instead of the discrete
            grid ``lane_offsets x speeds``.
        layer: a safety layer to share with other environments (one compiled optimizer for all);
            default: a new one for the scenario.
        render_mode: ``None`` or ``"rgb_array"``.

    ``info`` of a step: ``intervention`` (bool, some frame overrode the agent),
    ``intervention_frames``, ``fallback_frames``, ``solved_frames`` (frames a solve served the
    environment; the others tracked the plan held), ``frames``, ``feasible_goals`` (feasible
    candidates at the last frame, the agent's included), ``agent_feasible`` (last frame),
    ``solve_ms`` (mean wall time of the optimizer calls of this step; in a vectorized batch
    one call serves every environment), ``residuals`` (the executed candidate's obstacle,
    acceleration and non-holonomic residuals at the last frame), ``speed`` (end) and
    ``mean_speed`` (over the frames) [m/s], ``crashed``, ``goal`` (the held command y, v); with
    ``env.verify``, ``verified_frames`` (frames whose command kept a verified way out) and
    ``failsafe_frames`` (frames the stored fail-safe drove).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        scenario: ScenarioConfig | str | None = None,
        config: SafeEnvConfig | dict | None = None,
        reward: RewardConfig | dict | None = None,
        *,
        continuous: bool = False,
        layer: Optional[SafetyLayer] = None,
        render_mode: Optional[str] = None,
    ) -> None:
        if isinstance(scenario, str) or scenario is None:
            scenario = load_scenario(RL_SCENARIO if scenario is None else scenario)
        if not isinstance(scenario, ScenarioConfig):
            raise TypeError(f"`scenario` must be a ScenarioConfig, a scenario name or None; got {type(scenario).__name__}")
        self.scenario = scenario
        self.config = config if isinstance(config, SafeEnvConfig) else from_dict(SafeEnvConfig, config, where="env")
        self.reward_config = reward if isinstance(reward, RewardConfig) else from_dict(RewardConfig, reward, where="reward")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"`render_mode` must be None or 'rgb_array'; got {render_mode!r}")
        self.render_mode = render_mode
        self.continuous = bool(continuous)
        self.engine = SafeEnvs(1, scenario, self.config, self.reward_config, continuous=self.continuous, layer=layer,
                               render=render_mode == "rgb_array")
        self.layer = self.engine.layer
        self.action_space = action_space(self.config, self.continuous)
        self.observation_space = observation_space(self.config)

    @property
    def env_id(self) -> int:
        """This environment's id among those of its layer (keys its warm starts and stored fail-safe)."""
        return int(self.engine.ids[0])

    @property
    def episode(self) -> Optional[Any]:
        """The running episode (a :class:`mmpc.highway.HighwayEpisode` on highway-env), ``None`` before :meth:`reset`."""
        return None if self.engine.world is None else self.engine.world.episodes[0]

    @property
    def episode_seed(self) -> Optional[int]:
        """The seed of the running episode, ``None`` before :meth:`reset`."""
        return self.engine.seeds[0] if self.engine.seeds else None

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None) -> tuple[np.ndarray, dict]:
        """Start an episode; ``seed`` (or one drawn from the environment's generator) seeds
        highway-env and the traffic, so a seed fixes the whole episode."""
        super().reset(seed=seed)
        episode_seed = int(seed) if seed is not None else int(self.np_random.integers(SEED_RANGE))
        observations, infos = self.engine.reset([episode_seed])
        return observations[0], infos[0]

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        step = self.engine.advance([action], auto_reset=False)
        return step.observations[0], float(step.rewards[0]), bool(step.terminated[0]), bool(step.truncated[0]), step.infos[0]

    def check_action(self, action: Any) -> Any:
        """``action`` checked against the action space (:func:`mmpc.rl.spaces.check_action`)."""
        return check_action(action, self.config, self.continuous)

    def render(self) -> Optional[np.ndarray]:
        if self.render_mode != "rgb_array" or self.episode is None:
            return None
        return self.episode.env.render()

    def close(self) -> None:
        self.engine.close()
