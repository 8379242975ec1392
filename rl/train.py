"""Train stable-baselines3 agents on the safe environments (or, unprotected baselines, on the plain
environments or plain highway-env) and evaluate them on fixed seeds.

A run directory holds::

    config.yaml          the resolved configuration (algorithm, environment, action space, seed, budget;
                         after training, ``trained_timesteps``: the steps trained, the budget rounded
                         up to whole rollouts)
    scenario.yaml        its scenario alone, for ``mmpc drive --scenario DIR/scenario.yaml --driver sb3:DIR/model.zip``
    tb/<algo>_1/         TensorBoard event files: SB3's scalars plus solver/, safety/, driving/
    checkpoints/         <algo>_<steps>_steps.zip every ``train.checkpoint_every`` steps and at the end (and
                         an off-policy algorithm's latest replay buffer): ``--resume`` goes on from the latest
    model.zip            the final model
    crashes.csv          the training episodes that ended in a collision (:class:`mmpc.rl.callbacks.CrashLog`):
                         their seed, step and actions replay them
    eval.json            the evaluation: collision_rate, mean_speed, mean_return,
                         intervention_rate, episodes, and one row per episode
    .train.lock          held by the run while it writes, removed at its end (:data:`RUN_LOCK`)

A run gets a folder of its own: :func:`train` refuses a folder another run is writing to, and
one holding anything (an earlier run's files would be replaced or mixed with the new run's),
unless it resumes the run there (``resume``: same settings, from its latest checkpoint). It builds its environments and its model before it writes anything there, so a start refused
for its settings leaves the folder empty for the corrected command.
"""

from __future__ import annotations

import inspect
import json
import logging
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, NamedTuple, Optional, Sequence

import gymnasium as gym
import numpy as np
import torch
import yaml

from mmpc.config import ConfigError, is_finite_number, require, require_int, to_dict
from mmpc.files import atomic_write_text
from mmpc.highway.runner import Observer, Step
from mmpc.rl.config import ALGORITHMS, RLConfig
from mmpc.rl.reward import frame_reward, vehicle_reward
from mmpc.rl.folders import run_folder
from mmpc.rl.runs import ALGORITHM_CLASSES, TrainedRun, algorithm_class, run_record

if TYPE_CHECKING:
    from mmpc.rl.checkpoints import Checkpoint

logger = logging.getLogger(__name__)

#: Environments ``train`` can train on: the safe layer, the plain environments (the scenario's world,
#: no layer, highway-env's meta-actions) or plain highway-env.
ENV_KINDS = ("safe", "plain", "highway")
#: The lock file a training run holds in its folder (:func:`mmpc.rl.folders.run_folder`).
RUN_LOCK = ".train.lock"
#: Seeds numpy (and so stable-baselines3 and highway-env) accepts: [0, 2^32 - 1].
MAX_SEED = 2**32 - 1


# ----------------------------------------------------------------------------------- plain baseline


