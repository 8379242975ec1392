"""Closed-loop comparison of drivers (the expert and cloned policies) over the same seeds
(``mmpc imitate evaluate``): the episode metrics of :func:`mmpc.metrics.episode_metrics`
(those ``mmpc drive`` writes to ``metrics.json``) per episode, and per driver the collision
rate and the means.

Each driver drives the seeds in lockstep chunks (one driver call per step for a chunk), the
chunks of all drivers spread over worker processes.
"""

from __future__ import annotations

import multiprocessing
import signal
from typing import Callable, Optional, Sequence

import torch

from mmpc.scenario import ScenarioConfig

#: Summary columns: (key, header, format).
COLUMNS = (
    ("episodes", "episodes", "{:d}"),
    ("collisions", "collisions", "{:d}"),
    ("collision_rate", "collision rate", "{:.1%}"),
    ("duration", "mean duration [s]", "{:.1f}"),
    ("meta_cost_mean", "meta cost mean", "{:.3f}"),
    ("mean_speed", "mean v [m/s]", "{:.2f}"),
    ("lin_acc_mean", "|a| [m/s2]", "{:.2f}"),
    ("ang_acc_mean", "|psi''| [rad/s2]", "{:.3f}"),
    ("lane_changes", "lane changes", "{:.1f}"),
    ("offroad", "offroad steps", "{:d}"),
    ("min_clearance", "min clearance", "{:.2f}"),
)


def _worker_init(threads: int) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    torch.set_num_threads(threads)


def drive_chunk(scenario: ScenarioConfig, spec: str, seeds: Sequence[int]) -> list[dict]:
    """Metrics of ``seeds`` driven in lockstep by driver ``spec`` (each with ``driver`` added)."""
    from mmpc.drive import run_lockstep
    from mmpc.drivers import make_driver

    with torch.inference_mode():
        results = run_lockstep(scenario, seeds, driver=make_driver(spec, scenario))
    return [{"driver": spec, **result.metrics} for result in results]


def summarize(rows: Sequence[dict], specs: Sequence[str]) -> list[dict]:
    """Per driver: episodes, collisions (count, rate, seeds), off-road steps (sum), min clearance
    (min), the other metrics averaged over episodes."""
    summary = []
    for spec in specs:
        mine = [row for row in rows if row["driver"] == spec]
        if not mine:
            continue
        entry = {
            "driver": spec,
            "episodes": len(mine),
            "collisions": sum(row["collisions"] for row in mine),
            "collision_seeds": [row["seed"] for row in mine if row["collisions"]],
            "offroad": sum(row["offroad"] for row in mine),
            "min_clearance": min(row["min_clearance"] for row in mine),
        }
        entry["collision_rate"] = entry["collisions"] / len(mine)
        for key in ("meta_cost_mean", "mean_speed", "lin_acc_mean", "ang_acc_mean", "lane_changes", "duration", "solve_ms_mean"):
            entry[key] = sum(row[key] for row in mine) / len(mine)
        summary.append(entry)
    return summary


def format_table(summary: Sequence[dict], names: Optional[dict[str, str]] = None, markdown: bool = False) -> str:
    """Drivers as columns, :data:`COLUMNS` as rows (``names`` renames drivers)."""
    heads = [(names or {}).get(e["driver"], e["driver"]) for e in summary]
    rows = [[header] + [fmt.format(e[key]) for e in summary] for key, header, fmt in COLUMNS]
    if markdown:
        lines = ["| | " + " | ".join(heads) + " |", "|---|" + "---:|" * len(heads)]
        return "\n".join(lines + ["| " + " | ".join(c.replace("|", "\\|") for c in row) + " |" for row in rows])
    width = max(14, *map(len, heads))
    lines = [f"{'':<18}" + "".join(f"{h:>{width + 2}}" for h in heads)]
    return "\n".join(lines + [f"{row[0]:<18}" + "".join(f"{c:>{width + 2}}" for c in row[1:]) for row in rows])


def compare(
    scenario: ScenarioConfig,
    specs: Sequence[str],
    seeds: Sequence[int],
    *,
    lockstep: int = 10,
    workers: int = 1,
    threads: int = 1,
    on_chunk: Optional[Callable[[list[dict]], None]] = None,
) -> tuple[list[dict], list[dict]]:
    """Drive every seed with every driver.

    Args:
        scenario: the scenario (its duration sets the episode length).
        specs: driver specs (:func:`mmpc.drivers.make_driver`), e.g. ``mpc``, ``bc:RUN/policy.pt``.
        seeds: evaluation seeds (distinct).
        lockstep: episodes per driver call.
        workers: parallel processes (1: in this process).
        threads: torch threads per worker.
        on_chunk: called with each finished chunk's rows.

    Returns:
        (per-episode rows sorted by driver and seed, :func:`summarize` rows).
    """
    seeds = list(seeds)
    if not specs or not seeds or len(set(seeds)) != len(seeds):
        raise ValueError(f"`specs` and `seeds` must be non-empty and the seeds distinct; got {list(specs)}, {seeds[:10]}")
    if lockstep < 1 or workers < 1 or threads < 1:
        raise ValueError(f"`lockstep`, `workers` and `threads` must be >= 1; got {lockstep}, {workers}, {threads}")
    jobs = [(scenario, spec, seeds[i:i + lockstep]) for spec in specs for i in range(0, len(seeds), lockstep)]
    rows: list[dict] = []
    if workers == 1:
        for job in jobs:
            rows += drive_chunk(*job)
            if on_chunk is not None:
                on_chunk(rows[-len(job[2]):])
    else:
        with multiprocessing.get_context("spawn").Pool(min(workers, len(jobs)), _worker_init, (threads,)) as pool:
            for chunk in pool.imap_unordered(_star_drive_chunk, jobs):
                rows += chunk
                if on_chunk is not None:
                    on_chunk(chunk)
    rows.sort(key=lambda row: (list(specs).index(row["driver"]), seeds.index(row["seed"])))
    return rows, summarize(rows, specs)


def _star_drive_chunk(job: tuple) -> list[dict]:
    return drive_chunk(*job)
