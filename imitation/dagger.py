"""DAgger with the multi-modal MPC as the online expert (``mmpc imitate dagger``).

Round 0 clones the expert's own demonstrations (a Minari dataset from ``mmpc demos``, or
episodes the expert drives here). Every later round i:

1. the current policy pi_i drives ``episodes_per_iteration`` new seeded episodes (in lockstep:
   one policy call per step for all of them), recording the state the expert needs at every
   visited step (beta_i = 0: the learner alone drives, Ross et al.'s recommended schedule
   after the first round);
2. the expert labels every visited state of the round in large batches: ``label_batch``
   states per :meth:`mmpc.drivers.MPCDriver.decide` call, i.e. one optimizer call over
   ``label_batch x G`` goal-directed problems (the MPC is memoryless, so a state labelled
   off-line gets the command the expert would have given on-line);
3. the labelled states join the aggregate data set D and pi_{i+1} is trained on all of D
   from scratch (:func:`mmpc.imitation.bc.train_policy`).

Writes ``RUN/policy.pt`` (the last round's policy), ``RUN/round_<i>/policy.pt``,
``RUN/dagger.json`` (per round: samples, the learner's collisions and mean meta cost,
validation loss), ``RUN/data.npz`` (the aggregate data set) and TensorBoard events under
``RUN/tb``.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Optional, Sequence

import numpy as np
import torch

from mmpc.config import dataclass_from_dict
from mmpc.drive import stack_observations
from mmpc.drivers import Driver, Observation
from mmpc.imitation.bc import TrainConfig, hyperparameters_text, train_policy
from mmpc.imitation.dataset import Transitions
from mmpc.imitation.policy import PolicyDriver, save_policy
from mmpc.imitation.rollout import Rollout, executed_command, rollout_lockstep
from mmpc.scenario import ScenarioConfig

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class DaggerConfig:
    """Settings of :func:`run_dagger`.

    Attributes:
        iterations: DAgger rounds after round 0 [-].
        initial_episodes: expert-driven episodes of round 0 when no dataset is given [-].
        episodes_per_iteration: learner-driven episodes per round [-].
        seed_start: first seed of the episodes driven here (round 0 and every round draw
            consecutive, disjoint seeds from it; keep them apart from evaluation seeds).
        lockstep: episodes driven together (one driver call per step) [-].
        label_batch: visited states per expert call when labelling [-].
        duration: episode length [s]; ``None``: the scenario's.
        train: training of each round's policy.
    """

    iterations: int = 4
    initial_episodes: int = 16
    episodes_per_iteration: int = 16
    seed_start: int = 2000
    lockstep: int = 8
    label_batch: int = 256
    duration: Optional[float] = None
    train: TrainConfig = field(default_factory=TrainConfig)

    def __post_init__(self) -> None:
        for name in ("iterations", "initial_episodes", "episodes_per_iteration", "seed_start", "lockstep", "label_batch"):
            value = getattr(self, name)
            low = 0 if name in ("iterations", "seed_start") else 1
            if not isinstance(value, int) or isinstance(value, bool) or value < low:
                raise ValueError(f"`{name}` must be an int >= {low}; got {value!r}")
        if self.duration is not None and not (self.duration > 0 and math.isfinite(self.duration)):
            raise ValueError(f"`duration` must be null or a finite number > 0 s; got {self.duration}")

    @classmethod
    def from_dict(cls, values: Mapping[str, Any], *, where: str = "dagger config") -> "DaggerConfig":
        values = dict(values)
        if "train" in values:
            values["train"] = TrainConfig.from_dict(values["train"] or {}, where=f"{where}: train")
        return dataclass_from_dict(cls, values, where=where)


def label_states(expert: Driver, states: Sequence[Observation], batch: int) -> np.ndarray:
    """The expert's executed commands at ``states`` (E = 1 observations), ``batch`` states per call.

    Returns:
        (S, 2) float32 (acceleration [m/s^2], steering [rad]), clipped as highway-env applies them.
    """
    labels = np.empty((len(states), 2), dtype=np.float32)
    expert.reset(min(batch, len(states)))
    for start in range(0, len(states), batch):
        chunk = list(states[start:start + batch])
        decision = expert.decide(stack_observations(chunk, range(len(chunk))))
        for row in range(len(chunk)):
            labels[start + row] = executed_command(float(decision.acceleration[row]), float(decision.steering[row]))
    return labels


def _drive(scenario: ScenarioConfig, seeds: Sequence[int], driver: Driver, lockstep: int, keep_states: bool) -> list[Rollout]:
    rollouts: list[Rollout] = []
    for start in range(0, len(seeds), lockstep):
        rollouts += rollout_lockstep(scenario, seeds[start:start + lockstep], driver, keep_states=keep_states)
    return rollouts


def _rollout_stats(rollouts: Sequence[Rollout]) -> dict:
    episodes = [r.episode for r in rollouts]
    return {
        "episodes": len(episodes),
        "collisions": int(sum(bool(e.terminations.any()) for e in episodes)),
        "meta_cost_mean": float(np.mean([np.mean(e.infos["meta_cost"][:-1]) for e in episodes])),
        "steps": int(sum(e.steps for e in episodes)),
    }


def run_dagger(
    scenario: ScenarioConfig,
    out: Path,
    config: DaggerConfig = DaggerConfig(),
    *,
    dataset_dir: Optional[Path] = None,
    on_round: Optional[Callable[[dict], None]] = None,
) -> dict:
    """DAgger (see the module docstring).

    Args:
        scenario: the scenario (``config.duration`` overrides its length).
        out: the run folder.
        config: settings.
        dataset_dir: an ``mmpc demos`` directory for round 0 (default: the expert drives
            ``config.initial_episodes`` episodes here).
        on_round: called with each round's entry of ``dagger.json``.

    Returns:
        The ``dagger.json`` content.
    """
    from torch.utils.tensorboard import SummaryWriter

    from mmpc.drivers import MPCDriver
    from mmpc.scenario import build_mpc

    if config.duration is not None:
        scenario = scenario.replace(duration=config.duration)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    expert = MPCDriver(build_mpc(scenario))
    next_seed = config.seed_start
    rounds: list[dict] = []
    with SummaryWriter(str(out / "tb")) as writer, torch.inference_mode(False):
        writer.add_text("hyperparameters", hyperparameters_text(config))
        if dataset_dir is not None:
            from mmpc.imitation.dataset import dataset_transitions, open_dataset

            data = dataset_transitions(open_dataset(Path(dataset_dir)))
            stats: dict = {"source": str(dataset_dir)}
        else:
            seeds = list(range(next_seed, next_seed + config.initial_episodes))
            next_seed += config.initial_episodes
            with torch.inference_mode():
                rollouts = _drive(scenario, seeds, expert, config.lockstep, keep_states=False)
            data = Transitions(
                np.concatenate([r.episode.observations[:-1] for r in rollouts]),
                np.concatenate([r.episode.infos["ego"][:-1, 4:6] for r in rollouts]),
                np.concatenate([r.episode.actions for r in rollouts]),
                np.concatenate([np.full(r.episode.steps, i, dtype=np.int64) for i, r in enumerate(rollouts)]),
            )
            stats = {"source": "expert", "seeds": seeds, **_rollout_stats(rollouts)}
        for round_index in range(config.iterations + 1):
            if round_index > 0:
                seeds = list(range(next_seed, next_seed + config.episodes_per_iteration))
                next_seed += config.episodes_per_iteration
                with torch.inference_mode():
                    rollouts = _drive(scenario, seeds, PolicyDriver(policy), config.lockstep, keep_states=True)
                    states = [state for r in rollouts for state in r.states]
                    labels = label_states(expert, states, config.label_batch)
                first_id = int(data.episodes.max()) + 1
                data = Transitions(
                    np.concatenate([data.observations, *[r.episode.observations[:-1] for r in rollouts]]),
                    np.concatenate([data.commands, *[r.episode.infos["ego"][:-1, 4:6] for r in rollouts]]),
                    np.concatenate([data.actions, labels]),
                    np.concatenate([data.episodes, *[np.full(r.episode.steps, first_id + i, dtype=np.int64)
                                                     for i, r in enumerate(rollouts)]]),
                )
                stats = {"source": "learner", "seeds": seeds, **_rollout_stats(rollouts)}
                writer.add_scalar("dagger/learner_collisions", stats["collisions"], round_index)
                writer.add_scalar("dagger/learner_meta_cost_mean", stats["meta_cost_mean"], round_index)
            policy, history = train_policy(data, config.train, writer=writer, tag=f"round_{round_index}/")
            entry = {
                "round": round_index,
                **stats,
                "samples": int(data.actions.shape[0]),
                "val_loss": history.val_loss[history.best_epoch],
                "val_rmse_acceleration": history.val_rmse[history.best_epoch][0],
                "val_rmse_steering": history.val_rmse[history.best_epoch][1],
            }
            writer.add_scalar("dagger/samples", entry["samples"], round_index)
            writer.add_scalar("dagger/val_loss", entry["val_loss"], round_index)
            save_policy(out / f"round_{round_index}" / "policy.pt", policy, scenario=scenario.name, info={"round": round_index})
            rounds.append(entry)
            logger.info("DAgger round %d: %s", round_index, entry)
            if on_round is not None:
                on_round(entry)
    save_policy(out / "policy.pt", policy, scenario=scenario.name, info={"round": config.iterations, "samples": int(data.actions.shape[0])})
    np.savez_compressed(out / "data.npz", observations=data.observations, commands=data.commands, actions=data.actions,
                        episodes=data.episodes)
    report = {"scenario": scenario.name, "duration": scenario.duration,
              "config": json.loads(json.dumps(asdict(config), default=list)), "rounds": rounds}
    (out / "dagger.json").write_text(json.dumps(report, indent=2) + "\n")
    return report
