"""The evaluation's tasks: per (driver, scenario) the unfinished seeds grouped by ``seed //
lockstep``; a group is one task, driven in lockstep by :func:`mmpc.highway.run_lockstep` and
returned as one :data:`~mmpc.evaluate.store.COLUMNS` row per seed."""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple, Optional, Sequence

from mmpc.config import require_int
from mmpc.drivers import check_spec, make_driver
from mmpc.evaluate.backends import Backend, error_text, worker_name
from mmpc.evaluate.store import Key, new_row
from mmpc.files import file_slug
from mmpc.highway.runner import EpisodeResult, run_episode, run_lockstep, write_outputs
from mmpc.scenario import ScenarioConfig

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class EvaluationConfig:
    """What to run and how.

    Attributes:
        drivers: driver specs (:func:`mmpc.drivers.make_driver`: ``mpc``, ``frenet``,
            ``bc:RUN/policy.pt``, ...), distinct.
        seeds: episode seeds, the same for every driver and scenario; distinct, >= 0.
        workers: tasks in flight at once: 1 runs them in this process, more in a pool of that
            many worker processes; with ``ray``: ``None`` takes the cluster's CPU count.
        threads: torch threads of every task.
        lockstep: seeds per group (one task; driven in lockstep). Groups are ``seed //
            lockstep``, so results do not depend on ``workers`` or the backend. A resume may
            change it (see the module docstring).
        ray: ``None`` (this machine), ``"local"`` (start a local Ray with ``workers`` CPUs),
            ``"auto"`` or a cluster address (``"host:6379"``, ``"ray://host:10001"``). A Ray
            already initialised in this process is used as it is.
        retries: how many more times a task in flight when its worker died is run (alone)
            before its episodes become error rows.
        episode_layout: write each episode's ``metrics.json``, ``steps.csv`` and
            ``topdown.png`` into ``out / episode_layout.format(driver=..., scenario=...,
            seed=...)`` (``driver`` with characters other than letters, digits, ``.-_``
            replaced by ``_``); ``None``: no per-episode folders. On a Ray cluster the folders
            land where the task ran, so they need a shared file system.
        collision_videos: with ``episode_layout``: replay each episode that ended in a
            collision alone with a video (``episode.mp4``); identical to the evaluated episode
            for ``lockstep == 1``, up to floating-point rounding otherwise.
        report: write ``summary.md``, ``compare.png`` and the TensorBoard scalars.
    """

    drivers: tuple[str, ...] = ("mpc",)
    seeds: tuple[int, ...] = tuple(range(20))
    workers: Optional[int] = 1
    threads: int = 1
    lockstep: int = 1
    ray: Optional[str] = None
    retries: int = 1
    episode_layout: Optional[str] = None
    collision_videos: bool = False
    report: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.drivers, tuple) or not self.drivers or not all(isinstance(d, str) and d for d in self.drivers):
            raise ValueError(f"`drivers` must be a non-empty tuple of driver specs such as ('mpc',); got {self.drivers!r}")
        if len(set(self.drivers)) != len(self.drivers):
            raise ValueError(f"`drivers` must be distinct; got {self.drivers}")
        for spec in self.drivers:
            check_spec(spec)
        if (not isinstance(self.seeds, tuple) or not self.seeds
                or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in self.seeds)):
            raise ValueError(f"`seeds` must be a non-empty tuple of ints >= 0; got {self.seeds!r}")
        if len(set(self.seeds)) != len(self.seeds):
            raise ValueError(f"`seeds` must be distinct; got {len(self.seeds)} seeds, {len(set(self.seeds))} distinct")
        require_int("", low=1, lockstep=self.lockstep)
        self.backend  # validates workers, threads, ray and retries
        if self.episode_layout is not None:
            try:
                self.episode_layout.format(driver="d", scenario="s", seed=0)
            except (KeyError, IndexError, ValueError) as error:
                raise ValueError(f"`episode_layout` may use {{driver}}, {{scenario}}, {{seed}}; got {self.episode_layout!r}") from error
        if self.collision_videos and self.episode_layout is None:
            raise ValueError("`collision_videos` needs `episode_layout` (the folder the video goes into)")

    @property
    def backend(self) -> Backend:
        """Where the groups run."""
        return Backend(self.workers, self.threads, self.ray, self.retries)


class GroupTask(NamedTuple):
    """One task: a group of seeds of one driver and scenario, driven in lockstep.

    Fields:
        driver: driver spec.
        scenario: the scenario.
        seeds: the group's seeds (those of group ``group`` not finished yet).
        group: ``seed // lockstep``.
        threads: torch threads while it runs.
        out: evaluation folder for per-episode outputs (``None``: none).
        episode_layout: see :class:`EvaluationConfig`.
        collision_videos: see :class:`EvaluationConfig`.
    """

    driver: str
    scenario: ScenarioConfig
    seeds: tuple[int, ...]
    group: int
    threads: int = 1
    out: Optional[str] = None
    episode_layout: Optional[str] = None
    collision_videos: bool = False

    @property
    def label(self) -> str:
        """The task in messages."""
        return f"{self.driver} / {self.scenario.name} group {self.group}"


