"""Batch offline evaluation: drivers x scenarios x seeds, on this machine or a Ray cluster.

Every (driver, scenario, seed) is one closed-loop episode, fixed by those three. Episodes run in
*groups*: the seeds of a (driver, scenario) are split into fixed groups by ``seed // lockstep``
and a group's episodes are driven in lockstep (:func:`mmpc.drive.run_lockstep`), one driver
call per control step for all of them (for the MPC: one optimizer call over all their goal
batches). The groups depend on the seeds and ``lockstep`` only, never on the backend or the
number of workers, so the same call gives the same per-episode results locally and on Ray.

A group is one task. Tasks run in this process (``workers == 1``), in a pool of worker
processes, or as Ray tasks (``ray=...``); only this (coordinating) process writes the results:

- ``episodes.csv``: one row per episode (:data:`COLUMNS`), appended and fsync'ed as each group
  finishes. ``status`` is ``ok`` or ``error`` (the exception in ``error``).
- ``summary.json``: per driver x scenario the counts and means with 95 % confidence intervals
  (:func:`mmpc.evaluate_report.summarize`); with ``report``: ``summary.md``, ``compare.png``
  and TensorBoard scalars under ``tensorboard/`` (:mod:`mmpc.evaluate_report`).

Resuming: a second call with the same ``out`` skips the (driver, scenario, seed) keys already
``ok`` and re-runs the error and missing ones; the file is rewritten (temp file + rename)
without the rows being re-run, so no key appears twice. A worker process that dies takes its
pool down; the groups that were in flight are run again one at a time, so the one that kills
its worker is found and, after ``retries`` further deaths, written as error rows; the run goes
on. An episode that raises is an error row: a failing group is re-run one seed at a time so
only the failing episodes are errors.

A resumed call may use another ``lockstep`` (and other seeds): done is decided per key, and
each row records the ``group`` and ``group_size`` it was driven in. Group membership changes an
episode only through the rounding of the batched solves, and a resume with the same
``lockstep`` drives other groups too (error rows retried apart from their group's finished
seeds, seeds added to a group later), so refusing a new ``lockstep`` would not make a resumed
evaluation equal an uninterrupted one; ``summary.json`` names this call's ``lockstep``, the rows
their groups.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import logging
import multiprocessing
import os
import shutil
import socket
import time
from collections import deque
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, NamedTuple, Optional, Sequence

import torch

from mmpc.drive import EpisodeResult, run_episode, run_lockstep, write_outputs
from mmpc.drivers import DRIVERS, driver_names, make_driver
from mmpc.evaluate_report import format_table, summarize, write_report
from mmpc.files import atomic_write_text, exclusive
from mmpc.scenario import ScenarioConfig

__all__ = [
    "COLUMNS", "Evaluation", "EvaluationConfig", "EvaluationFolderError", "GroupTask", "evaluate",
    "format_table", "read_episodes", "run_group", "summarize",
]

logger = logging.getLogger(__name__)

#: An episode's identity.
KEY_COLUMNS = ("driver", "scenario", "seed")
#: How it ran: ``status`` ok/error, ``error`` the exception, ``group`` (= seed // lockstep) and
#: ``group_size`` (episodes driven together), ``worker`` (host:pid), ``wall_s`` (the group's
#: wall time [s]).
RUN_COLUMNS = ("status", "error", "group", "group_size", "worker", "wall_s")
#: The episode metrics (:func:`mmpc.metrics.episode_metrics`; empty where a scenario has none),
#: plus ``solve_ms_per_episode_mean``: each decision's time divided by the episodes it served.
METRIC_COLUMNS = (
    "steps", "duration", "collisions", "offroad", "mean_speed", "meta_cost_mean", "meta_cost_max", "plan_cost_mean",
    "speed_residual_mean", "right_lane_distance_mean", "lin_acc_mean", "ang_acc_mean", "solve_ms_mean",
    "solve_ms_max", "solve_ms_per_episode_mean", "lane_changes", "fallback_steps", "min_clearance",
)
COLUMNS = KEY_COLUMNS + RUN_COLUMNS + METRIC_COLUMNS
_INT_COLUMNS = frozenset({"seed", "group", "group_size", "steps", "collisions", "offroad", "lane_changes", "fallback_steps"})
_TEXT_COLUMNS = frozenset({"driver", "scenario", "status", "error", "worker"})

Key = tuple[str, str, int]


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
            if spec.partition(":")[0] not in DRIVERS:
                raise ValueError(f"unknown driver {spec.partition(':')[0]!r} in `drivers` {self.drivers}; expected one of "
                                 f"{driver_names()}")
        if (not isinstance(self.seeds, tuple) or not self.seeds
                or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in self.seeds)):
            raise ValueError(f"`seeds` must be a non-empty tuple of ints >= 0; got {self.seeds!r}")
        if len(set(self.seeds)) != len(self.seeds):
            raise ValueError(f"`seeds` must be distinct; got {len(self.seeds)} seeds, {len(set(self.seeds))} distinct")
        if self.workers is None and self.ray is None:
            raise ValueError("`workers` may be None (the cluster's CPUs) only with `ray`; got workers=None, ray=None")
        for name in ("workers", "threads", "lockstep"):
            value = getattr(self, name)
            if value is not None and (not isinstance(value, int) or value < 1):
                raise ValueError(f"`{name}` must be an int >= 1; got {value!r}")
        if not isinstance(self.retries, int) or self.retries < 0:
            raise ValueError(f"`retries` must be an int >= 0; got {self.retries!r}")
        if self.ray is not None and (not isinstance(self.ray, str) or not self.ray):
            raise ValueError(f"`ray` must be None, 'local', 'auto' or a cluster address; got {self.ray!r}")
        if self.episode_layout is not None:
            try:
                self.episode_layout.format(driver="d", scenario="s", seed=0)
            except (KeyError, IndexError, ValueError) as error:
                raise ValueError(f"`episode_layout` may use {{driver}}, {{scenario}}, {{seed}}; got {self.episode_layout!r}") from error
        if self.collision_videos and self.episode_layout is None:
            raise ValueError("`collision_videos` needs `episode_layout` (the folder the video goes into)")


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


class Evaluation(NamedTuple):
    """What :func:`evaluate` returns.

    Fields:
        rows: one row per requested episode (:data:`COLUMNS`), ordered driver, scenario, seed.
        summary: :func:`mmpc.evaluate_report.summarize` of ``rows``.
    """

    rows: list[dict]
    summary: list[dict]


# ----------------------------------------------------------------------------------- one task


def driver_slug(driver: str) -> str:
    """A driver spec as a file name: characters other than letters, digits and ``.-_`` -> ``_``."""
    return "".join(c if c.isalnum() or c in ".-_" else "_" for c in driver)


def episode_dir(out: Path, layout: str, driver: str, scenario: str, seed: int) -> Path:
    """Folder of one episode's outputs (see :attr:`EvaluationConfig.episode_layout`)."""
    return Path(out) / layout.format(driver=driver_slug(driver), scenario=scenario, seed=seed)


