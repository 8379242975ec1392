"""Batch offline evaluation: drivers x scenarios x seeds, on this machine or a Ray cluster.

Every (driver, scenario, seed) is one closed-loop episode, fixed by those three. Episodes run in
*groups*: the seeds of a (driver, scenario) are split into fixed groups by ``seed // lockstep``
and a group's episodes are driven in lockstep (:func:`mmpc.highway.runner.run_lockstep`), one driver
call per control step for all of them (for the MPC: one optimizer call over all their goal
batches). The groups depend on the seeds and ``lockstep`` only, never on the backend or the
number of workers, so the same call gives the same per-episode results locally and on Ray.

A group is one task. Tasks run in this process (``workers == 1``), in a pool of worker
processes, or as Ray tasks (``ray=...``); only this (coordinating) process writes the results:

- ``episodes.csv``: one row per episode (:data:`COLUMNS`), appended and fsync'ed as each group
  finishes. ``status`` is ``ok`` or ``error`` (the exception in ``error``).
- ``summary.json``: per driver x scenario the counts and means with 95 % confidence intervals
  (:func:`mmpc.evaluate.report.summarize`); with ``report``: ``summary.md``, ``compare.png``
  and TensorBoard scalars under ``tensorboard/`` (:mod:`mmpc.evaluate.report`).

Resuming: a second call with the same ``out`` skips the (driver, scenario, seed) keys already
``ok`` and re-runs the error and missing ones, once it has checked that each scenario's settings
and each driver's files (a checkpoint a spec names) are those the folder's episodes were run
with (``scenarios.json``, :func:`mmpc.evaluate.store.check_inputs`); ``episodes.csv`` is
rewritten (temp file + rename) without the rows being re-run, so no key appears twice. A
worker process that dies takes its pool down; the groups that were in flight are run again one
at a time, so the one that kills its worker is found and, after ``retries`` further deaths,
written as error rows; the run goes on. An episode that raises is an error row: a failing group
is re-run one seed at a time so only the failing episodes are errors.

A resumed call may use another ``lockstep`` (and other seeds): done is decided per key, and
each row records the ``group`` and ``group_size`` it was driven in. Group membership changes an
episode only through the rounding of the batched solves, and a resume with the same
``lockstep`` drives other groups too (error rows retried apart from their group's finished
seeds, seeds added to a group later), so refusing a new ``lockstep`` would not make a resumed
evaluation equal an uninterrupted one; ``summary.json`` names this call's ``lockstep``, the rows
their groups.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Callable, NamedTuple, Optional, Sequence

from mmpc.config import ConfigError
from mmpc.drivers import Driver, make_driver
from mmpc.evaluate.backends import run_tasks
from mmpc.evaluate.report import summarize, write_report
from mmpc.evaluate.store import EpisodeFile, Key, check_inputs, read_episodes, row_key
from mmpc.evaluate.tasks import EvaluationConfig, error_rows, plan_tasks, run_group
from mmpc.files import atomic_write_text, exclusive
from mmpc.scenario import ScenarioConfig

logger = logging.getLogger(__name__)


class Evaluation(NamedTuple):
    """What :func:`evaluate` returns.

    Fields:
        rows: one row per requested episode (:data:`COLUMNS`), ordered driver, scenario, seed.
        summary: :func:`mmpc.evaluate.report.summarize` of ``rows``.
    """

    rows: list[dict]
    summary: list[dict]


def check_scenarios(scenarios: Sequence[ScenarioConfig]) -> None:
    """Refuse scenarios that cannot be evaluated together, before any work or folder: none, two
    of one name (a name keys the rows and ``scenarios.json``; files of one ``name:``, or a
    ``name`` override given to several), or one that reads data this machine lacks
    (:meth:`mmpc.scenario.ScenarioConfig.missing_data`: NGSIM traffic without its recording).

    Raises:
        mmpc.config.ConfigError: the message names the repeated names or the scenario and what it lacks.
    """
    names = [s.name for s in scenarios]
    if not names:
        raise ConfigError("`scenarios` must be at least one scenario; got none")
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise ConfigError(f"the scenarios must have distinct names (a name keys the results); got {names}: "
                          f"{', '.join(map(repr, repeated))} more than once")
    for scenario in scenarios:
        missing = scenario.missing_data()
        if missing is not None:
            raise ConfigError(f"scenario {scenario.name!r}: {missing}")


def check_drivers(scenarios: Sequence[ScenarioConfig], drivers: Sequence[str]) -> None:
    """Build every driver for every scenario once, before any folder or row: a driver that cannot
    drive a scenario (a missing checkpoint, a check the scenario's settings are outside of) is
    refused here, not as error rows.

    Raises:
        mmpc.config.ConfigError: the message names the driver, the scenario and why.
    """
    for spec in drivers:
        for scenario in scenarios:
            build_driver(spec, scenario).close()


def build_driver(spec: str, scenario: ScenarioConfig) -> Driver:
    """:func:`mmpc.drivers.make_driver`, its refusal as a :class:`mmpc.config.ConfigError` naming the
    driver, the scenario and why."""
    try:
        return make_driver(spec, scenario)
    except (ValueError, OSError, KeyError) as error:
        raise ConfigError(f"driver {spec!r} cannot drive scenario {scenario.name!r}: {error}") from error


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
        mmpc.config.ConfigError (a ValueError): scenarios :func:`check_scenarios` refuses (none, two of
            one name, one without its data), or a driver that cannot drive one (:func:`check_drivers`),
            before ``out`` is made.
        EvaluationFolderError (a ValueError): ``out`` holds another scenario of the same name,
            episodes of a driver spec whose files changed since (:func:`mmpc.evaluate.store.check_inputs`),
            or a damaged ``episodes.csv`` or ``scenarios.json`` (the message names the file and line).
        mmpc.files.OutputFolderError (a RuntimeError): another evaluation holds ``out`` (its lock
            file ``.evaluate.lock``, removed when the call ends).
    """
    check_scenarios(scenarios)
    check_drivers(scenarios, config.drivers)
    names = [s.name for s in scenarios]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with exclusive(out, ".evaluate.lock", "another evaluation", remove=True):
        check_inputs(out, scenarios, config.drivers)
        wanted = {(d, s, seed) for d in config.drivers for s in names for seed in config.seeds}
        earlier: dict[Key, dict] = {}
        for row in read_episodes(out / "episodes.csv"):
            key = row_key(row)
            if not (key in wanted and row["status"] != "ok") and (key not in earlier or row["status"] == "ok"):
                earlier[key] = row  # finished rows, and rows of other keys as they were
        finished = {key for key, row in earlier.items() if row["status"] == "ok"}
        tasks = plan_tasks(scenarios, config, finished, out)
        logger.info("%s: %d of %d episodes finished earlier; %d to run in %d groups", out, len(wanted & finished),
                    len(wanted), sum(len(t.seeds) for t in tasks), len(tasks))
        store = EpisodeFile(out / "episodes.csv", list(earlier.values()))
        try:
            for _, rows in run_tasks(tasks, run_group, error_rows, config.backend):
                store.append(rows)
                for row in rows:
                    earlier[row_key(row)] = row
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

