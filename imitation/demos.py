"""Expert demonstrations: the multi-modal MPC drives seeded episodes, each finished episode is
staged atomically, and a Minari dataset is built from them (``mmpc imitate demos``).

Episodes run in lockstep groups (one optimizer call per step for the group's episodes), mmpc's
one grouping rule (:func:`mmpc.evaluate.tasks.lockstep_groups`: seed // lockstep), so a resumed
run recomputes an unfinished group exactly as an uninterrupted run would. Groups are tasks of
mmpc's one worker pool (:func:`mmpc.evaluate.run_tasks`: in this process or in worker
processes, each with its own torch threads).

One run at a time writes a directory: a run holds the lock file :data:`LOCK` in it (as
``mmpc evaluate`` does, :func:`mmpc.files.exclusive`) and a second is refused.
"""

from __future__ import annotations

import contextlib
import logging
import signal
from pathlib import Path
from typing import Callable, Iterator, NamedTuple, Optional, Sequence

import torch

from mmpc.config import to_dict
from mmpc.drivers import MPCDriver
from mmpc.drivers.verified import behind_check
from mmpc.evaluate import Backend, run_tasks
from mmpc.evaluate.tasks import lockstep_groups
from mmpc.files import TEMPORARY_PREFIX, atomic_write, exclusive
from mmpc.imitation.dataset import (
    MANIFEST,
    DemonstrationsDir,
    DemonstrationsError,
    Manifest,
    build_minari,
    built_seeds,
    dataset_id,
    minari_dataset_path,
    package_versions,
    save_episode,
)
from mmpc.imitation.rollout import Rollout, rollout_lockstep
from mmpc.scenario import ScenarioConfig, build_mpc

logger = logging.getLogger(__name__)

#: The lock file a run holds in its demonstrations directory.
LOCK = ".demos.lock"


class DemosReport(NamedTuple):
    """What :func:`generate_demonstrations` did.

    Fields:
        dataset_path: the Minari dataset's folder (the one holding ``data/``).
        dataset_id: its Minari id.
        seeds: the dataset's episodes, in order.
        generated: seeds driven by this call.
        reused: seeds found staged by an earlier (interrupted) run.
        rebuilt: whether the Minari dataset was (re)written.
    """

    dataset_path: Path
    dataset_id: str
    seeds: list[int]
    generated: list[int]
    reused: list[int]
    rebuilt: bool


class DemoTask(NamedTuple):
    """One lockstep group of the expert's episodes (a task of :func:`mmpc.evaluate.run_tasks`).

    Fields:
        scenario: the scenario.
        seeds: every seed of the group (all are driven: they share the optimizer batches).
        missing: the seeds to write (the others are staged already).
        episodes_dir: the staging folder.
        expert: who drives (:attr:`mmpc.imitation.dataset.Manifest.expert`).
    """

    scenario: ScenarioConfig
    seeds: tuple[int, ...]
    missing: tuple[int, ...]
    episodes_dir: Path
    expert: str = "verified:mpc"

    @property
    def label(self) -> str:
        return f"demonstrations {self.scenario.name} seeds {self.seeds[0]}-{self.seeds[-1]}"


def drive_group(task: DemoTask) -> list[int]:
    """Drive one group with the scenario's MPC (behind the check for ``verified:mpc``) and stage
    the episodes of ``task.missing``; returns the seeds written."""
    wanted = set(task.missing)
    written: list[int] = []

    def stage(rollout: Rollout) -> None:
        if rollout.episode.seed in wanted:
            save_episode(task.episodes_dir / f"seed_{rollout.episode.seed:06d}.npz", rollout.episode)
            written.append(rollout.episode.seed)

    with torch.inference_mode():
        expert = behind_check(MPCDriver(build_mpc(task.scenario), period=task.scenario.period), task.scenario,
                              task.expert == "verified:mpc")
        rollout_lockstep(task.scenario, task.seeds, expert, on_finished=stage)
    return written


def _group_failed(task: DemoTask, error: BaseException | str) -> list[int]:
    if isinstance(error, BaseException):
        raise error
    raise RuntimeError(f"{task.label}: {error}")