def _worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def _error_text(error: BaseException) -> str:
    text = f"{type(error).__name__}: {error}".replace("\n", " ").replace("\r", " ")
    return text[:500]


def error_rows(task: GroupTask, error: BaseException | str, wall_s: float = float("nan")) -> list[dict]:
    """Error rows for every seed of ``task``."""
    text = error if isinstance(error, str) else _error_text(error)
    return [
        _row(driver=task.driver, scenario=task.scenario.name, seed=seed, status="error", error=text, group=task.group,
             group_size=len(task.seeds), worker=_worker_name(), wall_s=wall_s)
        for seed in task.seeds
    ]


def _row(**values: object) -> dict:
    """A row with every one of :data:`COLUMNS`, in order (``None`` where not given)."""
    return {column: values.get(column) for column in COLUMNS}


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
        run_episode(task.scenario, result.seed, driver=make_driver(task.driver, task.scenario), video=staging / "episode.mp4")
    shutil.rmtree(target, ignore_errors=True)
    os.replace(staging, target)


def run_group(task: GroupTask) -> list[dict]:
    """Run one task: its seeds in lockstep with a driver built for it; one row per seed.

    Never raises for a failing episode: when the group raises, its seeds are run again one at a
    time and the ones that still raise become error rows (``status == "error"``).

    Returns:
        One row per seed, in the order of ``task.seeds``, with :data:`COLUMNS` keys.
    """
    previous = torch.get_num_threads()
    torch.set_num_threads(task.threads)
    start = time.perf_counter()
    try:
        results = run_lockstep(task.scenario, task.seeds, driver=make_driver(task.driver, task.scenario))
        if task.episode_layout is not None:
            for result in results:
                _write_episode(task, result)
    except Exception as error:  # noqa: BLE001 - any driver or simulator failure is an error row
        if len(task.seeds) == 1:
            logger.warning("%s / %s seed %d failed: %s", task.driver, task.scenario.name, task.seeds[0], _error_text(error))
            return error_rows(task, error, time.perf_counter() - start)
        logger.warning("%s / %s group %d failed (%s); running its %d seeds one at a time", task.driver,
                       task.scenario.name, task.group, _error_text(error), len(task.seeds))
        return [row for seed in task.seeds for row in run_group(task._replace(seeds=(seed,)))]
    finally:
        torch.set_num_threads(previous)
    wall_s = time.perf_counter() - start
    rows = []
    for result, share in zip(results, _per_episode_solve_ms(results)):
        rows.append(_row(**{**result.metrics, "driver": task.driver, "status": "ok", "error": "", "group": task.group,
                            "group_size": len(task.seeds), "worker": _worker_name(), "wall_s": wall_s,
                            "solve_ms_per_episode_mean": share}))
    return rows


