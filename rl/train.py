"""Train stable-baselines3 agents on the safe environments (or on plain highway-env, the
unprotected baseline) and evaluate them on fixed seeds.

A run directory holds::

    config.yaml          the resolved configuration (algorithm, environment, action space, seed, budget)
    scenario.yaml        its scenario alone, for ``mmpc drive --scenario DIR/scenario.yaml --driver sb3:DIR/model.zip``
    tb/<algo>_1/         TensorBoard event files: SB3's scalars plus solver/, safety/, driving/
    checkpoints/         <algo>_<steps>_steps.zip every ``train.checkpoint_every`` steps
    model.zip            the final model
    eval.json            the evaluation: collision_rate, mean_speed, mean_return,
                         intervention_rate, episodes, and one row per episode
    .train.lock          held by the run while it writes (:data:`RUN_LOCK`)

A run gets a folder of its own: :func:`train` refuses a folder another run is writing to, and
one holding anything (an earlier run's files would be replaced or mixed with the new run's).
"""

from __future__ import annotations

import contextlib
import inspect
import json
import logging
import math
import time
from pathlib import Path
from typing import Any, Callable, Iterator, NamedTuple, Optional, Sequence

import gymnasium as gym
import numpy as np
import torch
import yaml

from mmpc.config import require_int, to_dict
from mmpc.files import OutputFolderError, exclusive
from mmpc.highway.runner import Observer, Step
from mmpc.rl.config import ALGORITHMS, RLConfig
from mmpc.rl.envs import frame_reward, vehicle_meta_cost_reward
from mmpc.rl.runs import ALGORITHM_CLASSES, TrainedRun, algorithm_class

logger = logging.getLogger(__name__)

#: Environments ``train`` can train on: the safe layer or plain highway-env.
ENV_KINDS = ("safe", "highway")
#: The lock file a training run holds in its folder (:func:`mmpc.files.exclusive`).
RUN_LOCK = ".train.lock"


# ----------------------------------------------------------------------------------- plain baseline


class HighwayBaseline(gym.Wrapper):
    """Plain highway-env set up like a scenario: same road, traffic density, episode length,
    reward and observation as the safe environments, and highway-env's own action at
    ``frequency / decision_frames`` Hz (the agent's decision rate in the safe environments).

    Differences that remain: highway-env's traffic without :mod:`mmpc.highway.traffic`'s initial
    clearance; the reward is computed once per agent step, at its last frame (the safe
    environments sum it over the step's frames): highway-env's, or with ``source: meta_cost`` the
    step's frames times the meta cost reward of the state it ends in.

    ``info`` adds ``mean_speed`` (the ego's speed at the end of the step) [m/s] and ``frames``.
    """

    def __init__(self, config: RLConfig, *, continuous: bool) -> None:
        from mmpc.highway import env_config

        scenario = config.scenario
        frames = config.env.decision_frames
        values = env_config(scenario)
        values.update(config.reward.highway_env_config())
        values["observation"] = {"type": "Kinematics", "vehicles_count": config.env.kinematics_vehicles}
        values["policy_frequency"] = scenario.frequency / frames
        if not continuous:
            values["action"] = {"type": "DiscreteMetaAction"}
        super().__init__(gym.make(scenario.env_id, config=values))
        self.ego_speed = scenario.ego.speed
        self.frames = frames
        self.scenario = scenario
        self.reward = config.reward

    def reset(self, **kwargs: Any) -> tuple[Any, dict]:
        observation, info = self.env.reset(**kwargs)
        ego = self.env.unwrapped.vehicle
        ego.speed = self.ego_speed
        return self.env.unwrapped.observation_type.observe(), info

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict]:
        observation, reward, terminated, truncated, info = self.env.step(action)
        ego = self.env.unwrapped.vehicle
        info = dict(info, mean_speed=float(info.get("speed", ego.speed)), frames=self.frames)
        info["crashed"] = bool(ego.crashed)
        if self.reward.source == "meta_cost":
            reward = self.frames * vehicle_meta_cost_reward(ego, self.scenario, self.reward)
        return observation, reward, terminated, truncated, info


