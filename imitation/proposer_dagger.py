"""DAgger for the mode proposer (``mmpc imitate proposer``): the proposer in the loop, the expert's
full ranking as the label, one Minari dataset per round.

Round 0: the expert drives ``episodes`` seeded episodes and labels every state
(:mod:`mmpc.imitation.labels`). Round i >= 1: the proposer of round i - 1 picks the goal (among
its proposals, certified by the optimizer) at each environment-step with probability
``1 - beta_i``, ``beta_i = beta * beta_decay^(i - 1)``, and the expert labels every state. After
each round a new proposer is trained from scratch on all labels so far
(:func:`mmpc.imitation.listwise.train_proposer`) and drives ``check_episodes`` held-out seeds
alone (:class:`mmpc.imitation.proposer_driver.ProposerDriver`, the same seeds every round) beside
the expert: collisions, mean meta cost and the share of escalated steps are the round's check.
With ``verify`` (the default) the labels are the verified expert's and both drive behind the check.

Writes ``RUN/labels/round_<i>/`` (staged episodes and the round's Minari dataset),
``RUN/round_<i>/proposer.pt``, ``RUN/proposer.json`` (config, per round: beta, labelled states,
labelling throughput, held-out top-k agreement, the check) and TensorBoard events in ``RUN/tb``;
at the end ``RUN/proposer.pt``, the best round's (fewest check collisions, then lowest check meta
cost). Re-running the same command resumes: finished rounds are kept, an unfinished round's staged
episodes are reused, and more ``rounds`` extend the run (another configuration is refused). One run
at a time writes a folder: a run holds the lock file :data:`LOCK` in it and a second is refused.
"""

from __future__ import annotations

import json
import logging
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from mmpc.config import require_int, to_dict
from mmpc.files import atomic_write_text
from mmpc.highway import run_lockstep
from mmpc.imitation.dagger_rounds import best_of, beta_of, run_rounds
from mmpc.imitation.features import scene_geometry
from mmpc.imitation.labels import label_episodes, read_labels
from mmpc.imitation.listwise import ProposerTrainConfig, RankingLabels, train_proposer
from mmpc.imitation.proposer import ModeProposer, load_proposer, save_proposer
from mmpc.imitation.proposer_driver import ProposerDriver
from mmpc.rl.folders import run_folder
from mmpc.drivers import MPCDriver
from mmpc.drivers.verified import behind_check
from mmpc.scenario import ScenarioConfig, build_mpc

logger = logging.getLogger(__name__)

REPORT = "proposer.json"
#: The lock file a run holds in its folder while it writes (:func:`mmpc.rl.folders.run_folder`).
LOCK = ".proposer.lock"


@dataclass(frozen=True)
class ProposerDaggerConfig:
    """Settings of :func:`run_proposer_dagger` (``mmpc config show proposer``). The defaults (8
    rounds of 128 episodes of 40 s: ~4x10^5 labelled states) made the shipped high-speed proposer;
    the shipped cruise one ran ``rounds`` 8 (4.6x10^5).

    Attributes:
        rounds: rounds after round 0 [-].
        episodes: episodes driven and labelled per round [-].
        beta: probability that the expert drives an environment-step in round 1, in [0, 1] [-].
        beta_decay: factor on beta from one round to the next, in [0, 1] [-].
        seed_start: first seed of the labelled episodes (rounds draw consecutive disjoint seeds;
            keep them apart from evaluation seeds).
        lockstep: episodes driven together (one optimizer call per step for all) [-].
        check_episodes: held-out episodes each round's proposer drives alone (0: no check) [-].
        check_seed_start: first seed of those episodes.
        train: training of each round's proposer (its ``keep`` is the driver's).
        verify: labels behind the check (a goal is usable only where its first command keeps a
            verified way out, :class:`mmpc.imitation.labels.RankingExpert`), and the rounds' checks
            drive the proposer and the expert behind it (``verified:``). Runs recorded before the
            setting existed resume as they were labelled, without it.
    """

    rounds: int = 7
    episodes: int = 128
    beta: float = 0.5
    beta_decay: float = 0.5
    seed_start: int = 40000
    lockstep: int = 64
    check_episodes: int = 32
    check_seed_start: int = 49000
    train: ProposerTrainConfig = field(default_factory=ProposerTrainConfig)
    verify: bool = True

    def __post_init__(self) -> None:
        require_int("", low=1, episodes=self.episodes, lockstep=self.lockstep)
        if not isinstance(self.verify, bool):
            raise ValueError(f"`verify` must be true or false; got {self.verify!r}")
        require_int("", low=0, rounds=self.rounds, seed_start=self.seed_start, check_episodes=self.check_episodes,
                    check_seed_start=self.check_seed_start)
        for name in ("beta", "beta_decay"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"`{name}` must be in [0, 1]; got {getattr(self, name)!r}")
        labelled = range(self.seed_start, self.seed_start + (self.rounds + 1) * self.episodes)
        checked = range(self.check_seed_start, self.check_seed_start + self.check_episodes)
        if self.check_episodes and max(labelled.start, checked.start) < min(labelled.stop, checked.stop):
            raise ValueError(f"check seeds {checked.start}-{checked.stop - 1} overlap the labelled seeds "
                             f"{labelled.start}-{labelled.stop - 1}: the check must be held out")

    def beta_of(self, round_index: int) -> float:
        """The expert's share of the driving in round ``round_index`` (1 in round 0;
        :func:`mmpc.imitation.dagger_rounds.beta_of`)."""
        return beta_of(self.beta, self.beta_decay, round_index)

    def seeds_of(self, round_index: int) -> list[int]:
        first = self.seed_start + round_index * self.episodes
        return list(range(first, first + self.episodes))