def episode_dir(out: Path, layout: str, driver: str, scenario: str, seed: int) -> Path:
    """Folder of one episode's outputs (see :attr:`EvaluationConfig.episode_layout`)."""
    return Path(out) / layout.format(driver=file_slug(driver), scenario=scenario, seed=seed)


def error_rows(task: GroupTask, error: BaseException | str, wall_s: float = float("nan")) -> list[dict]:
    """Error rows for every seed of ``task``."""
    text = error if isinstance(error, str) else error_text(error)
    return [
        new_row(driver=task.driver, scenario=task.scenario.name, seed=seed, status="error", error=text, group=task.group,
                group_size=len(task.seeds), worker=worker_name(), wall_s=wall_s)
        for seed in task.seeds
    ]


def _per_episode_solve_ms(results: Sequence[EpisodeResult]) -> list[float]:
    """Each episode's mean over its steps of ``solve_ms / active``: a lockstep decision served
    ``active`` episodes (those with a record at that step)."""
    lengths = [len(result.records) for result in results]
    shares = []
    for result in results:
        values = [r.solve_ms / sum(length > r.step for length in lengths) for r in result.records]
        shares.append(sum(values) / len(values))
    return shares


def _write_episode(task: GroupTask, result: EpisodeResult) -> None:
    """Per-episode outputs, written into a temporary folder and renamed into place."""
    target = episode_dir(Path(task.out), task.episode_layout, task.driver, task.scenario.name, result.seed)
    staging = target.with_name(f".{target.name}.tmp-{os.getpid()}")
    shutil.rmtree(staging, ignore_errors=True)
    write_outputs(result, staging)
    if task.collision_videos and result.metrics["collisions"]:
        with contextlib.closing(make_driver(task.driver, task.scenario)) as driver:
            run_episode(task.scenario, result.seed, driver=driver, video=staging / "episode.mp4")
    shutil.rmtree(target, ignore_errors=True)
    os.replace(staging, target)


def run_group(task: GroupTask) -> list[dict]:
    """Run one task: its seeds in lockstep with a driver built for it; one row per seed.

    Never raises for a failing episode: when the group raises, its seeds are run again one at a
    time and the ones that still raise become error rows (``status == "error"``).

    Returns:
        One row per seed, in the order of ``task.seeds``, with :data:`COLUMNS` keys.
    """
    start = time.perf_counter()
    try:
        with contextlib.closing(make_driver(task.driver, task.scenario)) as driver:
            results = run_lockstep(task.scenario, task.seeds, driver=driver)
        if task.episode_layout is not None:
            for result in results:
                _write_episode(task, result)
    except Exception as error:  # noqa: BLE001 - any driver or simulator failure is an error row
        if len(task.seeds) == 1:
            logger.warning("%s / %s seed %d failed: %s", task.driver, task.scenario.name, task.seeds[0], error_text(error))
            return error_rows(task, error, time.perf_counter() - start)
        logger.warning("%s / %s group %d failed (%s); running its %d seeds one at a time", task.driver,
                       task.scenario.name, task.group, error_text(error), len(task.seeds))
        return [row for seed in task.seeds for row in run_group(task._replace(seeds=(seed,)))]
    wall_s = time.perf_counter() - start
    rows = []
    for result, share in zip(results, _per_episode_solve_ms(results)):
        rows.append(new_row(**{**result.metrics, "driver": task.driver, "status": "ok", "error": "", "group": task.group,
                               "group_size": len(task.seeds), "worker": worker_name(), "wall_s": wall_s,
                               "solve_ms_per_episode_mean": share}))
    return rows


def lockstep_groups(seeds: Sequence[int], lockstep: int) -> dict[int, list[int]]:
    """mmpc's one seed-grouping rule: group ``seed // lockstep`` -> its seeds (groups in order of
    their first seed in ``seeds``). A group always has the same members, so a resumed run drives
    an unfinished group exactly as an uninterrupted run would (lockstep batches round
    differently from single solves, so membership matters)."""
    require_int("", low=1, lockstep=lockstep)
    groups: dict[int, list[int]] = {}
    for seed in seeds:
        groups.setdefault(seed // lockstep, []).append(seed)
    return groups


def plan_tasks(
    scenarios: Sequence[ScenarioConfig], config: EvaluationConfig, finished: set[Key], out: Optional[Path] = None,
) -> list[GroupTask]:
    """The tasks still to run: per driver and scenario, the unfinished seeds grouped by
    ``seed // lockstep`` (groups in order of their first seed in ``config.seeds``)."""
    tasks = []
    for driver in config.drivers:
        for scenario in scenarios:
            unfinished = [seed for seed in config.seeds if (driver, scenario.name, seed) not in finished]
            for group, seeds in lockstep_groups(unfinished, config.lockstep).items():
                tasks.append(GroupTask(driver, scenario, tuple(seeds), group, config.threads,
                                       None if config.episode_layout is None else str(out), config.episode_layout,
                                       config.collision_videos))
    return tasks