def make_highway_env(config: RLConfig, *, continuous: bool = False) -> gym.Env:
    """The unprotected baseline environment (flattened ``Kinematics`` observation)."""
    return gym.wrappers.FlattenObservation(HighwayBaseline(config, continuous=continuous))


# ----------------------------------------------------------------------------------- evaluation


class EpisodeRow(NamedTuple):
    """One evaluation episode."""

    seed: int
    crashed: bool
    episode_return: float
    mean_speed: float
    steps: int
    frames: int
    intervention_frames: int


def summarize(rows: Sequence[EpisodeRow], *, safe: bool) -> dict:
    """``collision_rate``, ``mean_speed`` (mean of the episodes' frame-averaged speeds) [m/s],
    ``mean_return``, ``intervention_rate`` (share of frames; ``None`` without a safety layer),
    ``episodes``, and the rows."""
    frames = sum(r.frames for r in rows)
    return {
        "episodes": len(rows),
        "collision_rate": float(np.mean([r.crashed for r in rows])),
        "mean_speed": float(np.mean([r.mean_speed for r in rows])),
        "mean_return": float(np.mean([r.episode_return for r in rows])),
        "intervention_rate": (sum(r.intervention_frames for r in rows) / frames) if safe and frames else None,
        "seeds": [r.seed for r in rows],
        "per_episode": [r._asdict() for r in rows],
    }


def evaluate(
    policy: Callable[[np.ndarray], np.ndarray],
    config: RLConfig,
    *,
    env_kind: str,
    continuous: bool,
    seeds: Sequence[int],
    lockstep: int = 10,
    on_episode: Optional[Callable[[EpisodeRow], None]] = None,
) -> dict:
    """Run one episode per seed with a policy and summarize them (:func:`summarize`), in
    highway-env, the reference world, whichever world the agent trained in (``scenario.sim``).
    A safe agent drives through mmpc's one episode loop (:func:`mmpc.highway.runner.run_lockstep`)
    as :class:`mmpc.rl.driver.SafeAgentDriver`, its reward and speed counted after every frame
    as in training; a plain agent drives highway-env's own environment with its own actions.

    Args:
        policy: ``observations (B, obs) -> actions (B, ...)`` (e.g. a model's deterministic
            ``predict``).
        config: the run's configuration.
        env_kind: ``safe`` or ``highway``.
        continuous: Box actions.
        seeds: one episode per seed.
        lockstep: safe environments: episodes run together, one batched solve per frame (on the
            run's device, :func:`mmpc.device.run_device`), in groups ``seed // lockstep``
            (mmpc's one grouping rule).
        on_episode: called with every finished episode.
    """
    if env_kind not in ENV_KINDS:
        raise ValueError(f"`env_kind` must be one of {ENV_KINDS}; got {env_kind!r}")
    seeds = [int(s) for s in seeds]
    if not seeds:
        raise ValueError("`seeds` must not be empty")
    rows: list[EpisodeRow] = []
    if env_kind == "safe":
        from mmpc.evaluate.tasks import lockstep_groups
        from mmpc.highway.runner import run_lockstep
        from mmpc.rl.driver import SafeAgentDriver

        scenario = config.scenario.replace(sim="highway-env")
        driver = SafeAgentDriver(TrainedRun(_PolicyModel(policy), "policy", "safe", continuous, config), scenario)
        tally = _FrameTally(config)
        for chunk in lockstep_groups(seeds, lockstep).values():
            for index, (seed, result) in enumerate(zip(chunk, run_lockstep(scenario, chunk, driver=driver, observers=[tally]))):
                frames = len(result.records)
                intervened = driver.intervention_frames[index]
                rows.append(EpisodeRow(seed, bool(result.metrics["collisions"]),
                                       tally.rewards[index] - config.env.intervention_penalty * intervened,
                                       tally.speeds[index] / frames, math.ceil(frames / config.env.decision_frames), frames,
                                       intervened))
                if on_episode is not None:
                    on_episode(rows[-1])
    else:
        env = make_highway_env(config, continuous=continuous)
        try:
            for seed in seeds:
                observation, _ = env.reset(seed=seed)
                stats = _EpisodeStats(seed)
                done = False
                while not done:
                    action = policy(observation[None])[0]
                    observation, reward, terminated, truncated, info = env.step(action)
                    stats.add(float(reward), info)
                    done = terminated or truncated
                rows.append(stats.row())
                if on_episode is not None:
                    on_episode(rows[-1])
        finally:
            env.close()
    rows.sort(key=lambda r: seeds.index(r.seed))
    return summarize(rows, safe=env_kind == "safe")