class HighwayBaseline(gym.Wrapper):
    """Plain highway-env set up like a scenario: same road, traffic density, episode length,
    reward and observation as the safe environments, and highway-env's own action at
    ``frequency / decision_frames`` Hz (the agent's decision rate in the safe environments).

    Differences that remain: highway-env's traffic (not re-spawned around the ego: an ego faster
    than the traffic drives on an empty road once it passed it) without
    :mod:`mmpc.highway.traffic`'s initial clearance; MDPVehicle's unbounded acceleration and
    +-60 deg steering; the reward is computed once per agent step, at its last frame (the safe
    environments sum it over the step's frames): highway-env's, or with ``source: meta_cost`` the
    step's frames times the meta cost reward of the state it ends in. The plain environments
    (:class:`mmpc.rl.plain.PlainEnvs`, ``--env plain``) have none of these differences.

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
            values["action"] = {"type": "DiscreteMetaAction", "target_speeds": list(config.env.meta_speeds)}
        super().__init__(gym.make(scenario.env_id, config=values))
        self.continuous = continuous
        self.ego_speed = scenario.ego.speed
        self.frames = frames
        self.scenario = scenario
        self.reward = config.reward

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None) -> tuple[Any, dict]:
        """Start an episode; ``seed`` (or one drawn from the environment's generator) seeds
        highway-env, so a seed fixes the episode: ``info["episode_seed"]`` says which."""
        if seed is None:
            seed = int(self.np_random.integers(2**31 - 1))
        observation, info = self.env.reset(seed=seed, options=options)
        ego = self.env.unwrapped.vehicle
        ego.speed = self.ego_speed
        if not self.continuous:  # an MDPVehicle: its targets as if created at that speed (mmpc.rl.meta_actions.MetaActions.start)
            ego.speed_index = ego.speed_to_index(ego.speed)
            ego.target_speed = ego.index_to_speed(ego.speed_index)
        return self.env.unwrapped.observation_type.observe(), dict(info, episode_seed=seed)

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict]:
        observation, reward, terminated, truncated, info = self.env.step(action)
        ego = self.env.unwrapped.vehicle
        info = dict(info, mean_speed=float(info.get("speed", ego.speed)), frames=self.frames)
        info["crashed"] = bool(ego.crashed)
        if self.reward.source == "meta_cost":
            reward = self.frames * vehicle_reward(ego, self.scenario, self.reward)
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
    as :class:`mmpc.rl.driver.SafeAgentDriver`, a plain-environment agent as
    :class:`mmpc.rl.driver.MetaActionDriver`, their reward and speed counted after every frame as
    in training; a plain highway-env agent drives highway-env's own environment with its own actions.

    Args:
        policy: ``observations (B, obs) -> actions (B, ...)`` (e.g. a model's deterministic
            ``predict``).
        config: the run's configuration.
        env_kind: ``safe``, ``plain`` or ``highway``.
        continuous: Box actions.
        seeds: one episode per seed.
        lockstep: safe and plain environments: episodes run together, one batched solve per frame (on the
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
    if env_kind in ("safe", "plain"):
        from mmpc.evaluate.tasks import lockstep_groups
        from mmpc.highway.runner import run_lockstep
        from mmpc.rl.driver import MetaActionDriver, SafeAgentDriver

        scenario = config.scenario.replace(sim="highway-env")
        run = TrainedRun(_PolicyModel(policy), "policy", env_kind, continuous, config)
        driver = SafeAgentDriver(run, scenario) if env_kind == "safe" else MetaActionDriver(run, scenario)
        tally = _FrameTally(config)
        for chunk in lockstep_groups(seeds, lockstep).values():
            for index, (seed, result) in enumerate(zip(chunk, run_lockstep(scenario, chunk, driver=driver, observers=[tally]))):
                frames = len(result.records)
                intervened = driver.intervention_frames[index] if env_kind == "safe" else 0
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
    """Sums, per environment, the RL reward (:func:`mmpc.rl.reward.frame_reward`) and the ego's
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
    """The vectorized training environment (``train.n_envs`` environments, monitored): the safe or
    the plain environments on the scenario's world (``scenario.sim``), or plain highway-env."""
    from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor

    n_envs = config.train.n_envs
    if env_kind == "safe":
        from mmpc.rl.vec_env import SafeVecEnv

        venv = SafeVecEnv(n_envs, config.scenario, config.env, config.reward, continuous=continuous, seed=seed)
    elif env_kind == "plain":
        from mmpc.rl.vec_env import PlainVecEnv

        if continuous:
            raise ValueError("the plain environments take highway-env's DiscreteMetaAction (dqn or ppo); continuous "
                             "actions (sac) train on plain highway-env (--env highway)")
        venv = PlainVecEnv(n_envs, config.scenario, config.env, config.reward, seed=seed)
    elif env_kind == "highway":
        venv = DummyVecEnv([lambda: make_highway_env(config, continuous=continuous) for _ in range(n_envs)])
    else:
        raise ValueError(f"`env_kind` must be one of {ENV_KINDS}; got {env_kind!r}")
    venv.seed(seed)
    return VecMonitor(venv)


def algorithm_kwargs(config: RLConfig, algo: str) -> dict:
    """The run's constructor arguments of ``algo``; unknown names, and a ``learning_rate`` that is
    not a finite number > 0, raise :class:`mmpc.config.ConfigError`."""
    kwargs = dict(config.algorithms.get(algo, {}))
    allowed = set(inspect.signature(algorithm_class(algo).__init__).parameters) - {"self", "policy", "env"}
    unknown = sorted(set(kwargs) - allowed)
    require(not unknown, f"unknown argument(s) {unknown} in `algorithms.{algo}`; {ALGORITHM_CLASSES[algo]} accepts {sorted(allowed)}")
    rate = kwargs.get("learning_rate", 1.0)
    require(is_finite_number(rate) and rate > 0, f"`algorithms.{algo}.learning_rate` must be a finite number > 0; got {rate!r}")
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
    resume: bool = False,
) -> dict:
    """Train ``algo`` for ``timesteps`` environment steps, save it, evaluate it.

    With ``resume`` the run in ``out`` (the same algorithm, environment, seed and configuration)
    goes on from its latest checkpoint until it has trained ``timesteps`` steps in all; its
    TensorBoard curves and crash log continue where the checkpoint left them.

    stable-baselines3 trains whole rollouts (:func:`rollout_steps`): a budget that is not a
    multiple of one is rounded up, with a warning, and the run records the steps it trained
    (``trained_timesteps`` in config.yaml and the summary).

    Args:
        config: the run's configuration.
        algo: ``dqn``, ``ppo`` or ``sac``.
        timesteps: environment (agent) steps, summed over the vectorized environments.
        out: the run directory: new, empty or missing (created; see the module docstring); with
            ``resume``, the folder of the run to go on with.
        env_kind: ``safe`` (the goal-choosing environments), ``plain`` (no layer, highway-env's
            meta-actions, on the scenario's world) or ``highway`` (plain highway-env).
        seed: seeds the model and the training environments, in [0, 2^32 - 1].
        progress_bar: SB3's progress bar.
        evaluate_after: run the evaluation (``train.eval_episodes`` episodes) and write eval.json.

    Returns:
        The evaluation summary (``{}`` without evaluation).

    Raises:
        mmpc.config.ConfigError: settings the run cannot start with (``seed``, ``algorithms.<algo>``,
            the expert prior, or what the environments or the model refuse, e.g. the action space
            or the scenario's MPC), before anything is written to ``out``.
        mmpc.files.OutputFolderError: ``out`` cannot be written, is held by another run or holds
            files (:func:`mmpc.rl.folders.run_folder`); with ``resume``: it holds no run of these
            settings, or no checkpoint of it.
    """
    from stable_baselines3.common.callbacks import CallbackList

    from mmpc.rl.callbacks import CrashLog, SafetyTensorboardCallback
    from mmpc.rl.checkpoints import Checkpoints

    if algo not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {algo!r}; expected one of {sorted(ALGORITHMS)}")
    if env_kind not in ENV_KINDS:
        raise ValueError(f"`env_kind` must be one of {ENV_KINDS}; got {env_kind!r}")
    require_int("", low=1, timesteps=timesteps)
    require_int("", low=0, high=MAX_SEED, seed=seed)
    continuous = config.action_for(algo) == "continuous"
    # Other algorithms ignore the prior (as algorithms.ppo), and so does the plain baseline of a recipe:
    # highway-env's own actions hold no expert to start at.
    expert_prior = config.train.expert_prior if algo == "ppo" and env_kind == "safe" else 0.0
    require(expert_prior == 0 or (not continuous and config.env.expert_action),
            f"train: `expert_prior` sets PPO's discrete policy towards the expert action, so it needs discrete actions "
            f"and env.expert_action: true; got {'continuous' if continuous else 'discrete'} actions, expert_action "
            f"{config.env.expert_action}")
    kwargs = algorithm_kwargs(config, algo)
    torch.set_num_threads(config.train.torch_threads)
    out = Path(out)
    run = {"algo": algo, "env": env_kind, "action": "continuous" if continuous else "discrete",
           "timesteps": timesteps, "seed": seed, "config": to_dict(config)}
    fresh = None if resume else "a training run neither resumes nor overwrites one (--resume goes on with it)"
    with run_folder(out, RUN_LOCK, "another `mmpc rl train` run", fresh=fresh, describe=_held_run):
        recorded = run_record(out / "config.yaml") if resume else {}
        checkpoint = _resume_point(out, recorded, run) if resume else None
        env, model = _start(config, algo, env_kind, continuous, seed, out, kwargs, expert_prior, checkpoint)
        if checkpoint is None:
            # the scenario alone, for `mmpc drive --scenario DIR/scenario.yaml --driver sb3:DIR/model.zip`
            (out / "scenario.yaml").write_text(yaml.safe_dump(run["config"]["scenario"], sort_keys=False))
        else:
            run["resumed_at"] = recorded.get("resumed_at", []) + [checkpoint.steps]
            logger.info("%s resumes from %s (%d steps)", out, checkpoint.model.name, checkpoint.steps)
        atomic_write_text(out / "config.yaml", yaml.safe_dump(run, sort_keys=False))
        rollout = rollout_steps(model)
        if rollout is not None and timesteps % rollout:
            logger.warning("%s trains whole rollouts of %d steps (n_envs = %d): %d timesteps round up to %d (config.yaml "
                           "records trained_timesteps)", algo, rollout, config.train.n_envs, timesteps,
                           math.ceil(timesteps / rollout) * rollout)
        checkpoints = Checkpoints(config.train.checkpoint_every, out / "checkpoints", algo)
        safety = SafetyTensorboardCallback(config.train.log_every,
                                           crash_log=CrashLog(out / "crashes.csv", config.scenario.frequency,
                                                              append=checkpoint is not None),
                                           totals=(0, 0) if checkpoint is None else _counts_at(out, checkpoint.steps))
        start = time.perf_counter()
        try:
            model.learn(max(timesteps - model.num_timesteps, 0), callback=CallbackList([checkpoints, safety]),
                        tb_log_name=algo, progress_bar=progress_bar, reset_num_timesteps=checkpoint is None)
        finally:
            env.close()
        train_s = time.perf_counter() - start
        model.save(out / "model.zip")
        run["trained_timesteps"] = int(model.num_timesteps)
        atomic_write_text(out / "config.yaml", yaml.safe_dump(run, sort_keys=False))
        logger.info("trained %s on %s for %d steps in %.0f s", algo, env_kind, model.num_timesteps, train_s)
        if not evaluate_after:
            return {}
        summary = evaluate_run(model, config, env_kind=env_kind, continuous=continuous)
        summary = {"algo": algo, "env": env_kind, "timesteps": timesteps, "trained_timesteps": run["trained_timesteps"],
                   "train_seconds": train_s, **summary}
        (out / "eval.json").write_text(json.dumps(summary, indent=2) + "\n")
        return summary