# ----------------------------------------------------------------------------------- backends


def _init_worker(threads: int) -> None:
    torch.set_num_threads(threads)


def _in_process(tasks: Sequence[GroupTask]) -> Iterator[list[dict]]:
    for task in tasks:
        yield run_group(task)


def _process_pool(tasks: Sequence[GroupTask], workers: int, threads: int, retries: int) -> Iterator[list[dict]]:
    """Tasks in a pool of ``workers`` spawned processes, at most ``workers`` in flight.

    When a worker dies the pool breaks and every task in flight fails with it; the pool is
    recreated and those tasks (suspects) are run one at a time, alone, so a death then blames
    exactly one task: it is run again up to ``retries`` times, then written as error rows.
    """
    normal = deque(tasks)
    suspects: deque[GroupTask] = deque()
    deaths: dict[int, int] = {}  # id(task) -> deaths of its worker while it ran alone
    context = multiprocessing.get_context("spawn")
    while normal or suspects:
        pool = ProcessPoolExecutor(workers, mp_context=context, initializer=_init_worker, initargs=(threads,))
        running: dict[Future, GroupTask] = {}
        isolated = False  # the one task in flight is a suspect running alone
        try:
            while normal or suspects or running:
                if suspects:
                    if not running:
                        task = suspects.popleft()
                        running[pool.submit(run_group, task)] = task
                        isolated = True
                else:
                    isolated = False
                    while normal and len(running) < workers:
                        task = normal.popleft()
                        running[pool.submit(run_group, task)] = task
                done, _ = wait(running, return_when=FIRST_COMPLETED)
                broken = False
                for future in done:  # tasks that finished before a break keep their results
                    error = future.exception()
                    if isinstance(error, BrokenProcessPool):
                        broken = True
                        continue
                    task = running.pop(future)
                    yield error_rows(task, error) if error is not None else future.result()
                if broken:
                    raise BrokenProcessPool("a worker process died")
        except BrokenProcessPool:
            for task in running.values():
                if isolated:
                    deaths[id(task)] = deaths.get(id(task), 0) + 1
                    if deaths[id(task)] > retries:
                        logger.error("%s / %s group %d: its worker died %d times; recorded as errors", task.driver,
                                     task.scenario.name, task.group, deaths[id(task)])
                        yield error_rows(task, f"worker process died {deaths[id(task)]} times running this group")
                        continue
                logger.warning("%s / %s group %d: a worker process died; running the group again, alone", task.driver,
                               task.scenario.name, task.group)
                suspects.append(task)
        finally:
            pool.shutdown(wait=True, cancel_futures=True)


