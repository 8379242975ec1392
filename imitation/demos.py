"""Expert demonstrations: the multi-modal MPC drives seeded episodes, each finished episode is
staged atomically, and a Minari dataset is built from them (``mmpc imitate demos``).

Episodes run in lockstep chunks (one optimizer call per step for the chunk's episodes); chunk
k holds the requested seeds ``s`` with ``s // lockstep == k``, so a chunk always has the same
members and a resumed run recomputes an unfinished chunk exactly as an uninterrupted run
would (lockstep batches round differently from single solves, so membership matters). Chunks
run in parallel worker processes, each with its own torch threads.

One run at a time writes a directory: a run holds the lock file :data:`LOCK` in it (as
``mmpc evaluate`` does, :func:`mmpc.files.exclusive`) and a second is refused.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import signal
import time
from pathlib import Path
from typing import Callable, Iterator, NamedTuple, Optional, Sequence

import torch

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
from mmpc.scenario import ScenarioConfig

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


def chunks(seeds: Sequence[int], lockstep: int) -> list[list[int]]:
    """Group ``seeds`` by ``seed // lockstep`` (in order of first appearance)."""
    groups: dict[int, list[int]] = {}
    for seed in seeds:
        groups.setdefault(seed // lockstep, []).append(seed)
    return list(groups.values())


def _worker_init(threads: int) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles interrupts and terminates the pool
    torch.set_num_threads(threads)


def drive_chunk(scenario: ScenarioConfig, seeds: Sequence[int], missing: Sequence[int], episodes_dir: Path) -> list[int]:
    """Drive one lockstep chunk with the scenario's MPC and stage the episodes of ``missing``.

    Args:
        scenario: the scenario.
        seeds: every seed of the chunk (all are driven: they share the optimizer batches).
        missing: the seeds to write (the others are staged already).
        episodes_dir: the staging folder.

    Returns:
        The seeds written.
    """
    from mmpc.drivers import MPCDriver
    from mmpc.imitation.rollout import rollout_lockstep
    from mmpc.scenario import build_mpc

    wanted = set(missing)
    written: list[int] = []

    def stage(rollout) -> None:
        if rollout.episode.seed in wanted:
            save_episode(episodes_dir / f"seed_{rollout.episode.seed:06d}.npz", rollout.episode)
            written.append(rollout.episode.seed)

    with torch.inference_mode():
        rollout_lockstep(scenario, seeds, MPCDriver(build_mpc(scenario)), on_finished=stage)
    return written


@contextlib.contextmanager
def _locked_directory(root: Path, manifest: Manifest) -> Iterator[DemonstrationsDir]:
    """``root`` (created when missing) opened as a :class:`DemonstrationsDir` while this process
    holds its :data:`LOCK`; another run holding it raises :class:`DemonstrationsError`."""
    ours = (root / MANIFEST).exists() or (root / LOCK).exists()
    if root.exists() and (not root.is_dir() or not ours and any(root.iterdir())):
        DemonstrationsDir(root, manifest)  # not a demonstrations directory: refused before a lock file goes in
    root.mkdir(parents=True, exist_ok=True)
    with exclusive(root, LOCK, "another `mmpc imitate demos` run", DemonstrationsError):
        entries = list(root.iterdir())
        if not (root / MANIFEST).exists() and all(p.name == LOCK or p.name.startswith(TEMPORARY_PREFIX) for p in entries):
            # new but for the lock, which DemonstrationsDir would take for foreign content: give it the manifest
            for stale in (p for p in entries if p.name != LOCK):  # left by a run killed writing the manifest
                stale.unlink()
            atomic_write(root / MANIFEST, lambda handle: handle.write(manifest.to_json().encode()))
        yield DemonstrationsDir(root, manifest)


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
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
    on_progress: Optional[Callable[[int, int], None]] = None,
) -> DemosReport:
    """Drive the expert over ``seeds``, stage every episode, build the Minari dataset.

    Re-running with the same arguments after an interruption keeps the staged episodes and
    drives only the unfinished chunks; the dataset is rebuilt to hold each requested episode
    once, in the order of ``seeds``.

    Args:
        scenario: the scenario (its duration sets the episode length).
        seeds: the episodes' seeds (distinct).
        out: the demonstrations directory (see :mod:`mmpc.imitation.dataset`).
        workers: parallel processes (1: in this process).
        lockstep: episodes per lockstep chunk (part of the directory's identity).
        threads: torch threads per worker.
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
    with _locked_directory(Path(out), Manifest(scenario.to_dict(), lockstep, package_versions())) as directory:
        staged = directory.finished_seeds()
        reused = [s for s in seeds if s in staged]
        jobs = [(chunk, [s for s in chunk if s not in staged]) for chunk in chunks(seeds, lockstep)]
        jobs = [(chunk, missing) for chunk, missing in jobs if missing]
        total = len(seeds)

        def progress() -> None:
            if on_progress is not None:
                on_progress(len(set(seeds) & directory.finished_seeds()), total)

        progress()
        generated: list[int] = []
        with _sigterm_as_interrupt():
            if workers == 1 or len(jobs) <= 1:
                for chunk, missing in jobs:
                    generated += drive_chunk(scenario, chunk, missing, directory.episodes_dir)
                    progress()
            elif jobs:
                pool = multiprocessing.get_context("spawn").Pool(min(workers, len(jobs)), _worker_init, (threads,))
                try:
                    pending = [pool.apply_async(drive_chunk, (scenario, chunk, missing, directory.episodes_dir))
                               for chunk, missing in jobs]
                    while pending:
                        time.sleep(0.5)
                        progress()
                        for result in [r for r in pending if r.ready()]:
                            generated += result.get()
                            pending.remove(result)
                    pool.close()
                except BaseException:
                    pool.terminate()  # workers may be mid-episode; their partial files never got renamed
                    raise
                finally:
                    pool.join()
        progress()
        identifier = dataset_id(scenario)
        rebuilt = built_seeds(directory.root, identifier) != seeds
        if rebuilt:
            build_minari(directory, scenario, seeds)
        logger.info("demonstrations in %s: %d episodes (%d driven now, %d reused)", out, total, len(generated),
                    len(reused))
        return DemosReport(minari_dataset_path(directory.root, identifier), identifier, seeds, sorted(generated), reused,
                           rebuilt)