def _counts_at(out: Path, steps: int) -> tuple[int, int]:
    """The run's ``safety/crashes`` and ``safety/episodes`` last logged at or before ``steps`` (0 where none)."""
    from mmpc.rl.report import read_scalars

    scalars = read_scalars(out)
    counts = []
    for tag in ("safety/crashes", "safety/episodes"):
        logged = [(step, value) for step, value in scalars.get(tag, []) if step <= steps]
        counts.append(int(max(logged)[1]) if logged else 0)
    return counts[0], counts[1]


def _resume_point(out: Path, recorded: dict, run: dict) -> "Checkpoint":
    """The checkpoint a resumed run starts from: the latest of the run in ``out``, whose recorded
    settings (``recorded``, its config.yaml) must be ``run``'s (all but the budget)."""
    from mmpc.files import OutputFolderError
    from mmpc.rl.checkpoints import latest_checkpoint

    if not recorded:
        raise OutputFolderError(f"`out` {out} holds no training run to resume (no readable config.yaml); start one there "
                                "without --resume")
    keys = ("algo", "env", "action", "seed", "config")
    differing = [key for key in keys if recorded.get(key) != run[key]]
    if differing:
        raise OutputFolderError(f"`out` {out} holds {_held_run(out)}; resuming it needs its own settings, these differ in "
                                f"{differing} (resume with the run's algorithm, environment, seed and config)")
    checkpoint = latest_checkpoint(out / "checkpoints", run["algo"])
    if checkpoint is None:
        raise OutputFolderError(f"`out` {out} holds no checkpoint of {run['algo']} to resume from (checkpoints/ is empty); "
                                "start the run afresh in an empty folder")
    return checkpoint


