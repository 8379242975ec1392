"""Closed-loop evaluation over scenarios x seeds: per-episode outputs, a summary table, and a
video of every episode that ended in a collision.

Episodes are independent processes' work when ``workers > 1`` (each with ``threads`` torch
threads); a seed fixes an episode, so a collision found without video is replayed with one.
"""

from __future__ import annotations

import json
import math
import multiprocessing
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Callable, Optional, Sequence

import torch

from mmpc.drive import run_episode, write_outputs
from mmpc.drivers import make_driver
from mmpc.scenario import ScenarioConfig

#: Columns of the summary table: (key, header, format).
TABLE = (
    ("episodes", "episodes", "{:d}"),
    ("collisions", "collisions", "{:d}"),
    ("offroad", "offroad steps", "{:d}"),
    ("mean_speed", "mean v [m/s]", "{:.2f}"),
    ("speed_residual_mean", "(v-v_c)^2 [m2/s2]", "{:.3f}"),
    ("right_lane_distance_mean", "right-lane dist [m]", "{:.2f}"),
    ("lin_acc_mean", "|a| [m/s2]", "{:.2f}"),
    ("ang_acc_mean", "|psi''| [rad/s2]", "{:.3f}"),
    ("lane_changes", "lane changes", "{:.1f}"),
    ("fallback_steps", "fallback steps", "{:.1f}"),
    ("solve_ms_mean", "solve ms mean", "{:.1f}"),
    ("solve_ms_max", "solve ms max", "{:.1f}"),
)


def episode_dir(out: Path, scenario: str, seed: int) -> Path:
    return out / scenario / f"seed_{seed}"


def _run_one(scenario: ScenarioConfig, seed: int, out: Path, video: bool, driver: str) -> dict:
    directory = episode_dir(out, scenario.name, seed)
    result = run_episode(scenario, seed, driver=make_driver(driver, scenario), video=directory / "episode.mp4" if video else None)
    write_outputs(result, directory)
    return result.metrics


def summarize(rows: Sequence[dict]) -> list[dict]:
    """One row per scenario: counts summed, collisions listed by seed, the rest averaged over
    episodes (``solve_ms_max``: the largest)."""
    summary = []
    for name in dict.fromkeys(row["scenario"] for row in rows):
        mine = [row for row in rows if row["scenario"] == name]
        entry: dict = {
            "scenario": name,
            "episodes": len(mine),
            "collisions": sum(row["collisions"] for row in mine),
            "collision_seeds": [row["seed"] for row in mine if row["collisions"]],
            "offroad": sum(row["offroad"] for row in mine),
            "solve_ms_max": max(row["solve_ms_max"] for row in mine),
        }
        for key in ("mean_speed", "speed_residual_mean", "right_lane_distance_mean", "lin_acc_mean", "ang_acc_mean",
                    "meta_cost_mean", "lane_changes", "fallback_steps", "solve_ms_mean", "min_clearance"):
            values = [row[key] for row in mine if key in row]
            if values:
                entry[key] = min(values) if key == "min_clearance" else sum(values) / len(values)
        summary.append(entry)
    return summary


def format_table(summary: Sequence[dict]) -> str:
    """Plain-text table of :func:`summarize` rows (one column per scenario)."""
    names = [entry["scenario"] for entry in summary]
    width = max([12, *map(len, names)])
    lines = [f"{'':<22}" + "".join(f"{name:>{width + 2}}" for name in names)]
    for key, header, fmt in TABLE:
        cells = []
        for entry in summary:
            value = entry.get(key)
            cells.append("-" if value is None or (isinstance(value, float) and math.isnan(value)) else fmt.format(value))
        lines.append(f"{header:<22}" + "".join(f"{cell:>{width + 2}}" for cell in cells))
    for entry in summary:
        if entry["collisions"]:
            lines.append(f"collisions in {entry['scenario']}: seeds {entry['collision_seeds']}")
    return "\n".join(lines)


def evaluate(
    scenarios: Sequence[ScenarioConfig],
    seeds: Sequence[int],
    out: Path,
    *,
    workers: int = 1,
    threads: int = 1,
    driver: str = "mpc",
    on_episode: Optional[Callable[[dict], None]] = None,
) -> tuple[list[dict], list[dict]]:
    """Run every scenario for every seed; write per-episode outputs and ``summary.json``.

    Args:
        scenarios: scenarios (distinct names: they name the output folders).
        seeds: seeds, the same for every scenario.
        out: output folder: ``<scenario>/seed_<n>/`` per episode (``episode.mp4`` only for
            episodes with a collision) and ``summary.json``.
        workers: parallel episode processes; with 1 the episodes run in this process.
        threads: torch threads of each worker process (``workers > 1``; one worker uses the
            caller's setting).
        driver: driver spec (:func:`mmpc.drivers.make_driver`), built anew for each episode.
        on_episode: called with each episode's metrics as it finishes.

    Returns:
        (per-episode metrics, :func:`summarize` rows).
    """
    names = [s.name for s in scenarios]
    if len(set(names)) != len(names):
        raise ValueError(f"`scenarios` must have distinct names; got {names}")
    if workers < 1 or threads < 1:
        raise ValueError(f"`workers` and `threads` must be >= 1; got {workers}, {threads}")
    jobs = [(scenario, seed) for scenario in scenarios for seed in seeds]
    rows: list[dict] = []
    if workers == 1:
        for scenario, seed in jobs:
            rows.append(_run_one(scenario, seed, out, False, driver))
            if on_episode is not None:
                on_episode(rows[-1])
    else:
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(workers, mp_context=context, initializer=torch.set_num_threads, initargs=(threads,)) as pool:
            futures = [pool.submit(_run_one, scenario, seed, out, False) for scenario, seed in jobs]
            for future in as_completed(futures):
                rows.append(future.result())
                if on_episode is not None:
                    on_episode(rows[-1])
        rows.sort(key=lambda row: (names.index(row["scenario"]), list(seeds).index(row["seed"])))
    by_name = {s.name: s for s in scenarios}
    for row in rows:
        if row["collisions"]:  # replay the seed with the video
            _run_one(by_name[row["scenario"]], row["seed"], out, True, driver)
    summary = summarize(rows)
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.json").write_text(json.dumps({"summary": summary, "episodes": rows}, indent=2) + "\n")
    return rows, summary
