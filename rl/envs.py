"""Gymnasium environments in which an RL agent chooses goals and the batch optimizer drives.

``mmpc/SafeHighway-v0`` (discrete goals: lane offset x target speed) and
``mmpc/SafeHighwayContinuous-v0`` (Box goals for SAC / PPO), registered by :mod:`mmpc.rl`.

One agent step lasts ``k = decision_frames`` simulation frames. highway-env applies an action on
the first frame of its own step only (DESIGN section 5), so the environment runs highway-env at
one frame per ``env.step`` and drives the inner loop itself: the agent's goal command is held
for the k frames while the safety layer (:class:`mmpc.rl.safety.SafetyLayer`) replans at every
frame, or at the decision only and tracks the plan in between (``SafeEnvConfig.replan``).
Rewards are summed over the frames; the step ends early at a collision.

Several environments advance together through :func:`advance`, which gathers their problems at
every frame into ONE optimizer call; a single environment's :meth:`SafeHighwayEnv.step` is
:func:`advance` over itself, and :class:`mmpc.rl.vec_env.SafeHighwayVecEnv` uses it over all of
its environments. highway-env's states are CPU tensors; the safety layer moves them to its
device (the run's, :func:`mmpc.device.run_device`), and each frame's commands and flags come
back to the host in one copy per field.

Observation: highway-env's ``Kinematics`` observation (``kinematics_vehicles`` rows x
presence, x, y, vx, vy, normalised and clipped to [-1, 1]), flattened, followed (with
``solver_features``) by (feasible, meta cost, clearance) for each goal of the discrete grid
(and for the expert's choice, with ``expert_action``).
"""

from __future__ import annotations

from typing import Any, NamedTuple, Optional, Sequence

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from mmpc.highway import HighwayEpisode
from mmpc.highway.highway_env_world import HighwayEnvWorld
from mmpc.config import from_dict
from mmpc.rl.config import RL_SCENARIO, RewardConfig, SafeEnvConfig
from mmpc.highway.kinematics import DeferredKinematics
from mmpc.rl.agent_step import AgentStep, StepTally, run_agent_step
from mmpc.rl.safety import FEATURES_PER_GOAL, SafetyLayer
from mmpc.scenario import ScenarioConfig, load_scenario

#: Features per row of highway-env's Kinematics observation (its defaults).
KINEMATICS_FEATURES = ("presence", "x", "y", "vx", "vy")


def frame_reward(episode: HighwayEpisode, reward: RewardConfig) -> float:
    """The reward of the current state (see :class:`mmpc.rl.config.RewardConfig`): highway-env's,
    or the scenario's meta cost term made a reward."""
    return float(frame_rewards([episode], reward)[0])


def frame_rewards(episodes: Sequence[HighwayEpisode], reward: RewardConfig) -> torch.Tensor:
    """(R,) float64 :func:`frame_reward` of R episodes on one road, in one call of the reward's formula."""
    if reward.source == "meta_cost":
        return torch.tensor([vehicle_meta_cost_reward(e.ego, e.scenario, reward) for e in episodes], dtype=torch.float64)
    states = torch.tensor([[e.ego.speed * np.cos(e.ego.heading), e.ego.lane_index[2] if e.ego.lane_index is not None else 0,
                            e.ego.crashed, e.ego.on_road] for e in episodes], dtype=torch.float64)
    return reward.highway_terms()(states[:, 0], states[:, 1], episodes[0].scenario.lanes, states[:, 2], states[:, 3])


def vehicle_meta_cost_reward(ego: Any, scenario: ScenarioConfig, reward: RewardConfig) -> float:
    """``source: meta_cost``'s reward (:meth:`mmpc.rl.config.RewardConfig.meta_cost_reward`) of a
    highway-env vehicle ``ego``: the scenario's meta cost term at its speed and lateral position."""
    cost = scenario.objective.stage_cost(float(ego.speed), float(ego.position[1]), scenario.road)
    return reward.meta_cost_reward(cost, float(ego.crashed), float(ego.on_road))


