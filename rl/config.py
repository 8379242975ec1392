"""Settings of the safe action layer and of RL training runs, as frozen, validated dataclasses.

:class:`RLConfig` defaults are the documented training run (README, "Safe RL"); a YAML file
(``configs/rl/<name>.yaml`` or a path, :func:`mmpc.config.load_config`) changes some of them,
and every section rejects unknown keys::

    scenario: rl_highway_fast    # a scenario's name or path; or {from: NAME, duration: 2.0, ...}
    env: {decision_frames: 5, lane_offsets: [-1, 0, 1], speeds: [15, 20, 25, 28], ...}
    reward: {collision_reward: -1.0, right_lane_reward: 0.1, high_speed_reward: 0.4, ...}
    train: {n_envs: 8, log_every: 400, ...}
    algorithms: {dqn: {learning_rate: 5.0e-4, ...}, ppo: {...}, sac: {...}}

``mmpc config show rl`` prints the defaults. This module imports neither highway-env nor
stable-baselines3.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping, Optional

from mmpc.config import is_finite_number, require, require_int, require_non_negative, require_positive
from mmpc.scenario import ScenarioConfig, load_scenario
from mmpc.task_reward import HighwayReward
from mmpc.tracking import TrackingConfig

#: When the safety layer solves: at every simulation frame, or at the agent's decisions (tracking between).
REPLAN_MODES = ("frame", "decision")
#: Algorithms ``mmpc rl train`` knows, with the action space each trains on by default.
ALGORITHMS: dict[str, str] = {"dqn": "discrete", "ppo": "discrete", "sac": "continuous"}
#: Action spaces each algorithm supports (stable-baselines3: DQN discrete only, SAC Box only).
SUPPORTED_ACTIONS: dict[str, tuple[str, ...]] = {"dqn": ("discrete",), "ppo": ("discrete", "continuous"), "sac": ("continuous",)}


#: Settings a trained agent's observation and actions are made of (dotted keys of
#: :class:`RLConfig`): highway-env scales the ``Kinematics`` rows by the road's width
#: (``scenario.lanes``), ``env`` sets the observation's rows and solver features and the action
#: grid, and an action lasts ``decision_frames / frequency`` seconds. Evaluated with other values,
#: the agent would read inputs that mean something else (:func:`require_same_agent_inputs`).
AGENT_INPUTS = ("action", "scenario.lanes", "scenario.frequency", "env.decision_frames", "env.lane_offsets",
                "env.speeds", "env.lateral_range", "env.speed_range", "env.expert_action", "env.solver_features",
                "env.feature_cost_scale", "env.kinematics_vehicles", "env.meta_speeds")


def check_meta_speeds(speeds: Any, what: str = "meta-action target speeds") -> None:
    """Refuse (:class:`mmpc.config.ConfigError`) target speeds that are not >= 2 ascending, evenly
    spaced numbers [m/s] as a tuple: MDPVehicle steps through them by index."""
    listed = isinstance(speeds, tuple) and len(speeds) >= 2 and all(is_finite_number(v) for v in speeds)
    steps = [b - a for a, b in zip(speeds, speeds[1:])] if listed else [0.0]
    require(listed and min(steps) > 0 and max(steps) - min(steps) <= 1e-6 * max(steps),
            f"{what} must be >= 2 ascending, evenly spaced speeds [m/s] (MDPVehicle steps through them by index); "
            f"got {speeds!r}")


#: The scenario of the RL environments (``configs/scenarios/rl_highway_fast.yaml``): highway-env's
#: ``highway-fast-v0`` traffic, 30 s episodes at 10 Hz, the high-speed scenario's ellipse and band.
RL_SCENARIO = "rl_highway_fast"


def _recipe_algorithms() -> dict[str, dict[str, Any]]:
    """Per algorithm, the stable-baselines3 keyword arguments of the documented training run."""
    return {
        # highway-env's published DQN settings, except 2 gradient steps per vectorized step (8 transitions)
        "dqn": {"learning_rate": 5.0e-4, "buffer_size": 15000, "learning_starts": 200, "batch_size": 32, "gamma": 0.8,
                "train_freq": 1, "gradient_steps": 2, "target_update_interval": 50, "exploration_fraction": 0.7,
                "policy_kwargs": {"net_arch": [256, 256]}},
        # n_steps x n_envs = 1024 transitions per update
        "ppo": {"n_steps": 128, "batch_size": 64, "n_epochs": 10, "learning_rate": 5.0e-4, "gamma": 0.8,
                "policy_kwargs": {"net_arch": [256, 256]}},
        "sac": {"learning_rate": 5.0e-4, "buffer_size": 15000, "learning_starts": 200, "batch_size": 64, "gamma": 0.8,
                "policy_kwargs": {"net_arch": [256, 256]}},
    }


#: Where the RL environments take their reward from (:attr:`RewardConfig.source`).
REWARD_SOURCES = ("highway", "meta_cost")


@dataclass(frozen=True)
class RewardConfig:
    """The reward, computed at every simulation frame and summed over an agent step.

    ``source: highway`` is highway-env's (:class:`mmpc.task_reward.HighwayReward` with these terms).

    ``source: meta_cost`` is what the MPC expert ranks by: ``r = 1 - c / meta_cost_scale`` with
    ``c`` the scenario's meta cost term at the ego's state (``objective.stage_cost``, e.g. high
    speed ``w_speed (v - v_max)^2 + w_lane (y - y_right)^2``), ``collision_reward`` on a crashed
    frame, times 0 off the road. It is linear in ``c``, so a higher return is a lower mean meta
    cost over the same frames; with ``meta_cost_scale`` above the costs the layer drives into it
    stays positive, so ending an episode early never pays.

    Either way the safe environments subtract ``SafeEnvConfig.intervention_penalty`` for every
    frame the layer overrode the agent.

    Attributes:
        source: ``"highway"`` (highway-env's reward) or ``"meta_cost"`` (the scenario's meta cost).
        meta_cost_scale: ``source: meta_cost``: the meta cost term that earns 0 per frame [units of the meta cost].
        collision_reward: reward of a crashed frame (highway-env: -1).
        right_lane_reward: reward on the right lane (highway-env: 0.1).
        high_speed_reward: reward at or above ``reward_speed_range[1]`` (highway-env: 0.4).
        reward_speed_range: (low, high) forward speeds mapped onto [0, 1] [m/s] (highway-env: 20, 30).
        normalize: map the sum onto [0, 1] (highway-env: true).
    """

    source: str = "highway"
    meta_cost_scale: float = 100.0
    collision_reward: float = -1.0
    right_lane_reward: float = 0.1
    high_speed_reward: float = 0.4
    reward_speed_range: tuple[float, float] = (20.0, 30.0)
    normalize: bool = True

    def __post_init__(self) -> None:
        require(self.source in REWARD_SOURCES, f"reward: `source` must be one of {list(REWARD_SOURCES)}; got {self.source!r}")
        require_positive("reward", meta_cost_scale=self.meta_cost_scale)
        for name in ("collision_reward", "right_lane_reward", "high_speed_reward"):
            require(is_finite_number(getattr(self, name)), f"reward: `{name}` must be a finite number; got {getattr(self, name)!r}")
        low_high = self.reward_speed_range
        require(isinstance(low_high, tuple) and len(low_high) == 2 and all(map(is_finite_number, low_high)) and low_high[0] < low_high[1],
                 f"reward: `reward_speed_range` must be [low, high] m/s with low < high; got {low_high!r}")
        require(isinstance(self.normalize, bool), f"reward: `normalize` must be true or false; got {self.normalize!r}")
        require(not self.normalize or self.collision_reward < self.high_speed_reward + self.right_lane_reward,
                 "reward: with `normalize`, `collision_reward` must be below high_speed_reward + right_lane_reward")

    def meta_cost_reward(self, cost: Any, crashed: Any, on_road: Any) -> Any:
        """``source: meta_cost``'s reward of states with meta cost terms ``cost``: floats, or tensors
        of one shape with ``crashed`` and ``on_road`` as 0/1 of the same dtype."""
        return (self.collision_reward * crashed + (1 - crashed) * (1 - cost / self.meta_cost_scale)) * on_road

    def highway_terms(self) -> HighwayReward:
        """``source: highway``'s reward terms (:class:`mmpc.task_reward.HighwayReward`)."""
        return HighwayReward(self.collision_reward, self.right_lane_reward, self.high_speed_reward, self.reward_speed_range,
                             self.normalize)

    def highway_env_config(self) -> dict:
        """highway-env's reward (``source: highway``) as highway-env configuration keys."""
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
        decision_frames: k, simulation frames per agent step (the goal is held).
        replan: ``"frame"``: the optimizer replans at every frame of the agent step;
            ``"decision"``: at the agent's decision only, and the plan is tracked over the other
            frames (``tracking``), solved again where it would run into an obstacle as predicted
            now or the ego has left it (:meth:`mmpc.rl.safety.SafetyLayer.frame`).
        tracking: how ``replan: decision`` tracks the plan and when it gives it up.
        lane_offsets: discrete actions: target lanes relative to the ego's lane at decision time
            (clamped to the road).
        speeds: discrete actions: target average speeds [m/s]; actions are
            ``lane_offsets x speeds``, offset-major.
        lateral_range: continuous actions: ``a[0]`` in [-1, 1] maps to the ego lane's centre
            plus ``a[0] * lateral_range`` lane widths (clamped to the lane centres of the road).
        speed_range: continuous actions: ``a[1]`` in [-1, 1] maps linearly onto (low, high) [m/s].
        expert_action: discrete actions: one more action after the grid, "drive what the MPC
            expert would": its own choice among every candidate of the decision solve (the grid
            and the scenario's standard goals), held over the agent step like a grid goal. The
            agent can then do no worse than the expert at the decision rate and learns when to
            deviate from it. Needs ``replan: decision``.
        solver_features: append per-goal solver features to the observation: for every action
            of the discrete grid (and the expert action) at the current state, feasible flag, meta cost
            ``m / (m + feature_cost_scale)`` (``m`` the cost per trajectory sample) and clearance
            ``min(1, d / 3)`` (``d`` the smallest normalised ellipse distance).
        feature_cost_scale: see ``solver_features`` [units of the meta cost].
        intervention_penalty: subtracted from the reward for every frame on which the agent's
            goal was not feasible (the layer drove another candidate or braked).
        intervention_speed_scale: a feasible candidate's distance to the agent's goal is
            ``hypot(dv / intervention_speed_scale, dy / lane_width)``: a lane weighs like this
            speed difference [m/s].
        kinematics_vehicles: rows of highway-env's ``Kinematics`` observation (ego first).
        meta_speeds: the plain agents' (``--env plain`` and ``highway``) target speeds, highway-env's
            ``DiscreteMetaAction`` ``target_speeds``: ascending and evenly spaced [m/s]
            (highway-env's default 20, 25, 30; a set that reaches the traffic's speeds lets a
            plain agent follow it).
        verify: every frame's command is taken only if it keeps a verified way out
            (:class:`mmpc.verify.Guard`: else braking, the plan's other feasible candidates, a
            fail-safe); an override counts as an intervention. On by default, in both worlds:
            whatever the agent asks, no collision while the traffic keeps
            :class:`mmpc.verify.TrafficAssumptions`. ``false`` is the layer alone (the MPC's
            feasible candidates, no way-out check); runs recorded before the setting existed
            are read so (:func:`mmpc.rl.runs.recorded_config`).
    """

    decision_frames: int = 5
    replan: str = "frame"
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    lane_offsets: tuple[int, ...] = (-1, 0, 1)
    speeds: tuple[float, ...] = (15.0, 20.0, 25.0, 28.0)
    lateral_range: float = 1.0
    speed_range: tuple[float, float] = (10.0, 28.0)
    expert_action: bool = False
    solver_features: bool = True
    feature_cost_scale: float = 25.0
    intervention_penalty: float = 0.1
    intervention_speed_scale: float = 5.0
    kinematics_vehicles: int = 5
    meta_speeds: tuple[float, ...] = (20.0, 25.0, 30.0)
    verify: bool = True

    def __post_init__(self) -> None:
        where = "env"
        require_int(where, low=1, decision_frames=self.decision_frames)
        require(self.replan in REPLAN_MODES, f"{where}: `replan` must be one of {list(REPLAN_MODES)}; got {self.replan!r}")
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
        require(isinstance(self.expert_action, bool), f"{where}: `expert_action` must be true or false; got {self.expert_action!r}")
        require(not self.expert_action or self.replan == "decision",
                 f"{where}: `expert_action` needs `replan: decision` (the expert's choice comes from the decision's solve); "
                 f"got replan {self.replan!r}")
        require(isinstance(self.solver_features, bool), f"{where}: `solver_features` must be true or false; got {self.solver_features!r}")
        require_positive(where, feature_cost_scale=self.feature_cost_scale, intervention_speed_scale=self.intervention_speed_scale)
        require_non_negative(where, intervention_penalty=self.intervention_penalty)
        require_int(where, low=1, kinematics_vehicles=self.kinematics_vehicles)
        check_meta_speeds(self.meta_speeds, f"{where}: `meta_speeds`")
        require(isinstance(self.verify, bool), f"{where}: `verify` must be true or false; got {self.verify!r}")

    @property
    def num_discrete_goals(self) -> int:
        """A, the size of the discrete goal grid ``lane_offsets x speeds``."""
        return len(self.lane_offsets) * len(self.speeds)

    @property
    def num_actions(self) -> int:
        """Discrete actions: the grid's A goals, then the expert action when ``expert_action``."""
        return self.num_discrete_goals + int(self.expert_action)

    @property
    def top_speed(self) -> float:
        """Highest speed an action can ask for [m/s]."""
        return max(max(self.speeds), self.speed_range[1])