class _PolicyModel:
    """A policy ``observations -> actions`` as the ``predict`` of a stable-baselines3 model."""

    def __init__(self, policy: Callable[[np.ndarray], np.ndarray]) -> None:
        self.policy = policy

    def predict(self, observations: np.ndarray, deterministic: bool = True) -> tuple[np.ndarray, None]:
        return self.policy(observations), None


class _FrameTally(Observer):
    """Sums, per environment, the RL reward (:func:`mmpc.rl.envs.frame_reward`) and the ego's
    speed after every frame, as the safe environments count them."""

    def __init__(self, config: RLConfig) -> None:
        self.reward = config.reward
        self.rewards: list[float] = []
        self.speeds: list[float] = []

    def start(self, episodes: Sequence[Any]) -> None:
        self.rewards = [0.0] * len(episodes)
        self.speeds = [0.0] * len(episodes)

    def applied(self, step: Step) -> None:
        self.rewards[step.index] += frame_reward(step.episode, self.reward)
        self.speeds[step.index] += float(step.episode.ego.speed)


class _EpisodeStats:
    def __init__(self, seed: int) -> None:
        self.seed = seed
        self.total = 0.0
        self.steps = 0
        self.frames = 0
        self.speed_sum = 0.0
        self.intervened = 0
        self.crashed = False

    def add(self, reward: float, info: dict) -> None:
        frames = int(info.get("frames", 1))
        self.total += reward
        self.steps += 1
        self.frames += frames
        self.speed_sum += float(info["mean_speed"]) * frames
        self.intervened += int(info.get("intervention_frames", 0))
        self.crashed = self.crashed or bool(info.get("crashed", False))

    def row(self) -> EpisodeRow:
        return EpisodeRow(self.seed, self.crashed, self.total, self.speed_sum / max(self.frames, 1), self.steps,
                          self.frames, self.intervened)


# ----------------------------------------------------------------------------------- training


def make_training_env(config: RLConfig, *, env_kind: str, continuous: bool, seed: int):
    """The vectorized training environment (``train.n_envs`` environments, monitored): the safe
    environments on the scenario's world (``scenario.sim``), or plain highway-env."""
    from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor

    n_envs = config.train.n_envs
    if env_kind == "safe" and config.scenario.sim == "batched":
        from mmpc.rl.sim_vec_env import SafeSimVecEnv

        venv = SafeSimVecEnv(n_envs, config.scenario, config.env, config.reward, continuous=continuous, seed=seed)
    elif env_kind == "safe":
        from mmpc.rl.vec_env import SafeHighwayVecEnv

        venv = SafeHighwayVecEnv(n_envs, config.scenario, config.env, config.reward, continuous=continuous)
    elif env_kind == "highway":
        venv = DummyVecEnv([lambda: make_highway_env(config, continuous=continuous) for _ in range(n_envs)])
    else:
        raise ValueError(f"`env_kind` must be one of {ENV_KINDS}; got {env_kind!r}")
    venv.seed(seed)
    return VecMonitor(venv)