class WallTime(float):
    """A wall-clock measurement [ms] in ``info``, e.g. ``solve_ms``.

    It is a plain float for every use (logging, arithmetic, JSON) except equality: any two
    ``WallTime`` compare equal. Timings are a property of the machine, not of the environment's
    state, and gymnasium's ``check_env`` requires two steps from the same seed and action to
    return equal ``info`` dicts.
    """

    def __eq__(self, other: object) -> bool:
        return isinstance(other, WallTime) or float.__eq__(self, other)

    def __ne__(self, other: object) -> bool:
        return not self.__eq__(other)

    __hash__ = float.__hash__


def action_space(config: SafeEnvConfig, continuous: bool) -> spaces.Space:
    """Box ``[-1, 1]^2`` goal commands, or the discrete grid ``lane_offsets x speeds`` (then the
    expert action, with ``expert_action``)."""
    if continuous:
        if config.expert_action:
            raise ValueError("env: `expert_action` is a discrete action; continuous goals (SAC) need expert_action: false")
        return spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
    return spaces.Discrete(config.num_actions)


def observation_space(config: SafeEnvConfig) -> spaces.Box:
    """The flat observation: kinematics rows, then (with ``solver_features``) the goal features."""
    size = config.kinematics_vehicles * len(KINEMATICS_FEATURES)
    if config.solver_features:
        size += config.num_actions * FEATURES_PER_GOAL
    return spaces.Box(-1.0, 1.0, shape=(size,), dtype=np.float32)


def observation_vectors(kinematics: np.ndarray, features: Optional[np.ndarray], config: SafeEnvConfig) -> np.ndarray:
    """(E, rows, 5) Kinematics observations and (E, A, 3) solver features -> (E, size) float32
    observations, clipped to [-1, 1]."""
    expected = (config.kinematics_vehicles, len(KINEMATICS_FEATURES))
    if kinematics.shape[1:] != expected:
        raise RuntimeError(f"the Kinematics observation has shape {kinematics.shape[1:]}; expected {expected}")
    parts = [kinematics.reshape(kinematics.shape[0], -1)]
    if config.solver_features:
        parts.append(np.asarray(features, dtype=np.float32).reshape(kinematics.shape[0], -1))
    return np.clip(np.concatenate(parts, axis=1), -1.0, 1.0).astype(np.float32)


def check_action(action: Any, config: SafeEnvConfig, continuous: bool) -> Any:
    """``action`` checked against the safe environments' action space: the goal index as an int
    (a Python or numpy integer, or a 0-d integer array: SB3's vectorized environments pass numpy
    int64, ``predict`` of one observation a 0-d array), or the (2,) array of finite numbers
    (values outside [-1, 1] are clipped later).

    Raises:
        ValueError: anything else (a float index such as 2.7, an array of indices, a wrong
            shape, NaN), naming what came and what is expected.
    """
    if continuous:
        try:
            values = np.asarray(action)
        except ValueError as error:  # ragged nesting
            raise ValueError(f"`action` must be an array of 2 numbers; got {action!r}") from error
        if values.dtype.kind not in "iuf":
            raise ValueError(f"`action` must be an array of 2 numbers; got dtype {values.dtype} ({action!r})")
        if values.shape != (2,):
            raise ValueError(f"`action` must have shape (2,); got {values.shape}")
        if not np.isfinite(values).all():
            raise ValueError(f"`action` must be finite numbers (in [-1, 1]); got {values.tolist()}")
        return values
    count = config.num_actions
    if isinstance(action, np.ndarray) and action.shape == ():
        action = action[()]
    if isinstance(action, (bool, np.bool_)) or not isinstance(action, (int, np.integer)):
        came = (f"an array of shape {action.shape} and dtype {action.dtype}" if isinstance(action, np.ndarray)
                else f"{action!r} ({type(action).__name__})")
        meaning = "a goal of the grid lane_offsets x speeds" + (f", or {count - 1}: the expert's choice" if config.expert_action else "")
        raise ValueError(f"`action` must be an int in [0, {count}) ({meaning}); got {came}")
    if not 0 <= action < count:
        raise ValueError(f"`action` must be an int in [0, {count}); got {action}")
    return int(action)


def action_tensor(checked: Sequence[Any], continuous: bool) -> torch.Tensor:
    """Checked actions (:func:`check_action`) -> (E, 2) float32 continuous goals or (E,) long goal indices."""
    if continuous:
        return torch.as_tensor(np.asarray(checked, dtype=np.float32))
    return torch.as_tensor(checked, dtype=torch.long)