@dataclass(frozen=True)
class TrainConfig:
    """How ``mmpc rl train`` trains and evaluates.

    Attributes:
        n_envs: environments per vectorized step (the safe layer solves all of them in one
            optimizer call per frame).
        log_every: environment steps (summed over environments) between two TensorBoard
            writes of the custom scalars.
        checkpoint_every: environment steps between two checkpoints.
        eval_episodes: evaluation episodes at the end of training.
        eval_seed: seed of the first evaluation episode; episode i uses ``eval_seed + i`` (the
            same seeds for the safe and the plain agents).
        eval_envs: evaluation episodes run in lockstep (one batched solve per frame).
        torch_threads: torch CPU threads of the run.
        expert_prior: with ``env.expert_action`` and PPO: the probability the untrained policy
            gives the expert action (the rest shared evenly), so that training starts from the
            expert and learns where to deviate; 0 keeps stable-baselines3's initialisation. DQN
            and SAC ignore it (as they ignore ``algorithms.ppo``), and so do the plain baselines
            (``--env plain``, ``--env highway``), which have no expert action.
    """

    n_envs: int = 8
    log_every: int = 400
    checkpoint_every: int = 2000
    eval_episodes: int = 50
    eval_seed: int = 100_000
    eval_envs: int = 10
    torch_threads: int = 1
    expert_prior: float = 0.0

    def __post_init__(self) -> None:
        require_int("train", low=1, n_envs=self.n_envs, log_every=self.log_every, checkpoint_every=self.checkpoint_every,
                    eval_episodes=self.eval_episodes, eval_envs=self.eval_envs, torch_threads=self.torch_threads)
        require(is_finite_number(self.expert_prior) and 0.0 <= self.expert_prior < 1.0,
                 f"train: `expert_prior` must be a probability in [0, 1); got {self.expert_prior!r}")
        require_int("train", low=0, eval_seed=self.eval_seed)


