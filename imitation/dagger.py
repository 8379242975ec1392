"""DAgger with the multi-modal MPC as the online expert (``mmpc imitate dagger``).

Round 0 clones the expert's own demonstrations (a Minari dataset from ``mmpc imitate demos``, or
episodes the expert drives here). Every later round i = 1 ... K:

1. the mixture ``pi_i = beta_i pi* + (1 - beta_i) pi^_i`` drives ``episodes_per_iteration`` new
   seeded episodes (in lockstep: one learner call per step for all of them): at every step of
   every episode the expert pi* drives with probability ``beta_i = beta * beta_decay^(i - 1)``
   and the current policy pi^_i otherwise (Ross et al., 2011); the expert is only asked where
   it drives. With ``noise`` > 0, Gaussian noise ``N(0, diag(noise)^2)`` is added to every
   executed command (DART, Laskey et al., 2017): the visited states then include the
   recoveries from command errors the clean expert never makes, and the policy cannot just
   copy the command being executed;
2. the expert labels every step the learner drove (every step, with noise), in large batches:
   ``label_batch`` states per :meth:`mmpc.drivers.MPCDriver.decide` call, i.e. one optimizer
   call over ``label_batch x G`` goal-directed problems (the MPC is memoryless, so a state
   labelled off-line gets the command the expert would have given on-line); without noise the
   steps it drove carry its command already;
3. the labelled states join the aggregate data set D and pi^_{i+1} is trained on all of D from
   scratch (:func:`mmpc.imitation.bc.train_policy`);
4. the new policy drives ``check_episodes`` seeded episodes alone (seeds from
   ``check_seed_start``, the same every round, apart from the training and evaluation seeds):
   its collisions and mean meta cost there are the round's check. The policy returned is the
   round's with the fewest check collisions (ties: the later round, trained on more data), as
   Ross et al. (2011) return the best policy on validation rather than the last.

The expert's command averages its plan over the MPC's ``command_window`` (0.3 s in the shipped
scenarios), and a plan starts from the acceleration and heading rate being executed, so over
0.3 s the command follows them closely (figures in docs/experiments/2026-11-21-imitation.md). A
policy given the executing command then learns to copy it (causal confusion), and one not given it
sees labels that vary with something it cannot observe. ``label_window`` sets a longer window
for the expert that drives and labels here, so the labels are (nearly) functions of the
scene: the policy clones the first ``label_window`` seconds of the expert's plan.

Writes, after every round, ``RUN/round_<i>/policy.pt``, ``RUN/data.npz`` (the aggregate data
set) and ``RUN/dagger.json`` (the config and, per round: beta, the share of steps the expert
drove, collisions and mean meta cost of the round's episodes, samples, validation loss, the
check), and TensorBoard events under ``RUN/tb``; at the end ``RUN/policy.pt`` (the best round's
policy, named in ``dagger.json``'s ``best_round``).
Re-running the same command on the same folder resumes after the last finished round, and a
re-run with more ``iterations`` extends the run (a folder of another configuration is refused).
A run holds the folder's :data:`LOCK` while it writes, so a second run there is refused.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, NamedTuple, Optional, Sequence

import numpy as np
import torch

from mmpc.config import from_dict, require_int, to_dict
from mmpc.drivers import Decision, Driver, Observation
from mmpc.drivers.verified import behind_check
from mmpc.highway.highway_env_world import stack_observations
from mmpc.evaluate import Backend, run_tasks
from mmpc.evaluate.tasks import lockstep_groups
from mmpc.files import atomic_write, atomic_write_text
from mmpc.imitation.bc import TrainConfig, hyperparameters_text, train_policy
from mmpc.imitation.dagger_rounds import best_of, beta_of, run_rounds
from mmpc.imitation.dataset import Transitions
from mmpc.imitation.features import scene_geometry
from mmpc.imitation.policy import PolicyConfig, PolicyDriver, load_policy, save_policy
from mmpc.imitation.rollout import Rollout, executed_command, rollout_lockstep
from mmpc.problem import EGO_V
from mmpc.rl.folders import run_folder
from mmpc.scenario import ScenarioConfig

logger = logging.getLogger(__name__)


#: The lock file a run holds in its folder while it writes (:func:`mmpc.rl.folders.run_folder`).
LOCK = ".dagger.lock"

#: The policy DAgger trains by default: 2 x 128 ReLU, fewer check collisions than BC's 2 x 256 tanh
#: on the same data (docs/experiments/2026-11-21-imitation.md).
DAGGER_POLICY = PolicyConfig(hidden=(128, 128), activation="relu")


@dataclass(frozen=True)
class DaggerConfig:
    """Settings of :func:`run_dagger`. The defaults are the recipe of the README's results
    (``mmpc imitate dagger`` without ``--config``; ``mmpc config show dagger``).

    Attributes:
        iterations: DAgger rounds after round 0 (check collisions / 20 in rounds 8-12 with the
            expert of then: 2, 2, 2, 2, 7) [-].
        initial_episodes: expert-driven episodes of round 0 when no dataset is given [-].
        episodes_per_iteration: episodes driven by the mixture per round [-].
        beta: probability that the expert drives a step in round 1, in [0, 1] [-].
        beta_decay: factor on beta from one round to the next, in [0, 1] [-].
        noise: standard deviations of the Gaussian noise on the executed acceleration [m/s^2]
            and steering [rad] in rounds >= 1 (0: none).
        label_window: command window of the expert that drives and labels here [s] (see the
            module docstring; the shipped scenarios' is 0.3 s); ``None``: the scenario's
            ``mpc.command_window``.
        seed_start: first seed of the episodes driven here (round 0 and every round draw
            consecutive, disjoint seeds from it; keep them apart from evaluation seeds, 0-49,
            and demonstrations, 1000+).
        lockstep: episodes driven together (one driver call per step) [-].
        label_batch: visited states per expert call when labelling [-].
        duration: episode length [s]; ``None``: the scenario's.
        check_episodes: episodes the policy of every round drives alone (0: no check; the last
            round's policy is returned) [-].
        check_seed_start: first seed of those episodes.
        train: training of each round's policy.
        verify: the expert that drives and labels is the MPC behind the check (``verified:mpc``:
            every label keeps a verified way out from its state; a ``--dataset`` must hold that
            expert's demonstrations). Runs recorded before the setting existed resume without it.
    """

    iterations: int = 12
    initial_episodes: int = 20
    episodes_per_iteration: int = 20
    beta: float = 0.3
    beta_decay: float = 0.5
    noise: tuple[float, float] = (0.5, 0.01)
    label_window: Optional[float] = 1.0
    seed_start: int = 2000
    lockstep: int = 8
    label_batch: int = 256
    duration: Optional[float] = None
    check_episodes: int = 20
    check_seed_start: int = 3000
    train: TrainConfig = field(default_factory=lambda: TrainConfig(policy=DAGGER_POLICY))
    verify: bool = True

    def __post_init__(self) -> None:
        require_int("", low=1, initial_episodes=self.initial_episodes, episodes_per_iteration=self.episodes_per_iteration,
                    lockstep=self.lockstep, label_batch=self.label_batch)
        require_int("", low=0, iterations=self.iterations, seed_start=self.seed_start, check_episodes=self.check_episodes,
                    check_seed_start=self.check_seed_start)
        if isinstance(self.noise, list):
            object.__setattr__(self, "noise", tuple(self.noise))
        if len(self.noise) != 2 or not all(isinstance(v, (int, float)) and 0 <= v < math.inf for v in self.noise):
            raise ValueError(f"`noise` must be two finite stds >= 0 (acceleration [m/s^2], steering [rad]); got {self.noise!r}")
        for name in ("beta", "beta_decay"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"`{name}` must be in [0, 1]; got {getattr(self, name)!r}")
        if self.label_window is not None and not (self.label_window > 0 and math.isfinite(self.label_window)):
            raise ValueError(f"`label_window` must be null or a finite number > 0 s; got {self.label_window}")
        if self.duration is not None and not (self.duration > 0 and math.isfinite(self.duration)):
            raise ValueError(f"`duration` must be null or a finite number > 0 s; got {self.duration}")
        if not isinstance(self.verify, bool):
            raise ValueError(f"`verify` must be true or false; got {self.verify!r}")

    def beta_of(self, round_index: int) -> float:
        """beta_i of round i >= 1 (the expert's share of the driving; :func:`mmpc.imitation.dagger_rounds.beta_of`)."""
        return beta_of(self.beta, self.beta_decay, round_index)


def _rows(observation: Observation, rows: torch.Tensor) -> Observation:
    """The observation of some of its E environments (``rows`` on the observation's device)."""
    return Observation(
        observation.ego[rows], observation.vehicles[rows],
        None if observation.vehicle_mask is None else observation.vehicle_mask[rows],
        None if observation.kinematics is None else observation.kinematics[rows.cpu().numpy()],
        observation.ids()[rows],
    )


class MixtureDriver(Driver):
    """``beta pi* + (1 - beta) pi^``: for every environment and step, the expert drives with
    probability ``beta``, the learner otherwise (always where the ego is reversing, which the MPC
    does not plan for). The expert decides only for its rows (one batched call); its rows of the
    decision keep its goal index and feasible count (>= 0), the learner's have -1, which is how a
    recorded step tells who drove.

    Args:
        expert: the expert (e.g. :class:`mmpc.drivers.MPCDriver`).
        learner: the policy being trained.
        beta: the expert's probability, in [0, 1].
        rng: the coin flips.

    The mixture takes its observations where the learner computes (:attr:`device`) and hands the
    expert its rows on the expert's device; the decision lies on the learner's device.
    """

    def __init__(self, expert: Driver, learner: Driver, beta: float, rng: np.random.Generator) -> None:
        if not 0.0 <= beta <= 1.0:
            raise ValueError(f"`beta` must be in [0, 1]; got {beta}")
        self.expert, self.learner, self.beta, self.rng = expert, learner, beta, rng
        self.name = f"mixture(beta={beta:g})"

    @property
    def device(self) -> torch.device:
        return self.learner.device

    def reset(self, num_envs: int) -> None:
        self.expert.reset(num_envs)
        self.learner.reset(num_envs)

    def decide(self, observation: Observation) -> Decision:
        start = time.perf_counter()
        decision = self.learner.decide(observation)
        chosen = torch.from_numpy(self.rng.random(observation.num_envs) < self.beta).to(observation.ego.device)
        chosen &= observation.ego[:, EGO_V] >= 0  # the MPC plans forward motion only; the learner keeps the rest
        if bool(chosen.any()):
            rows = chosen.nonzero().squeeze(1)
            expert = self.expert.decide(_rows(observation, rows).to(self.expert.device))
            merged = {}
            for name in ("acceleration", "steering", "goal_index", "feasible_goals", "fallback", "plan_cost"):
                values = getattr(decision, name).clone()
                values[rows.to(values.device)] = getattr(expert, name).to(values.device, values.dtype)
                merged[name] = values
            decision = Decision(solve_ms=0.0, **merged)
        return decision._replace(solve_ms=(time.perf_counter() - start) * 1e3)


class NoisyDriver(Driver):
    """Another driver's commands plus Gaussian noise (DART): ``u + N(0, diag(std)^2)``.

    Args:
        driver: the driver whose commands are perturbed.
        std: standard deviations of the acceleration [m/s^2] and steering [rad] noise.
        rng: the noise.
    """

    def __init__(self, driver: Driver, std: tuple[float, float], rng: np.random.Generator) -> None:
        self.driver, self.std, self.rng = driver, std, rng
        self.name = f"{driver.name}+noise{tuple(std)}"

    @property
    def device(self) -> torch.device:
        return self.driver.device

    def reset(self, num_envs: int) -> None:
        self.driver.reset(num_envs)

    def decide(self, observation: Observation) -> Decision:
        decision = self.driver.decide(observation)
        noise = torch.from_numpy(self.rng.normal(0.0, 1.0, (observation.num_envs, 2)) * np.asarray(self.std))
        noise = noise.to(decision.acceleration.device)
        return decision._replace(acceleration=decision.acceleration + noise[:, 0].to(decision.acceleration.dtype),
                                 steering=decision.steering + noise[:, 1].to(decision.steering.dtype))


def label_states(expert: Driver, states: Sequence[Observation], batch: int) -> np.ndarray:
    """The expert's executed commands at ``states`` (E = 1 observations, on any device; each
    batch goes to the expert's device, its commands come back in one copy), ``batch`` states per call.
    The expert is reset before each batch: a warm-starting expert (:mod:`mmpc.warm`) labels every
    state from the cold start, whatever the order (the commands it recorded while driving were warm).

    Returns:
        (S, 2) float32 (acceleration [m/s^2], steering [rad]), clipped as highway-env applies them.
    """
    labels = np.empty((len(states), 2), dtype=np.float32)
    for start in range(0, len(states), batch):
        chunk = list(states[start:start + batch])
        expert.reset(len(chunk))  # states off-line, not one environment's next steps: each batch from scratch (cold)
        decision = expert.decide(stack_observations(chunk, range(len(chunk))).to(expert.device))
        commands = zip(decision.acceleration.cpu().tolist(), decision.steering.cpu().tolist())
        for row, (acceleration, steering) in enumerate(commands):
            labels[start + row] = executed_command(acceleration, steering)
    return labels


class _DriveTask(NamedTuple):
    """A lockstep group of DAgger's episodes."""

    scenario: ScenarioConfig
    seeds: tuple[int, ...]
    driver: Driver
    keep_states: bool

    @property
    def label(self) -> str:
        return f"DAgger {self.driver.name} seeds {self.seeds[0]}-{self.seeds[-1]}"


def _drive_group(task: _DriveTask) -> list[Rollout]:
    return rollout_lockstep(task.scenario, task.seeds, task.driver, keep_states=task.keep_states)


def _raise(task: _DriveTask, error: BaseException | str) -> list[Rollout]:
    raise error if isinstance(error, BaseException) else RuntimeError(f"{task.label}: {error}")


def _drive(scenario: ScenarioConfig, seeds: Sequence[int], driver: Driver, lockstep: int, keep_states: bool) -> list[Rollout]:
    """Episodes of ``seeds`` in lockstep groups (``seed // lockstep``), in this process: the
    mixture's random stream runs through the groups in order."""
    tasks = [_DriveTask(scenario, tuple(group), driver, keep_states) for group in lockstep_groups(seeds, lockstep).values()]
    backend = Backend(workers=1, threads=torch.get_num_threads())
    return [rollout for _, rollouts in run_tasks(tasks, _drive_group, _raise, backend) for rollout in rollouts]


def _rollout_stats(rollouts: Sequence[Rollout]) -> dict:
    episodes = [r.episode for r in rollouts]
    return {
        "episodes": len(episodes),
        "collisions": int(sum(bool(e.terminations.any()) for e in episodes)),
        "meta_cost_mean": float(np.mean([np.mean(e.infos["meta_cost"][:-1]) for e in episodes])),
        "steps": int(sum(e.steps for e in episodes)),
    }


def best_round(rounds: Sequence[dict]) -> int:
    """The round whose policy had the fewest check collisions (ties: the later round); the last
    round when the rounds carry no check."""
    return best_of(rounds, lambda e: (e["check_collisions"], -e["round"]) if "check_collisions" in e else None)


def _transitions(rollouts: Sequence[Rollout], actions: Sequence[np.ndarray], first_id: int) -> Transitions:
    """The steps of ``rollouts`` with the given (T, 2) labels (NaN rows left out), episode ids
    from ``first_id``."""
    parts = []
    for i, (r, labels) in enumerate(zip(rollouts, actions)):
        keep = ~np.isnan(labels[:, 0])
        parts.append(Transitions(r.episode.infos["ego"][:-1][keep], r.episode.infos["neighbours"][:-1][keep], labels[keep],
                                 np.full(int(keep.sum()), first_id + i, dtype=np.int64)))
    return Transitions.concatenate(parts)


def label_rollouts(expert: Driver, rollouts: Sequence[Rollout], batch: int, *, noisy: bool = False) -> tuple[list[np.ndarray], int]:
    """Expert labels of every step of ``rollouts`` (recorded with ``keep_states``): the executed
    command where the expert drove (``feasible_goals >= 0``) and no noise was added,
    :func:`label_states` elsewhere; NaN where the ego was reversing (outside the MPC's domain).

    Returns:
        One (T, 2) float32 array per rollout, and the number of steps the expert drove.
    """
    labels = [r.episode.actions.copy() for r in rollouts]
    drove = [r.episode.infos["feasible_goals"][:-1] >= 0 for r in rollouts]
    for label, rollout in zip(labels, rollouts):
        label[rollout.episode.infos["ego"][:-1, EGO_V] < 0] = np.nan
    pending = [(i, t) for i, r in enumerate(rollouts) for t in range(r.episode.steps)
               if (noisy or not drove[i][t]) and not np.isnan(labels[i][t, 0])]
    computed = label_states(expert, [rollouts[i].states[t] for i, t in pending], batch) if pending else []
    for (i, t), label in zip(pending, computed):
        labels[i][t] = label
    return labels, int(sum(d.sum() for d in drove))


def _report(identity: dict, config: DaggerConfig, rounds: list[dict]) -> dict:
    """The content of ``dagger.json``: the run's identity, its rounds and the best of them."""
    return {**identity, "iterations": config.iterations, "best_round": best_round(rounds), "rounds": rounds}


def _resume(out: Path, identity: dict) -> tuple[list[dict], Optional[Transitions]]:
    """Rounds and aggregate data of an earlier run of the same configuration in ``out``."""
    path = out / "dagger.json"
    if not path.exists():
        return [], None
    try:
        report = json.loads(path.read_text())
        earlier = {key: report[key] for key in identity}
        rounds = list(report["rounds"])
        earlier["config"] = {"verify": False, **earlier["config"]}  # a run recorded before the check existed
    except (ValueError, KeyError, TypeError) as error:
        raise ValueError(f"{path} is not a readable DAgger report ({type(error).__name__}: {error}); "
                         "remove it or choose another --out") from error
    try:  # in today's form: a report of an earlier mmpc may hold retired scenario keys
        earlier["scenario"] = to_dict(from_dict(ScenarioConfig, earlier["scenario"], where=f"{path}: scenario"))
    except (ValueError, TypeError) as error:
        raise ValueError(f"{path} holds a scenario this mmpc cannot read ({error}); choose another --out") from error
    if earlier != identity:
        changed = sorted(k for k in identity if earlier[k] != identity[k])
        if "config" in changed:
            changed[changed.index("config")] = "config: " + ", ".join(
                sorted(k for k in identity["config"] if earlier["config"].get(k) != identity["config"][k]))
        raise ValueError(f"{out} holds a DAgger run of another configuration (differs in: {', '.join(changed)}); "
                         "re-run with the same settings to resume, or choose another --out")
    if not rounds:
        return [], None
    with np.load(out / "data.npz") as stored:
        data = Transitions(*(stored[name] for name in Transitions._fields))
    if data.actions.shape[0] != rounds[-1]["samples"]:
        raise ValueError(f"{out / 'data.npz'} holds {data.actions.shape[0]} samples, dagger.json's last round "
                         f"{rounds[-1]['samples']}; remove the folder or choose another --out")
    return rounds, data


def run_dagger(
    scenario: ScenarioConfig,
    out: Path,
    config: DaggerConfig = DaggerConfig(),
    *,
    dataset_dir: Optional[Path] = None,
    on_round: Optional[Callable[[dict], None]] = None,
) -> dict:
    """DAgger (see the module docstring); resumes an interrupted run in ``out``.

    Args:
        scenario: the scenario (``config.duration`` overrides its length).
        out: the run folder.
        config: settings.
        dataset_dir: an ``mmpc imitate demos`` directory for round 0 (default: the expert drives
            ``config.initial_episodes`` episodes here).
        on_round: called with each round's entry of ``dagger.json`` (also for resumed rounds).

    Returns:
        The ``dagger.json`` content.

    Raises:
        mmpc.files.OutputFolderError: ``out`` cannot be written, or another run holds it (its :data:`LOCK`).
        ValueError: ``out`` holds a run of another configuration, or a corrupt ``dagger.json``.
    """
    out = Path(out)
    with run_folder(out, LOCK, "another `mmpc imitate dagger` run"):
        return _run_rounds(scenario, out, config, dataset_dir, on_round)


def _run_rounds(scenario: ScenarioConfig, out: Path, config: DaggerConfig, dataset_dir: Optional[Path],
                on_round: Optional[Callable[[dict], None]]) -> dict:
    """:func:`run_dagger` in the folder ``out``, whose lock this process holds."""
    from torch.utils.tensorboard import SummaryWriter

    from mmpc.drivers import MPCDriver
    from mmpc.scenario import build_mpc

    if config.duration is not None:
        scenario = scenario.replace(duration=config.duration)
    settings = json.loads(json.dumps(asdict(config), default=list))
    settings.pop("iterations")  # a re-run with more iterations extends the run
    identity = {"scenario": to_dict(scenario), "config": settings,
                "dataset": None if dataset_dir is None else str(dataset_dir)}
    rounds, data = _resume(out, identity)
    for entry in rounds:
        logger.info("DAgger round %d found in %s", entry["round"], out)
        if on_round is not None:
            on_round(entry)
    expert_scenario = scenario
    if config.label_window is not None:
        expert_scenario = scenario.replace(mpc=dataclasses.replace(scenario.mpc, command_window=config.label_window))
    # cold solves: it labels recorded states off-line, where a warm start from the last call's states would not apply
    expert = behind_check(MPCDriver(build_mpc(expert_scenario.replace(
        mpc=dataclasses.replace(expert_scenario.mpc, warm_iterations=0)))), scenario, config.verify)
    expert_name = "verified:mpc" if config.verify else "mpc"
    road = scenario.road
    policy = load_policy(out / f"round_{rounds[-1]['round']}" / "policy.pt") if rounds else None
    with SummaryWriter(str(out / "tb")) as writer, torch.inference_mode(False):
        if not rounds:
            writer.add_text("hyperparameters", hyperparameters_text(config))

        def play(round_index: int) -> dict:
            """One round: drive (round 0: the expert or the dataset), label, train, check; the round's files."""
            nonlocal data, policy
            if round_index == 0 and dataset_dir is not None:
                from mmpc.imitation.dataset import dataset_road, dataset_transitions, open_dataset

                dataset = open_dataset(Path(dataset_dir))
                if dataset_road(dataset) != road:
                    raise ValueError(f"dataset {dataset_dir} was driven on {dataset_road(dataset)}; the scenario has {road}")
                recorded_expert = dataset.storage.metadata.get("mmpc_expert", "mpc")
                if recorded_expert != expert_name:
                    raise ValueError(f"dataset {dataset_dir} holds demonstrations of {recorded_expert}; this run labels with "
                                     f"{expert_name} (`verify`): record them with `mmpc imitate demos --expert "
                                     f"{expert_name}`, or --set verify={str(not config.verify).lower()}")
                window = dataset.storage.metadata["mmpc_scenario"]["mpc"]["command_window"]
                if window != expert_scenario.mpc.command_window:
                    raise ValueError(f"dataset {dataset_dir} holds commands over a {window} s window; `label_window` is "
                                     f"{expert_scenario.mpc.command_window} s: drive round 0 here (no --dataset) instead")
                data = dataset_transitions(dataset)
                stats: dict = {"source": str(dataset_dir)}
            elif round_index == 0:
                seeds = list(range(config.seed_start, config.seed_start + config.initial_episodes))
                with torch.inference_mode():
                    rollouts = _drive(scenario, seeds, expert, config.lockstep, keep_states=False)
                data = _transitions(rollouts, [r.episode.actions for r in rollouts], 0)
                stats = {"source": "expert", "seeds": seeds, **_rollout_stats(rollouts)}
            else:
                first = config.seed_start + config.initial_episodes + (round_index - 1) * config.episodes_per_iteration
                seeds = list(range(first, first + config.episodes_per_iteration))
                beta = config.beta_of(round_index)
                rng = np.random.default_rng([config.seed_start, round_index])
                driver: Driver = MixtureDriver(expert, PolicyDriver(policy), beta, rng)
                noisy = any(v > 0 for v in config.noise)
                if noisy:
                    driver = NoisyDriver(driver, config.noise, rng)
                with torch.inference_mode():
                    rollouts = _drive(scenario, seeds, driver, config.lockstep, keep_states=True)
                    labels, expert_steps = label_rollouts(expert, rollouts, config.label_batch, noisy=noisy)
                data = Transitions.concatenate([data, _transitions(rollouts, labels, int(data.episodes.max()) + 1)])
                stats = {"source": "mixture", "beta": beta, "seeds": seeds, **_rollout_stats(rollouts)}
                stats["expert_share"] = expert_steps / max(stats["steps"], 1)
                writer.add_scalar("dagger/collisions", stats["collisions"], round_index)
                writer.add_scalar("dagger/meta_cost_mean", stats["meta_cost_mean"], round_index)
                writer.add_scalar("dagger/expert_share", stats["expert_share"], round_index)
            policy, history = train_policy(data, road, config.train, scene=scene_geometry(scenario), writer=writer,
                                           tag=f"round_{round_index}/")
            entry = {
                "round": round_index,
                **stats,
                "samples": int(data.actions.shape[0]),
                "val_loss": history.val_loss[history.best_epoch],
                "val_rmse_acceleration": history.val_rmse[history.best_epoch][0],
                "val_rmse_steering": history.val_rmse[history.best_epoch][1],
            }
            if config.check_episodes:
                seeds = list(range(config.check_seed_start, config.check_seed_start + config.check_episodes))
                with torch.inference_mode():
                    check = _rollout_stats(_drive(scenario, seeds, PolicyDriver(policy), config.lockstep, keep_states=False))
                entry.update(check_collisions=check["collisions"], check_meta_cost_mean=check["meta_cost_mean"],
                             check_steps=check["steps"])
                writer.add_scalar("dagger/check_collisions", check["collisions"], round_index)
            writer.add_scalar("dagger/samples", entry["samples"], round_index)
            writer.add_scalar("dagger/val_loss", entry["val_loss"], round_index)
            save_policy(out / f"round_{round_index}" / "policy.pt", policy, scenario=scenario.name, info={"round": round_index})
            atomic_write(out / "data.npz", lambda handle: np.savez_compressed(handle, **data._asdict()))
            return entry

        def record(rounds: list[dict]) -> None:
            atomic_write_text(out / "dagger.json", json.dumps(_report(identity, config, rounds), indent=2) + "\n")
            logger.info("DAgger round %d: %s", rounds[-1]["round"], rounds[-1])

        run_rounds(rounds, config.iterations, play, record, on_round)
    report = _report(identity, config, rounds)
    best = report["best_round"]
    chosen = next(entry for entry in rounds if entry["round"] == best)
    save_policy(out / "policy.pt", load_policy(out / f"round_{best}" / "policy.pt"), scenario=scenario.name,
                info={"round": best, "samples": chosen["samples"]})
    return report