def _ray_tasks(tasks: Sequence[GroupTask], address: str, workers: Optional[int], retries: int) -> Iterator[list[dict]]:
    """Tasks as Ray tasks (1 CPU each), at most ``workers`` in flight; a task whose worker died
    is retried by Ray ``retries`` times, then its episodes are error rows."""
    try:
        import ray
    except ImportError as error:
        raise ImportError("`ray` evaluation needs Ray: pip install 'mmpc[ray]'") from error
    started = False
    if not ray.is_initialized():
        if address == "local":
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
        else:
            ray.init(address=address, log_to_driver=False)
        started = True
    try:
        if workers is None:
            workers = max(1, int(ray.cluster_resources().get("CPU", 1)))
        remote = ray.remote(num_cpus=1, max_retries=retries)(run_group)
        pending = deque(tasks)
        running: dict = {}
        while pending or running:
            while pending and len(running) < workers:
                task = pending.popleft()
                running[remote.remote(task)] = task
            done, _ = ray.wait(list(running), num_returns=1)
            for ref in done:
                task = running.pop(ref)
                try:
                    rows = ray.get(ref)
                except ray.exceptions.RayError as error:
                    logger.error("%s / %s group %d failed on Ray: %s", task.driver, task.scenario.name, task.group,
                                 _error_text(error))
                    rows = error_rows(task, error)
                yield rows
    finally:
        if started:
            ray.shutdown()


# ----------------------------------------------------------------------------------- the store


class EvaluationFolderError(ValueError):
    """An evaluation folder whose ``episodes.csv`` or ``scenarios.json`` cannot be resumed from
    (another format, a damaged line, episodes of another scenario of the same name)."""


#: What to do about a damaged line of ``episodes.csv``.
_DAMAGED_LINE = "fix or delete the line (a deleted episode is run again) or use another `out`"


def _parse(column: str, text: str, where: str) -> object:
    if column in _TEXT_COLUMNS:
        return text
    if text == "":
        return None
    try:
        return int(text) if column in _INT_COLUMNS else float(text)
    except ValueError:
        expected = "an integer" if column in _INT_COLUMNS else "a number"
        raise EvaluationFolderError(f"{where}: `{column}` is {text!r}, expected {expected}; {_DAMAGED_LINE}") from None


def read_episodes(path: Path) -> list[dict]:
    """The rows of an ``episodes.csv``, typed (ints, floats, ``None`` for empty cells).

    A last line without its newline (a write cut short by a killed process) is dropped.

    Raises:
        EvaluationFolderError: the header lacks a key column, or a line has another number of
            fields than the header, an empty key, a status other than ok/error or a value that
            does not parse; the message names the file and the line.
    """
    path = Path(path)
    if not path.exists():
        return []
    data = path.read_bytes()
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as error:
        line = data[:error.start].count(b"\n") + 1
        raise EvaluationFolderError(f"{path}, line {line}: not UTF-8 text ({error}); {_DAMAGED_LINE}") from error
    if text and not text.endswith("\n"):
        logger.warning("%s: dropping an incomplete last line (an interrupted write)", path)
        text = text[: text.rfind("\n") + 1]
    reader = csv.reader(io.StringIO(text))
    rows = []
    try:
        header = next(reader, [])
        missing = [c for c in KEY_COLUMNS + ("status",) if c not in header]
        if text and missing:
            raise EvaluationFolderError(f"{path} is not an evaluation's episodes.csv: columns {missing} missing; "
                                        "use another `out`")
        for fields in reader:
            if not fields:  # a blank line
                continue
            where = f"{path}, line {reader.line_num}"
            if len(fields) != len(header):
                raise EvaluationFolderError(f"{where}: {len(fields)} fields, expected {len(header)} (the header's); "
                                            f"{_DAMAGED_LINE}")
            values = dict(zip(header, fields))
            row = {column: _parse(column, values.get(column, ""), where) for column in COLUMNS}
            if not row["driver"] or not row["scenario"] or row["seed"] is None or row["status"] not in ("ok", "error"):
                raise EvaluationFolderError(
                    f"{where}: expected a driver, a scenario, a seed and status ok or error; got "
                    f"driver={row['driver']!r}, scenario={row['scenario']!r}, seed={row['seed']!r}, "
                    f"status={row['status']!r}; {_DAMAGED_LINE}")
            rows.append(row)
    except csv.Error as error:  # e.g. a NUL byte, as a crash can leave
        raise EvaluationFolderError(f"{path}, line {reader.line_num}: {error}; {_DAMAGED_LINE}") from error
    return rows


