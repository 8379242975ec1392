"""Settings of the safe action layer and of RL training runs, as frozen, validated dataclasses.

A training run is described by one YAML file (``configs/rl/<name>.yaml``) read by
:func:`load_rl_config`; every section rejects unknown keys::

    scenario: {...}          # a full mmpc scenario (or the name / path of one)
    env: {decision_frames: 5, lane_offsets: [-1, 0, 1], speeds: [16, 20, 24, 28], ...}
    reward: {collision_reward: -1.0, right_lane_reward: 0.1, high_speed_reward: 0.4, ...}
    train: {n_envs: 4, log_every: 500, ...}
    algorithms: {dqn: {learning_rate: 5.0e-4, ...}, ppo: {...}, sac: {...}}

This module imports neither highway-env nor stable-baselines3.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional


from mmpc.config import (
    OptimizerConfig, dataclass_from_dict, is_finite_number, read_config_yaml, require, require_non_negative,
    require_positive,
)
from mmpc.configs import shipped_config_dir
from mmpc.scenario import CruiseObjective, EgoConfig, IDMTraffic, ScenarioConfig, load_scenario

#: Algorithms ``mmpc train-rl`` knows, with the action space each trains on by default.
ALGORITHMS: dict[str, str] = {"dqn": "discrete", "ppo": "discrete", "sac": "continuous"}
#: Action spaces each algorithm supports (stable-baselines3: DQN discrete only, SAC Box only).
SUPPORTED_ACTIONS: dict[str, tuple[str, ...]] = {"dqn": ("discrete",), "ppo": ("discrete", "continuous"), "sac": ("continuous",)}


def rl_scenario() -> ScenarioConfig:
    """The default scenario of the RL environments: highway-env's ``highway-fast-v0`` traffic
    (3 lanes, 20 IDM/MOBIL vehicles at highway-env's 21-24 m/s, density 1, ego at 25 m/s),
    30 s episodes, simulated and planned at 10 Hz. The MPC's standard goals cruise at 25 m/s
    with car-following goals on the ego's and the neighbouring lanes.

    Traffic is highway-env's own (no re-spawning window) so that the plain highway-env
    baseline (:func:`mmpc.rl.train.make_highway_env`) drives the same traffic; only vehicles
    closer than 10 m ahead of the ego in its lane at the start are moved away.
    """
    return ScenarioConfig(
        name="rl_highway_fast",
        objective=CruiseObjective(v_cruise=25.0, near_lane_speeds=(10.0, 15.0, 20.0, 25.0), near_lanes=1),
        lanes=3,
        duration=30.0,
        frequency=10.0,
        env_id="highway-fast-v0",
        ego=EgoConfig(speed=25.0, lane=None),
        traffic=IDMTraffic(vehicles_count=20, vehicles_density=1.0, target_speeds=None, window=None,
                           initial_clearance=10.0, lane_changes=True),
        # fast traffic: the high-speed scenario's ellipse and 8-degree band, not cruise's 13 degrees
        optimizer=OptimizerConfig(ellipse_a=8.0, ellipse_b=3.0, max_heading_deg=8.0, heading_target_deg=7.2),
    )


@dataclass(frozen=True)
class RewardConfig:
    """highway-env's reward, computed at every simulation frame and summed over an agent step.

    ``r = collision_reward * crashed + right_lane_reward * lane / (lanes - 1)
    + high_speed_reward * clip((v cos(heading) - low) / (high - low), 0, 1)``, mapped from
    ``[collision_reward, high_speed_reward + right_lane_reward]`` onto [0, 1] when
    ``normalize``, times 0 off the road; the safe environments subtract
    ``SafeEnvConfig.intervention_penalty`` for every frame the layer overrode the agent.

    Attributes:
        collision_reward: reward of a crashed frame (highway-env: -1).
        right_lane_reward: reward on the right lane (highway-env: 0.1).
        high_speed_reward: reward at or above ``reward_speed_range[1]`` (highway-env: 0.4).
        reward_speed_range: (low, high) forward speeds mapped onto [0, 1] [m/s] (highway-env: 20, 30).
        normalize: map the sum onto [0, 1] (highway-env: true).
    """

    collision_reward: float = -1.0
    right_lane_reward: float = 0.1
    high_speed_reward: float = 0.4
    reward_speed_range: tuple[float, float] = (20.0, 30.0)
    normalize: bool = True

    def __post_init__(self) -> None:
        for name in ("collision_reward", "right_lane_reward", "high_speed_reward"):
            require(is_finite_number(getattr(self, name)), f"reward: `{name}` must be a finite number; got {getattr(self, name)!r}")
        low_high = self.reward_speed_range
        require(isinstance(low_high, tuple) and len(low_high) == 2 and all(map(is_finite_number, low_high)) and low_high[0] < low_high[1],
                 f"reward: `reward_speed_range` must be [low, high] m/s with low < high; got {low_high!r}")
        require(isinstance(self.normalize, bool), f"reward: `normalize` must be true or false; got {self.normalize!r}")
        require(not self.normalize or self.collision_reward < self.high_speed_reward + self.right_lane_reward,
                 "reward: with `normalize`, `collision_reward` must be below high_speed_reward + right_lane_reward")

    def highway_env_config(self) -> dict:
        """The same reward as highway-env configuration keys."""
        return {
            "collision_reward": self.collision_reward,
            "right_lane_reward": self.right_lane_reward,
            "high_speed_reward": self.high_speed_reward,
            "reward_speed_range": list(self.reward_speed_range),
            "normalize_reward": self.normalize,
            "lane_change_reward": 0.0,
        }


@dataclass(frozen=True)
class SafeEnvConfig:
    """The safe goal-choosing environments (:mod:`mmpc.rl.envs`).

    The agent's action is a *goal command*, a target lateral position y [m] and a target
    average speed v [m/s]; at every simulation frame of the agent step the layer plans towards
    the goal ``(x_ego + v * horizon, y)`` together with the scenario's standard goals.

    Attributes:
        decision_frames: k, simulation frames per agent step (the goal is held, the optimizer
            replans every frame).
        lane_offsets: discrete actions: target lanes relative to the ego's lane at decision time
            (clamped to the road).
        speeds: discrete actions: target average speeds [m/s]; actions are
            ``lane_offsets x speeds``, offset-major.
        lateral_range: continuous actions: ``a[0]`` in [-1, 1] maps to the ego lane's centre
            plus ``a[0] * lateral_range`` lane widths (clamped to the lane centres of the road).
        speed_range: continuous actions: ``a[1]`` in [-1, 1] maps linearly onto (low, high) [m/s].
        solver_features: append per-goal solver features to the observation: for every goal of
            the discrete grid at the current state, feasible flag, meta cost
            ``m / (m + feature_cost_scale)`` (``m`` the cost per trajectory sample) and clearance
            ``min(1, d / 3)`` (``d`` the smallest normalised ellipse distance).
        feature_cost_scale: see ``solver_features`` [units of the meta cost].
        intervention_penalty: subtracted from the reward for every frame on which the agent's
            goal was not feasible (the layer drove another candidate or braked).
        intervention_speed_scale: a feasible candidate's distance to the agent's goal is
            ``hypot(dv / intervention_speed_scale, dy / lane_width)``: a lane weighs like this
            speed difference [m/s].
        kinematics_vehicles: rows of highway-env's ``Kinematics`` observation (ego first).
    """

    decision_frames: int = 5
    lane_offsets: tuple[int, ...] = (-1, 0, 1)
    speeds: tuple[float, ...] = (15.0, 20.0, 25.0, 28.0)
    lateral_range: float = 1.0
    speed_range: tuple[float, float] = (10.0, 28.0)
    solver_features: bool = True
    feature_cost_scale: float = 25.0
    intervention_penalty: float = 0.1
    intervention_speed_scale: float = 5.0
    kinematics_vehicles: int = 5

    def __post_init__(self) -> None:
        where = "env"
        require(isinstance(self.decision_frames, int) and self.decision_frames >= 1,
                 f"{where}: `decision_frames` must be an int >= 1; got {self.decision_frames!r}")
        require(isinstance(self.lane_offsets, tuple) and len(self.lane_offsets) > 0
                 and all(isinstance(o, int) and not isinstance(o, bool) for o in self.lane_offsets),
                 f"{where}: `lane_offsets` must be a non-empty list of ints; got {self.lane_offsets!r}")
        require(isinstance(self.speeds, tuple) and len(self.speeds) > 0 and all(is_finite_number(s) and s > 0 for s in self.speeds),
                 f"{where}: `speeds` must be a non-empty list of speeds > 0 m/s; got {self.speeds!r}")
        require(is_finite_number(self.lateral_range) and self.lateral_range >= 0,
                 f"{where}: `lateral_range` must be a number >= 0 lanes; got {self.lateral_range!r}")
        low_high = self.speed_range
        require(isinstance(low_high, tuple) and len(low_high) == 2 and all(map(is_finite_number, low_high)) and 0 < low_high[0] <= low_high[1],
                 f"{where}: `speed_range` must be [low, high] with 0 < low <= high m/s; got {low_high!r}")
        require(isinstance(self.solver_features, bool), f"{where}: `solver_features` must be true or false; got {self.solver_features!r}")
        require_positive(where, feature_cost_scale=self.feature_cost_scale, intervention_speed_scale=self.intervention_speed_scale)
        require_non_negative(where, intervention_penalty=self.intervention_penalty)
        require(isinstance(self.kinematics_vehicles, int) and self.kinematics_vehicles >= 1,
                 f"{where}: `kinematics_vehicles` must be an int >= 1; got {self.kinematics_vehicles!r}")

    @property
    def num_discrete_goals(self) -> int:
        """A, the size of the discrete goal grid ``lane_offsets x speeds``."""
        return len(self.lane_offsets) * len(self.speeds)

    @property
    def top_speed(self) -> float:
        """Highest speed an action can ask for [m/s]."""
        return max(max(self.speeds), self.speed_range[1])


@dataclass(frozen=True)
class TrainConfig:
    """How ``mmpc train-rl`` trains and evaluates.

    Attributes:
        n_envs: environments per vectorized step (the safe layer solves all of them in one
            optimizer call per frame).
        log_every: environment steps (summed over environments) between two TensorBoard
            writes of the custom scalars.
        checkpoint_every: environment steps between two checkpoints.
        eval_episodes: evaluation episodes at the end of training.
        eval_seed: seed of the first evaluation episode; episode i uses ``eval_seed + i``.
        eval_envs: evaluation episodes run in lockstep (one batched solve per frame).
        torch_threads: torch CPU threads of the run.
    """

    n_envs: int = 4
    log_every: int = 500
    checkpoint_every: int = 5000
    eval_episodes: int = 50
    eval_seed: int = 100_000
    eval_envs: int = 10
    torch_threads: int = 1

    def __post_init__(self) -> None:
        for name in ("n_envs", "log_every", "checkpoint_every", "eval_episodes", "eval_envs", "torch_threads"):
            value = getattr(self, name)
            require(isinstance(value, int) and not isinstance(value, bool) and value >= 1,
                     f"train: `{name}` must be an int >= 1; got {value!r}")
        require(isinstance(self.eval_seed, int) and self.eval_seed >= 0, f"train: `eval_seed` must be an int >= 0; got {self.eval_seed!r}")


@dataclass(frozen=True)
class RLConfig:
    """One training setup: scenario, environment, reward, training and per-algorithm settings.

    Attributes:
        scenario: the driving scenario (default :func:`rl_scenario`).
        env: the safe layer's environment settings.
        reward: the reward, shared by the safe environments and the plain highway-env baseline.
        train: training and evaluation settings.
        algorithms: per algorithm (``dqn``, ``ppo``, ``sac``), keyword arguments of its
            stable-baselines3 constructor (e.g. ``learning_rate``, ``policy_kwargs``).
        action: ``discrete`` or ``continuous``; ``None``: the algorithm's default
            (:data:`ALGORITHMS`).
    """

    scenario: ScenarioConfig = field(default_factory=rl_scenario)
    env: SafeEnvConfig = field(default_factory=SafeEnvConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    algorithms: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    action: Optional[str] = None

    def __post_init__(self) -> None:
        require(isinstance(self.scenario, ScenarioConfig), f"rl config: `scenario` must be a ScenarioConfig; got {type(self.scenario).__name__}")
        unknown = sorted(set(self.algorithms) - set(ALGORITHMS))
        require(not unknown, f"rl config: unknown algorithm(s) {unknown} in `algorithms`; expected some of {sorted(ALGORITHMS)}")
        for name, kwargs in self.algorithms.items():
            require(isinstance(kwargs, Mapping), f"rl config: `algorithms.{name}` must be a mapping of keyword arguments; got {kwargs!r}")
        require(self.action in (None, "discrete", "continuous"),
                 f"rl config: `action` must be null, discrete or continuous; got {self.action!r}")
        require(
            self.scenario.optimizer.v_max >= self.env.top_speed,
            f"rl config: the scenario's `optimizer.v_max` ({self.scenario.optimizer.v_max} m/s) must be >= the "
            f"fastest goal an action can ask for ({self.env.top_speed} m/s)",
        )

    def action_for(self, algo: str) -> str:
        """The action space ``algo`` trains on; raises ``ValueError`` if it cannot."""
        require(algo in ALGORITHMS, f"unknown algorithm {algo!r}; expected one of {sorted(ALGORITHMS)}")
        action = self.action or ALGORITHMS[algo]
        require(action in SUPPORTED_ACTIONS[algo],
                 f"algorithm {algo!r} cannot train on {action} actions; it supports {list(SUPPORTED_ACTIONS[algo])}")
        return action

    def to_dict(self) -> dict:
        """Plain data (YAML-ready) that :meth:`from_dict` reads back; the scenario inline."""
        values = dataclasses.asdict(self)
        values["scenario"] = self.scenario.to_dict()
        values["algorithms"] = {name: dict(kwargs) for name, kwargs in self.algorithms.items()}
        return _plain(values)

    @classmethod
    def from_dict(cls, values: Mapping[str, Any], *, where: str = "rl config") -> "RLConfig":
        """Build from parsed YAML; unknown keys in any section raise ``ValueError``."""
        if not isinstance(values, Mapping):
            raise TypeError(f"{where} must be a mapping; got {type(values).__name__}")
        values = dict(values)
        if "scenario" in values:
            scenario = values["scenario"]
            if isinstance(scenario, (str, Path)):
                values["scenario"] = load_scenario(scenario)
            else:
                values["scenario"] = ScenarioConfig.from_dict(scenario, where=f"{where}: scenario")
        sections = {"env": SafeEnvConfig, "reward": RewardConfig, "train": TrainConfig}
        for name, section in sections.items():
            if name in values:
                items = {key: _as_tuple(value) for key, value in dict(values[name] or {}).items()}
                values[name] = dataclass_from_dict(section, items, where=f"{where}: {name}")
        if "algorithms" in values:
            values["algorithms"] = dict(values["algorithms"] or {})
        return dataclass_from_dict(cls, values, where=where)


def load_rl_config(path: Optional[str | Path] = None) -> RLConfig:
    """Read ``configs/rl/<name>.yaml`` (a path, or a name of a shipped file); ``None``: defaults.

    Raises:
        FileNotFoundError: no such file; the message lists the shipped configs.
        ValueError: an invalid or unknown key.
    """
    if path is None:
        return RLConfig()
    path, values = read_config_yaml(path, RL_CONFIG_DIR, "rl config", "configs")
    return RLConfig.from_dict(values, where=f"rl config {path}")


#: Folder of the RL configs that ship with the repository.
RL_CONFIG_DIR = shipped_config_dir("rl")


def _as_tuple(value: Any) -> Any:
    return tuple(value) if isinstance(value, list) else value


def _plain(value: Any) -> Any:
    """Tuples -> lists, recursively (for YAML)."""
    if isinstance(value, Mapping):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(item) for item in value]
    return value