def check_drive(scenario: ScenarioConfig, driver, seeds: list[int], lockstep: int) -> dict:
    """Collisions and mean meta cost of ``driver`` over ``seeds`` (lockstep groups of ``lockstep``)."""
    collisions, costs = 0, []
    for start in range(0, len(seeds), lockstep):
        for result in run_lockstep(scenario, seeds[start:start + lockstep], driver=driver):
            collisions += int(result.metrics["collisions"] > 0)
            costs.append(result.metrics["meta_cost_mean"])
    return {"collisions": collisions, "meta_cost_mean": float(np.mean(costs)), "episodes": len(seeds)}


def _best_round(rounds: list[dict]) -> int:
    """The round whose proposer had the fewest check collisions, then the lowest check meta cost
    (ties: the earlier round); the last round when the rounds carry no check."""
    return best_of(rounds, lambda e: (e["check"]["collisions"], e["check"]["meta_cost_mean"]) if "check" in e else None)


def _identity(scenario: ScenarioConfig, config: ProposerDaggerConfig) -> dict:
    """What a resumed run must match (``rounds`` may grow)."""
    settings = {key: value for key, value in to_dict(config).items() if key != "rounds"}
    return {"scenario": {k: v for k, v in to_dict(scenario).items() if k != "seeds"}, "config": settings}


def _read_report(path: Path, identity: dict) -> list[dict]:
    if not path.exists():
        return []
    try:
        report = json.loads(path.read_text())
        rounds = list(report["rounds"])
    except (ValueError, KeyError, TypeError) as error:
        raise ValueError(f"{path} is corrupt ({type(error).__name__}: {error}); remove the run folder or choose "
                         "another --out") from error
    recorded = report.get("identity")
    if isinstance(recorded, dict) and isinstance(recorded.get("config"), dict) and "verify" not in recorded["config"]:
        recorded = {**recorded, "config": {**recorded["config"], "verify": False}}  # labelled before the check existed
    if recorded != identity:
        raise ValueError(f"{path.parent} holds a proposer run of another configuration; re-run with the same scenario "
                         "and config to resume (a run labelled without the check: --set verify=false), or choose another --out")
    return rounds


def run_proposer_dagger(
    scenario: ScenarioConfig,
    out: Path,
    config: ProposerDaggerConfig = ProposerDaggerConfig(),
    *,
    on_round: Optional[Callable[[dict], None]] = None,
    on_progress: Optional[Callable[[int, int], None]] = None,
) -> dict:
    """Run (or resume) the proposer's DAgger (see the module docstring).

    Args:
        scenario: the scenario (``scenario.sim`` picks the world; the batched simulator for scale).
        out: the run folder.
        config: the settings.
        on_round: called with each finished round's entry of ``proposer.json``.
        on_progress: called as ``on_progress(finished, total)`` while a round's episodes get labelled.

    Returns:
        The content of ``proposer.json``.

    Raises:
        mmpc.files.OutputFolderError: ``out`` cannot be written, or another run holds it (its :data:`LOCK`).
        ValueError: ``out`` holds a run of another configuration, or a corrupt ``proposer.json``.
    """
    out = Path(out)
    with run_folder(out, LOCK, "another `mmpc imitate proposer` run"):
        return _run_rounds(scenario, out, config, on_round, on_progress)