@contextlib.contextmanager
def locked_directory(root: Path, manifest: Manifest,
                     holder: str = "another `mmpc imitate demos` run") -> Iterator[DemonstrationsDir]:
    """``root`` (created when missing) opened as a :class:`DemonstrationsDir` while this process
    holds its :data:`LOCK`; another run holding it raises :class:`DemonstrationsError` naming
    ``holder``. (Also the staging of the proposer's ranking labels, :mod:`mmpc.imitation.labels`.)"""
    ours = (root / MANIFEST).exists() or (root / LOCK).exists()
    if root.exists() and (not root.is_dir() or not ours and any(root.iterdir())):
        DemonstrationsDir(root, manifest)  # not a demonstrations directory: refused before a lock file goes in
    root.mkdir(parents=True, exist_ok=True)
    with exclusive(root, LOCK, holder, DemonstrationsError):
        entries = list(root.iterdir())
        if not (root / MANIFEST).exists() and all(p.name == LOCK or p.name.startswith(TEMPORARY_PREFIX) for p in entries):
            # new but for the lock, which DemonstrationsDir would take for foreign content: give it the manifest
            for stale in (p for p in entries if p.name != LOCK):  # left by a run killed writing the manifest
                stale.unlink()
            atomic_write(root / MANIFEST, lambda handle: handle.write(manifest.to_json().encode()))
        yield DemonstrationsDir(root, manifest)


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Let SIGTERM stop generation like Ctrl-C (KeyboardInterrupt), so the same cleanup runs."""
    def handler(signum, frame):
        raise KeyboardInterrupt(f"signal {signum}")

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread: leave signals alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def generate_demonstrations(
    scenario: ScenarioConfig,
    seeds: Sequence[int],
    out: Path,
    *,
    workers: int = 1,
    lockstep: int = 4,
    threads: int = 1,
    expert: str = "verified:mpc",
    on_progress: Optional[Callable[[int, int], None]] = None,
) -> DemosReport:
    """Drive the expert over ``seeds``, stage every episode, build the Minari dataset.

    Re-running with the same arguments after an interruption keeps the staged episodes and
    drives only the unfinished groups; the dataset is rebuilt to hold each requested episode
    once, in the order of ``seeds``.

    Args:
        scenario: the scenario (its duration sets the episode length).
        seeds: the episodes' seeds (distinct).
        out: the demonstrations directory (see :mod:`mmpc.imitation.dataset`).
        workers: parallel processes (1: in this process).
        lockstep: the grouping of the episodes (part of the directory's identity).
        threads: torch threads per worker.
        expert: ``"verified:mpc"``, the MPC behind the check (:mod:`mmpc.verify`: every recorded
            action keeps a verified way out), or ``"mpc"``, the MPC alone (part of the directory's
            identity and the dataset's metadata, ``mmpc_expert``).
        on_progress: called as ``on_progress(finished, total)`` while episodes get staged.

    Returns:
        A :class:`DemosReport`.

    Raises:
        mmpc.imitation.dataset.DemonstrationsError: ``out`` is foreign or corrupt, holds
            another configuration's episodes, or another run holds its :data:`LOCK`.
        KeyboardInterrupt: interrupted (SIGINT or SIGTERM); finished episodes stay staged.
    """
    seeds = [int(s) for s in seeds]
    if not seeds or len(set(seeds)) != len(seeds) or min(seeds) < 0:
        raise ValueError(f"`seeds` must be distinct non-negative ints, at least one; got {seeds[:10]}")
    if workers < 1 or lockstep < 1 or threads < 1:
        raise ValueError(f"`workers`, `lockstep` and `threads` must be >= 1; got {workers}, {lockstep}, {threads}")
    manifest = Manifest(to_dict(scenario), lockstep, package_versions(), expert)  # refuses an unknown expert
    with locked_directory(Path(out), manifest) as directory:
        staged = directory.finished_seeds()
        reused = [s for s in seeds if s in staged]
        tasks = [DemoTask(scenario, tuple(group), tuple(s for s in group if s not in staged), directory.episodes_dir, expert)
                 for group in lockstep_groups(seeds, lockstep).values()]
        tasks = [task for task in tasks if task.missing]
        total = len(seeds)

        def progress() -> None:
            if on_progress is not None:
                on_progress(len(set(seeds) & directory.finished_seeds()), total)

        progress()
        generated: list[int] = []
        with sigterm_as_interrupt():
            for _, written in run_tasks(tasks, drive_group, _group_failed, Backend(min(workers, max(len(tasks), 1)), threads)):
                generated += written
                progress()
        progress()
        identifier = dataset_id(scenario)
        rebuilt = built_seeds(directory.root, identifier) != seeds
        if rebuilt:
            build_minari(directory, scenario, seeds)
        logger.info("demonstrations in %s: %d episodes (%d driven now, %d reused)", out, total, len(generated),
                    len(reused))
        return DemosReport(minari_dataset_path(directory.root, identifier), identifier, seeds, sorted(generated), reused,
                           rebuilt)