def algorithm_kwargs(config: RLConfig, algo: str) -> dict:
    """The run's constructor arguments of ``algo``; unknown names raise ``ValueError``."""
    kwargs = dict(config.algorithms.get(algo, {}))
    allowed = set(inspect.signature(algorithm_class(algo).__init__).parameters) - {"self", "policy", "env"}
    unknown = sorted(set(kwargs) - allowed)
    if unknown:
        raise ValueError(f"unknown argument(s) {unknown} in `algorithms.{algo}`; {ALGORITHM_CLASSES[algo]} accepts {sorted(allowed)}")
    return kwargs


def prefer_expert_action(model: Any, prior: float) -> None:
    """Make an untrained PPO policy over discrete actions give its last action (the expert's)
    probability ``prior`` and the others ``(1 - prior) / (n - 1)`` each: the action logits' bias.
    stable-baselines3 initialises the action head with weights of gain 0.01, so the bias decides."""
    head = model.policy.action_net
    count = head.out_features
    with torch.no_grad():
        head.bias.zero_()
        head.bias[count - 1] = math.log(prior * (count - 1) / (1.0 - prior))


def train(
    config: RLConfig,
    algo: str,
    timesteps: int,
    out: Path,
    *,
    env_kind: str = "safe",
    seed: int = 0,
    progress_bar: bool = False,
    evaluate_after: bool = True,
) -> dict:
    """Train ``algo`` for ``timesteps`` environment steps, save it, evaluate it.

    Args:
        config: the run's configuration.
        algo: ``dqn``, ``ppo`` or ``sac``.
        timesteps: environment (agent) steps, summed over the vectorized environments.
        out: the run directory: new, empty or missing (created; see the module docstring).
        env_kind: ``safe`` (the goal-choosing environments) or ``highway`` (plain highway-env).
        seed: seeds the model and the training environments.
        progress_bar: SB3's progress bar.
        evaluate_after: run the evaluation (``train.eval_episodes`` episodes) and write eval.json.

    Returns:
        The evaluation summary (``{}`` without evaluation).

    Raises:
        mmpc.files.OutputFolderError: ``out`` is held by another run or holds files (:func:`run_folder`).
    """
    from stable_baselines3.common.callbacks import CallbackList, CheckpointCallback

    from mmpc.rl.callbacks import SafetyTensorboardCallback

    if algo not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {algo!r}; expected one of {sorted(ALGORITHMS)}")
    if env_kind not in ENV_KINDS:
        raise ValueError(f"`env_kind` must be one of {ENV_KINDS}; got {env_kind!r}")
    require_int("", low=1, timesteps=timesteps)
    continuous = config.action_for(algo) == "continuous"
    # Other algorithms ignore the prior (as algorithms.ppo), and so does the plain baseline of a recipe:
    # highway-env's own actions hold no expert to start at.
    expert_prior = config.train.expert_prior if algo == "ppo" and env_kind == "safe" else 0.0
    if expert_prior > 0 and (continuous or not config.env.expert_action):
        raise ValueError(f"train: `expert_prior` sets PPO's discrete policy towards the expert action, so it needs "
                         f"discrete actions and env.expert_action: true; got {'continuous' if continuous else 'discrete'} "
                         f"actions, expert_action {config.env.expert_action}")
    kwargs = algorithm_kwargs(config, algo)
    torch.set_num_threads(config.train.torch_threads)
    out = Path(out)
    with run_folder(out):
        run = {"algo": algo, "env": env_kind, "action": "continuous" if continuous else "discrete",
               "timesteps": timesteps, "seed": seed, "config": to_dict(config)}
        (out / "config.yaml").write_text(yaml.safe_dump(run, sort_keys=False))
        # the scenario alone, for `mmpc drive --scenario DIR/scenario.yaml --driver sb3:DIR/model.zip`
        (out / "scenario.yaml").write_text(yaml.safe_dump(run["config"]["scenario"], sort_keys=False))
        env = make_training_env(config, env_kind=env_kind, continuous=continuous, seed=seed)
        # the policy stays on the CPU and reads numpy whatever --device says (that is the MPC's and the simulator's)
        kwargs.setdefault("device", "cpu")
        model = algorithm_class(algo)("MlpPolicy", env, seed=seed, verbose=0, tensorboard_log=str(out / "tb"), **kwargs)
        if expert_prior > 0:
            prefer_expert_action(model, expert_prior)
        checkpoints = CheckpointCallback(max(config.train.checkpoint_every // config.train.n_envs, 1),
                                         str(out / "checkpoints"), name_prefix=algo)
        start = time.perf_counter()
        try:
            model.learn(timesteps, callback=CallbackList([checkpoints, SafetyTensorboardCallback(config.train.log_every)]),
                        tb_log_name=algo, progress_bar=progress_bar)
        finally:
            env.close()
        train_s = time.perf_counter() - start
        model.save(out / "model.zip")
        logger.info("trained %s on %s for %d steps in %.0f s", algo, env_kind, timesteps, train_s)
        if not evaluate_after:
            return {}
        summary = evaluate_run(model, config, env_kind=env_kind, continuous=continuous)
        summary = {"algo": algo, "env": env_kind, "timesteps": timesteps, "train_seconds": train_s, **summary}
        (out / "eval.json").write_text(json.dumps(summary, indent=2) + "\n")
        return summary


@contextlib.contextmanager
def run_folder(out: Path) -> Iterator[None]:
    """Hold the run folder ``out`` (created when missing) while the block writes it: its
    :data:`RUN_LOCK` keeps a second run out, and a folder holding anything else is refused, since
    the run would replace or mix with what is there (``mmpc rl train`` does not resume).

    Raises:
        mmpc.files.OutputFolderError: another run holds ``out``, or ``out`` holds files.
    """
    out.mkdir(parents=True, exist_ok=True)
    if not (out / RUN_LOCK).exists():
        _require_empty(out)  # before the lock file goes in: a refused folder is left as it was
    with exclusive(out, RUN_LOCK, "another `mmpc rl train` run", OutputFolderError):
        _require_empty(out)
        yield


def _require_empty(out: Path) -> None:
    names = sorted(p.name for p in out.iterdir() if p.name != RUN_LOCK)
    if names:
        raise OutputFolderError(f"`out` {out} already holds {_held_run(out)}: {', '.join(names)}; a training run "
                                "neither resumes nor overwrites one: choose another --out (or remove that folder)")


def _held_run(out: Path) -> str:
    """What an occupied run folder holds, as words (the run its config.yaml records, or files)."""
    try:
        run = yaml.safe_load((out / "config.yaml").read_text())
        described = f"{run['algo']} on {run['env']}, seed {run['seed']}"
    except (OSError, yaml.YAMLError, TypeError, KeyError):
        return "files"
    return f"a {'finished' if (out / 'model.zip').is_file() else 'unfinished'} run ({described})"


def evaluate_run(model: Any, config: RLConfig, *, env_kind: str, continuous: bool,
                 on_episode: Optional[Callable[[EpisodeRow], None]] = None) -> dict:
    """Evaluate a model on the config's fixed seeds (``train.eval_seed`` + 0 .. eval_episodes - 1)."""
    seeds = range(config.train.eval_seed, config.train.eval_seed + config.train.eval_episodes)

    def policy(observations: np.ndarray) -> np.ndarray:
        actions, _ = model.predict(observations, deterministic=True)
        return actions

    return evaluate(policy, config, env_kind=env_kind, continuous=continuous, seeds=seeds,
                    lockstep=config.train.eval_envs, on_episode=on_episode)