@dataclass(frozen=True)
class RLConfig:
    """One training setup: scenario, environment, reward, training and per-algorithm settings.
    The defaults are the documented training run: DQN picks goals (lane offset x target speed)
    every 0.5 s and the batch optimizer plans towards them at 10 Hz among highway-env's own
    highway-fast traffic; the same settings train the unprotected baselines with highway-env's
    DiscreteMetaAction: on the same world without the layer (``mmpc rl train --env plain``:
    same traffic, car, episode length, reward, observation and decision rate) or on plain
    highway-env (``--env highway``: highway-env's own traffic and MDPVehicle).

    Attributes:
        scenario: the driving scenario (default :data:`RL_SCENARIO`, the shipped file). In YAML
            its name or path, or ``{from: NAME_OR_PATH, key: value, ...}`` to change some of
            its settings, or a whole scenario inline (as trained runs record it).
        env: the safe layer's environment settings.
        reward: the reward, shared by the safe environments and the plain highway-env baseline.
        train: training and evaluation settings.
        algorithms: per algorithm (``dqn``, ``ppo``, ``sac``), keyword arguments of its
            stable-baselines3 constructor (e.g. ``learning_rate``, ``policy_kwargs``).
        action: ``discrete`` or ``continuous``; ``None``: the algorithm's default
            (:data:`ALGORITHMS`).
    """

    config_folder: ClassVar[str] = "rl"
    scenario: ScenarioConfig = field(default_factory=lambda: load_scenario(RL_SCENARIO))
    env: SafeEnvConfig = field(default_factory=SafeEnvConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    algorithms: Mapping[str, Mapping[str, Any]] = field(default_factory=_recipe_algorithms)
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


def require_same_agent_inputs(trained: RLConfig, requested: RLConfig) -> None:
    """Raise :class:`mmpc.config.ConfigError` where ``requested`` (e.g. a trained run's config with
    ``--set`` overrides) changes a setting of :data:`AGENT_INPUTS` from ``trained``, the message
    naming the key, the trained value and the requested one."""
    for dotted in AGENT_INPUTS:
        before, after = (functools.reduce(getattr, dotted.split("."), config) for config in (trained, requested))
        require(before == after, f"`{dotted}` must stay {before!r}, the value the agent was trained with; got {after!r} "
                                 "(the agent's observation or actions are made of it; other settings, such as the "
                                 "traffic, the duration or the reward, may change)")