def _csv_lines(rows: Sequence[dict]) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=COLUMNS, extrasaction="ignore", lineterminator="\n")
    for row in rows:
        writer.writerow({column: "" if row.get(column) is None else row[column] for column in COLUMNS})
    return buffer.getvalue()


class _EpisodeFile:
    """``episodes.csv``, written by the coordinating process only: rewritten atomically at the
    start of a run, then appended to (one write + fsync per finished group)."""

    def __init__(self, path: Path, rows: Sequence[dict]) -> None:
        self.path = path
        atomic_write_text(path, ",".join(COLUMNS) + "\n" + _csv_lines(rows))
        self._handle = open(path, "a", encoding="utf-8", newline="")

    def append(self, rows: Sequence[dict]) -> None:
        self._handle.write(_csv_lines(rows))
        self._handle.flush()
        os.fsync(self._handle.fileno())

    def close(self) -> None:
        self._handle.close()


#: What to do about a damaged ``scenarios.json``.
_CORRUPT_SCENARIOS = ("delete it only if the episodes in this folder were run with the scenarios as they are now; "
                      "otherwise use another `out`")


def scenario_fingerprint(scenario: ScenarioConfig) -> str:
    """A short hash of every setting of a scenario (:meth:`ScenarioConfig.to_dict`)."""
    return hashlib.sha256(json.dumps(scenario.to_dict(), sort_keys=True).encode()).hexdigest()[:16]


def _check_scenarios(out: Path, scenarios: Sequence[ScenarioConfig]) -> None:
    """Refuse to mix episodes of two different scenarios under one name in ``out``."""
    path = out / "scenarios.json"
    known: dict[str, str] = {}
    if path.exists():
        try:
            known = json.loads(path.read_text(encoding="utf-8"))
        except ValueError as error:  # JSONDecodeError names the line and column; UnicodeDecodeError the byte
            raise EvaluationFolderError(f"{path} is corrupt ({error}); expected the JSON object of scenario name -> "
                                        f"settings hash this folder's episodes were run with; {_CORRUPT_SCENARIOS}") from error
        if not isinstance(known, dict) or not all(isinstance(v, str) for v in known.values()):
            raise EvaluationFolderError(f"{path} is corrupt: expected a JSON object of scenario name -> settings hash; "
                                        f"got {str(known)[:100]}; {_CORRUPT_SCENARIOS}")
    for scenario in scenarios:
        fingerprint = scenario_fingerprint(scenario)
        if known.setdefault(scenario.name, fingerprint) != fingerprint:
            raise EvaluationFolderError(
                f"{out} holds episodes of another scenario named {scenario.name!r} (settings changed, e.g. --duration or "
                f"--set); use another `out` or rename the scenario (--set name=...)"
            )
    atomic_write_text(path, json.dumps(known, indent=2) + "\n")


# ----------------------------------------------------------------------------------- evaluate