def _start(config: RLConfig, algo: str, env_kind: str, continuous: bool, seed: int, out: Path, kwargs: dict,
           expert_prior: float, checkpoint: Optional["Checkpoint"] = None) -> tuple[Any, Any]:
    """The training environments and the model (new, or read from ``checkpoint``), built before the
    run writes anything in ``out``: a setting they refuse (a ``ValueError`` of the environments, the
    MPC, stable-baselines3 or torch) raises :class:`mmpc.config.ConfigError` with its message."""
    # a resumed run's environments draw other episodes than its start's did
    env_seed = seed if checkpoint is None else (seed + checkpoint.steps) % (MAX_SEED + 1)
    try:
        env = make_training_env(config, env_kind=env_kind, continuous=continuous, seed=env_seed)
        try:
            # the policy stays on the CPU and reads numpy whatever --device says (that is the MPC's and the simulator's)
            if checkpoint is None:
                model = algorithm_class(algo)("MlpPolicy", env, seed=seed, verbose=0, tensorboard_log=str(out / "tb"),
                                              **{"device": "cpu", **kwargs})
            else:
                model = algorithm_class(algo).load(checkpoint.model, env=env, device="cpu", tensorboard_log=str(out / "tb"))
                if checkpoint.replay_buffer is not None:
                    model.load_replay_buffer(checkpoint.replay_buffer)
        except BaseException:
            env.close()
            raise
    except ConfigError:
        raise
    except ValueError as error:
        raise ConfigError(f"{algo} on {env_kind} cannot start: {error}") from error
    if expert_prior > 0 and checkpoint is None:
        prefer_expert_action(model, expert_prior)
    return env, model


def rollout_steps(model: Any) -> Optional[int]:
    """The environment steps of one rollout of ``model``: stable-baselines3 trains whole rollouts,
    so ``model.learn(T)`` trains T rounded up to a multiple of it. PPO's ``n_steps x n_envs``,
    DQN's and SAC's ``train_freq x n_envs`` (``None`` for a ``train_freq`` counted in episodes)."""
    from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm
    from stable_baselines3.common.type_aliases import TrainFrequencyUnit

    if isinstance(model, OnPolicyAlgorithm):
        return model.n_steps * model.n_envs
    if model.train_freq.unit == TrainFrequencyUnit.STEP:
        return model.train_freq.frequency * model.n_envs
    return None


def _held_run(out: Path) -> str:
    """What an occupied run folder holds, as words (the run its config.yaml records, or files)."""
    run = run_record(out / "config.yaml")
    if not {"algo", "env", "seed"} <= set(run):
        return "files"
    described = f"{run['algo']} on {run['env']}, seed {run['seed']}"
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