class StepOutcome(NamedTuple):
    """What one agent step gave one environment (gymnasium's ``step`` tuple)."""

    observation: np.ndarray
    reward: float
    terminated: bool
    truncated: bool
    info: dict


class SafeHighwayEnv(gym.Env):
    """highway-env with the batch optimizer as a safe action layer; the agent picks goals.

    Args:
        scenario: the driving scenario, a :class:`mmpc.ScenarioConfig` or the name / path of
            one (default :data:`mmpc.rl.config.RL_SCENARIO`); its ``duration`` is the episode
            length.
        config: environment settings (a :class:`SafeEnvConfig` or a mapping of its fields).
        reward: reward settings (a :class:`RewardConfig` or a mapping of its fields).
        continuous: Box actions ``[-1, 1]^2`` (lateral target, speed) instead of the discrete
            grid ``lane_offsets x speeds``.
        layer: a safety layer to share (environments of one vectorized batch must share one);
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

    Environments that share a layer get distinct ids from it (:meth:`SafetyLayer.new_env_id`), which
    key their warm starts and stored fail-safes; a reset forgets its environment's.
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
        # no warm starts: an environment reset alone is solved alone; the decision solves of its
        # neighbours in a vectorized batch would not be one decision period apart
        self.layer = layer if layer is not None else SafetyLayer.for_scenario(scenario, self.config, warm_starts=False)
        if self.layer.config != self.config:
            raise ValueError("`layer` was built for other environment settings than `config`")
        if self.layer.road != scenario.road:
            raise ValueError(f"`layer` plans on {self.layer.road}, the scenario's road is {scenario.road}")
        self.action_space = action_space(self.config, self.continuous)
        self.observation_space = observation_space(self.config)
        #: this environment's id among those of its layer (keys its stored fail-safe)
        self.env_id = self.layer.new_env_id()
        self.episode: Optional[HighwayEpisode] = None
        self.episode_seed: Optional[int] = None

    # ------------------------------------------------------------------ gymnasium API

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None) -> tuple[np.ndarray, dict]:
        """Start an episode; ``seed`` (or one drawn from the environment's generator) seeds
        highway-env and the traffic, so a seed fixes the whole episode."""
        return reset_many([self], [seed])[0]

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        return tuple(advance([self], [action])[0])  # type: ignore[return-value]

    def render(self) -> Optional[np.ndarray]:
        if self.render_mode != "rgb_array" or self.episode is None:
            return None
        return self.episode.env.render()

    def close(self) -> None:
        if self.episode is not None:
            self.episode.close()
            self.episode = None

    # ------------------------------------------------------------------ pieces used by advance

    def begin_episode(self, seed: Optional[int]) -> None:
        """Create the episode of ``seed`` (``None``: drawn from the environment's generator)."""
        super().reset(seed=seed)
        self.close()
        self.episode_seed = int(seed) if seed is not None else int(self.np_random.integers(2**31 - 1))
        self.episode = HighwayEpisode(self.scenario, self.episode_seed, render=self.render_mode == "rgb_array")
        self.layer.forget(torch.tensor([self.env_id]))
        self._kinematics = DeferredKinematics(self.episode.unwrapped, self.config.kinematics_vehicles)
        self.episode.unwrapped.observation_type = self._kinematics

    def observation(self, features: Optional[np.ndarray]) -> np.ndarray:
        """The observation vector: kinematics rows flattened, then the solver features (A, 3)."""
        if self.episode is None:
            raise RuntimeError("call reset() before observing")
        return observation_vectors(self._kinematics.compute()[None], None if features is None else features[None],
                                   self.config)[0]

    def check_action(self, action: Any) -> Any:
        """``action`` checked against the action space (:func:`check_action`)."""
        return check_action(action, self.config, self.continuous)

    @staticmethod
    def _features(envs: Sequence["SafeHighwayEnv"]) -> tuple[list[Optional[np.ndarray]], float]:
        """Solver features of each environment's current state (one solve for all); ms of it."""
        if not envs[0].config.solver_features:
            return [None] * len(envs), 0.0
        layer = envs[0].layer
        solve = layer.decision_solve(episodes_world(envs).observe(range(len(envs)))[0])
        return list(layer.features(solve)), solve.scored.solve_ms


def episodes_world(envs: Sequence[SafeHighwayEnv]) -> HighwayEnvWorld:
    """The current episodes of environments that share one safety layer, as one world observed for
    the layer (its dtype and device, no Kinematics rows)."""
    layer = envs[0].layer
    return HighwayEnvWorld([env.episode for env in envs], dtype=layer.mpc.optimizer.dtype, kinematics=False,
                           device=layer.device, env_ids=[env.env_id for env in envs])


def reset_many(envs: Sequence[SafeHighwayEnv], seeds: Sequence[Optional[int]]) -> list[tuple[np.ndarray, dict]]:
    """Reset several environments that share one safety layer; one solve for their features.

    Returns:
        ``(observation, info)`` per environment, as gymnasium's ``reset``.
    """
    if len(seeds) != len(envs):
        raise ValueError(f"`seeds` must hold one seed per environment ({len(envs)}); got {len(seeds)}")
    for env, seed in zip(envs, seeds):
        env.begin_episode(seed)
    features, solve_ms = SafeHighwayEnv._features(envs)
    return [(env.observation(f), {"solve_ms": WallTime(solve_ms), "episode_seed": env.episode_seed}) for env, f in zip(envs, features)]


def advance(envs: Sequence[SafeHighwayEnv], actions: Sequence[Any]) -> list[StepOutcome]:
    """One agent step of several environments, with ONE optimizer call per simulation frame for
    all of them (plus one for the solver features of the resulting states).

    Every environment turns its action into a goal command at its current state, holds it for
    ``decision_frames`` frames and stops early when its ego crashes or its episode's time is up.

    Args:
        envs: environments that share one safety layer and have been reset.
        actions: one action per environment.

    Returns:
        One :class:`StepOutcome` per environment, in order.

    Raises:
        ValueError: an action its environment refuses (:meth:`SafeHighwayEnv.check_action`),
            before any environment moves.
    """
    if len(envs) == 0:
        return []
    if len(actions) != len(envs):
        raise ValueError(f"`actions` must hold one action per environment ({len(envs)}); got {len(actions)}")
    checked = []
    for index, (env, action) in enumerate(zip(envs, actions)):
        try:
            checked.append(env.check_action(action))
        except ValueError as error:
            if len(envs) == 1:
                raise
            raise ValueError(f"environment {index}: {error}") from None
    actions = checked
    layer = envs[0].layer
    if any(env.layer is not layer for env in envs):
        raise ValueError("environments advanced together must share one SafetyLayer (pass `layer=` when creating them)")
    for index, env in enumerate(envs):
        if env.episode is None:
            raise RuntimeError(f"environment {index} has no episode: call reset() first")
        if env.episode.done:
            raise RuntimeError(f"environment {index}'s episode is over: call reset()")
    count = len(envs)
    config = envs[0].config
    world = episodes_world(envs)
    observation = world.observe(range(count))[0]
    solve = None
    if config.replan == "decision" and not envs[0].continuous:  # the grid solve the observation's features came from
        solve = layer.decision_solve(observation)
    step = AgentStep.begin(layer, observation, action_tensor(actions, envs[0].continuous), continuous=envs[0].continuous,
                           period=1.0 / envs[0].scenario.frequency, solve=solve)
    tally = StepTally(count, layer.device, config.intervention_penalty)
    if solve is not None:
        tally.solve_ms.append(solve.scored.solve_ms)
    run_agent_step(step, world, tally,
                   lambda rows: frame_rewards([world.episodes[i] for i in rows.tolist()], envs[0].reward_config).to(layer.device))
    features, features_ms = SafeHighwayEnv._features(envs)
    if config.solver_features:
        tally.solve_ms.append(features_ms)
    speed = torch.tensor([float(env.episode.ego.speed) for env in envs], dtype=torch.float64)
    crashed = torch.tensor([bool(env.episode.ego.crashed) for env in envs])
    rewards, infos = tally.infos(step.commands, speed, crashed, WallTime(float(np.mean(tally.solve_ms)) if tally.solve_ms else 0.0))
    return [StepOutcome(env.observation(features[i]), float(rewards[i]), info["crashed"], not info["crashed"] and env.episode.done, info)
            for i, (env, info) in enumerate(zip(envs, infos))]