def plan_tasks(
    scenarios: Sequence[ScenarioConfig], config: EvaluationConfig, finished: set[Key], out: Optional[Path] = None,
) -> list[GroupTask]:
    """The tasks still to run: per driver and scenario, the unfinished seeds grouped by
    ``seed // lockstep`` (groups in order of their first seed in ``config.seeds``)."""
    tasks = []
    for driver in config.drivers:
        for scenario in scenarios:
            groups: dict[int, list[int]] = {}
            for seed in config.seeds:
                if (driver, scenario.name, seed) not in finished:
                    groups.setdefault(seed // config.lockstep, []).append(seed)
            for group, seeds in groups.items():
                tasks.append(GroupTask(driver, scenario, tuple(seeds), group, config.threads,
                                       None if config.episode_layout is None else str(out), config.episode_layout,
                                       config.collision_videos))
    return tasks


def evaluate(
    scenarios: Sequence[ScenarioConfig],
    out: Path,
    config: EvaluationConfig = EvaluationConfig(),
    *,
    on_episode: Optional[Callable[[dict], None]] = None,
) -> Evaluation:
    """Run every (driver, scenario, seed) episode not yet finished in ``out``; write
    ``episodes.csv``, ``summary.json`` and (``config.report``) the report.

    Args:
        scenarios: scenarios, distinct names (they key the rows).
        out: output folder; holding an earlier run of the same scenarios, that run is resumed.
        config: drivers, seeds, backend and outputs.
        on_episode: called in this process with each new row (finished or error) as it is
            written (e.g. a progress bar).

    Returns:
        An :class:`Evaluation`: the rows of all requested episodes (this run's and earlier
        ones') and their summary.

    Raises:
        ValueError: duplicate scenario names.
        EvaluationFolderError (a ValueError): ``out`` holds another scenario of the same name, or
            a damaged ``episodes.csv`` or ``scenarios.json`` (the message names the file and line).
        RuntimeError: another evaluation holds ``out``.
    """
    names = [s.name for s in scenarios]
    if not names or len(set(names)) != len(names):
        raise ValueError(f"`scenarios` must be at least one, with distinct names; got {names}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with exclusive(out, ".evaluate.lock", "another evaluation"):
        _check_scenarios(out, scenarios)
        wanted = {(d, s, seed) for d in config.drivers for s in names for seed in config.seeds}
        earlier: dict[Key, dict] = {}
        for row in read_episodes(out / "episodes.csv"):
            key = (row["driver"], row["scenario"], row["seed"])
            if not (key in wanted and row["status"] != "ok") and (key not in earlier or row["status"] == "ok"):
                earlier[key] = row  # finished rows, and rows of other keys as they were
        finished = {key for key, row in earlier.items() if row["status"] == "ok"}
        tasks = plan_tasks(scenarios, config, finished, out)
        logger.info("%s: %d of %d episodes finished earlier; %d to run in %d groups", out, len(wanted & finished),
                    len(wanted), sum(len(t.seeds) for t in tasks), len(tasks))
        store = _EpisodeFile(out / "episodes.csv", list(earlier.values()))
        try:
            if config.ray is not None:
                batches = _ray_tasks(tasks, config.ray, config.workers, config.retries)
            elif config.workers == 1:
                batches = _in_process(tasks)
            else:
                batches = _process_pool(tasks, config.workers, config.threads, config.retries)
            for rows in batches:
                store.append(rows)
                for row in rows:
                    earlier[(row["driver"], row["scenario"], row["seed"])] = row
                    if on_episode is not None:
                        on_episode(row)
        finally:
            store.close()
        rows = [earlier[(d, s, seed)] for d in config.drivers for s in names for seed in config.seeds]
        summary = summarize(rows)
        report = {
            "drivers": list(config.drivers), "scenarios": names, "seeds": list(config.seeds),
            "lockstep": config.lockstep, "threads": config.threads, "backend": "ray" if config.ray else "local",
            "summary": summary,
        }
        atomic_write_text(out / "summary.json", json.dumps(report, indent=2, allow_nan=False) + "\n")
        if config.report:
            write_report(rows, summary, out)
    errors = sum(row["status"] != "ok" for row in rows)
    if errors:
        logger.warning("%s: %d of %d episodes are error rows (re-run the same call to retry them)", out, errors, len(rows))
    return Evaluation(rows, summary)