def _run_rounds(scenario: ScenarioConfig, out: Path, config: ProposerDaggerConfig,
                on_round: Optional[Callable[[dict], None]], on_progress: Optional[Callable[[int, int], None]]) -> dict:
    """:func:`run_proposer_dagger` in the folder ``out``, whose lock this process holds."""
    from torch.utils.tensorboard import SummaryWriter

    identity = _identity(scenario, config)
    rounds = [entry for entry in _read_report(out / REPORT, identity) if entry["round"] <= config.rounds]
    name = "".join(c if c.isalnum() else "_" for c in scenario.name)
    scene = scene_geometry(scenario)
    check_seeds = list(range(config.check_seed_start, config.check_seed_start + config.check_episodes))
    expert_check = next((entry["expert_check"] for entry in rounds if "expert_check" in entry), None)
    # the labels so far, read once; each round adds its own (episode ids continue across rounds)
    resumed = 0 < len(rounds) <= config.rounds
    labels = read_labels([out / "labels" / f"round_{i}" for i in range(len(rounds))]) if resumed else None
    writer = SummaryWriter(str(out / "tb"))
    try:
        def play(index: int) -> dict:
            """One round: drive and label (the proposer of the round before in the loop), train, check."""
            nonlocal labels, expert_check
            proposer: Optional[ModeProposer] = load_proposer(out / f"round_{index - 1}" / "proposer.pt") if index else None
            beta = config.beta_of(index)
            report = label_episodes(
                scenario, config.seeds_of(index), out / "labels" / f"round_{index}", proposer=proposer, beta=beta,
                keep=config.train.keep, lockstep=config.lockstep, seed=index,
                dataset_id=f"mmpc/{name}-rankings-round{index}-v0", verify=config.verify, on_progress=on_progress,
            )
            first_episode = 0 if labels is None else int(labels.episodes.max()) + 1
            new = read_labels([out / "labels" / f"round_{index}"], first_episode=first_episode)
            labels = new if labels is None else RankingLabels.concatenate([labels, new])
            trained, history = train_proposer(labels, scenario.road, config.train, scene=scene, writer=writer,
                                              tag=f"round_{index}/")
            entry = {
                "round": index, "beta": beta, "episodes": config.episodes, "states": labels.num_states,
                "labelled_now": report.states,
                "labels_per_s": report.states / report.seconds if report.generated and report.seconds > 0 else None,
                "top_k_agreement": history.val_agreement[history.best_epoch],
                "feasible_recall": history.val_recall[history.best_epoch],
                "best_epoch": history.best_epoch,
            }
            save_proposer(out / f"round_{index}" / "proposer.pt", trained, scenario=scenario.name,
                          info={"keep": config.train.keep, "round": index, "states": labels.num_states})
            if check_seeds:
                driver = ProposerDriver(build_mpc(scenario), trained, keep=config.train.keep)
                entry["check"] = check_drive(scenario, behind_check(driver, scenario, config.verify), check_seeds,
                                             config.lockstep)
                entry["check"]["escalated_share"] = driver.escalated_rows / max(driver.decided_rows, 1)
                if expert_check is None:
                    expert = MPCDriver(build_mpc(scenario), period=scenario.period)
                    expert_check = check_drive(scenario, behind_check(expert, scenario, config.verify), check_seeds,
                                               config.lockstep)
                entry["expert_check"] = expert_check
                writer.add_scalar("check/collisions", entry["check"]["collisions"], labels.num_states)
                writer.add_scalar("check/meta_cost_mean", entry["check"]["meta_cost_mean"], labels.num_states)
            writer.add_scalar("labels/top_k_agreement", entry["top_k_agreement"], labels.num_states)
            writer.flush()
            return entry

        def record(rounds: list[dict]) -> None:
            best = _best_round(rounds)
            shutil.copyfile(out / f"round_{best}" / "proposer.pt", out / "proposer.pt")
            atomic_write_text(out / REPORT, json.dumps({"identity": identity, "rounds": rounds, "best_round": best},
                                                       indent=2) + "\n")

        run_rounds(rounds, config.rounds, play, record, on_round)
    finally:
        writer.close()
    return json.loads((out / REPORT).read_text())
