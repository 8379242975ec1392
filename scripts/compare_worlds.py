"""Do two evaluations agree? Per (driver, scenario): collisions, the statistics that lead to
them (fallback and fail-safe steps, the share of verified steps, short times to collision, other
cars' lane changes near the ego, the closest approach) and the driving (mean speed, meta cost),
each with its 95 % interval in each folder, and the 95 % interval of the difference.

Made for the batched simulator against highway-env, same driver, scenarios and seeds::

    mmpc evaluate --scenarios cruise,high_speed --seeds 0-199 --out runs/worlds/highway-env
    mmpc evaluate --scenarios cruise,high_speed --seeds 0-199 --lockstep 200 --sim batched --out runs/worlds/batched
    python scripts/compare_worlds.py runs/worlds/highway-env runs/worlds/batched --out runs/worlds

The two folders must hold the same seeds of each (driver, scenario) run with the same settings but
the world (``scenarios.json``); other runs are refused. Episodes are the units: a metric's interval is Student's t interval of the mean over episodes
(for collisions, the share of episodes with one, Wilson's interval); two worlds agree on a metric
when Welch's t interval of the difference of means holds 0 (:mod:`mmpc.evaluate.intervals`).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Optional, Sequence

from mmpc.evaluate import read_episodes
from mmpc.evaluate.intervals import mean_ci, welch_ci, wilson_ci
from mmpc.evaluate.store import scenario_differences

#: The metrics compared: (episodes.csv column, label).
METRICS = (("collisions", "episodes with a collision"), ("fallback_steps", "fallback steps"),
           ("failsafe_steps", "fail-safe steps"), ("verified_share", "share of steps verified"),
           ("short_ttc_steps", "steps with time to collision < 2 s"),
           ("near_lane_change_steps", "car-steps of lane changes near the ego"),
           ("min_clearance", "closest approach (ellipse-normalised)"), ("mean_speed", "mean speed [m/s]"),
           ("meta_cost_mean", "meta cost (mean per step)"), ("task_return", "task return (highway-env's reward)"))


def _bounds(centre: Optional[float], interval: Optional[Sequence[float]]) -> tuple[float, float, float]:
    """(centre, low, high) of an interval of :mod:`mmpc.evaluate.intervals`: an unknown interval
    (fewer than two finite values) is unbounded, an unknown centre (no finite value) NaN."""
    centre = math.nan if centre is None else centre
    return (centre, -math.inf, math.inf) if interval is None else (centre, interval[0], interval[1])


def check_alike(reference: Path, other: Path, *, allow_different_scenarios: bool = False) -> None:
    """Refuse runs that are not the same episodes in two worlds: a folder without episodes, one
    folder twice, or a (driver, scenario) in both whose finished seeds differ, or whose scenario
    settings (other than the world, ``sim``) differ or are not recorded, unless
    ``allow_different_scenarios``. ``ValueError`` saying which."""
    for folder in (reference, other):
        if not (folder / "episodes.csv").is_file():
            raise ValueError(f"{folder} holds no episodes.csv; expected an `mmpc evaluate` output folder")
    if reference.resolve() == other.resolve():
        raise ValueError(f"{reference} and {other} are one folder; compare the runs of two worlds")
    first, second = _groups(reference), _groups(other)
    for key in sorted(set(first) & set(second)):
        seeds = [sorted(row["seed"] for row in rows) for rows in (first[key], second[key])]
        if seeds[0] != seeds[1]:
            raise ValueError(f"{key[0]} on {key[1]} finished other seeds in the two folders ({len(seeds[0])} in {reference}, "
                             f"{len(seeds[1])} in {other}, {len(set(seeds[0]) & set(seeds[1]))} in common); compare runs of "
                             "the same seeds")
        lines = scenario_differences(reference, key[1], other, key[1], ignore=("name", "sim"))
        if lines and not allow_different_scenarios:
            raise ValueError(f"{key[1]} was run with other settings in {other} than in {reference} ({'; '.join(lines)}); "
                             "compare runs that differ in the world (--sim) only, or pass --allow-different-scenarios if that is meant")


def _groups(folder: Path) -> dict[tuple[str, str], list[dict]]:
    """A folder's finished episodes by (driver, scenario)."""
    rows: dict[tuple[str, str], list[dict]] = {}
    for row in read_episodes(folder / "episodes.csv"):
        if row["status"] == "ok":
            rows.setdefault((row["driver"], row["scenario"]), []).append(row)
    return rows


def compare(reference: Path, other: Path) -> list[dict]:
    """One row per (driver, scenario, metric) present with ``status == ok`` episodes in both folders
    (a metric is left out where an episode has none: ``verified_share`` of a driver not verified,
    the newer statistics of an evaluation older than them)."""
    first, second = _groups(reference), _groups(other)
    results = []
    for key in sorted(set(first) & set(second)):
        for column, label in METRICS:
            if any(r[column] is None for r in first[key] + second[key]):
                continue
            a = [float(r[column] > 0) if column == "collisions" else float(r[column]) for r in first[key]]
            b = [float(r[column] > 0) if column == "collisions" else float(r[column]) for r in second[key]]
            if column == "collisions":
                interval_a, interval_b = (_bounds(sum(x) / len(x), wilson_ci(int(sum(x)), len(x))) for x in (a, b))
            else:
                interval_a, interval_b = (_bounds(*mean_ci(x)) for x in (a, b))
            difference = _bounds(*welch_ci(a, b)) if len(a) > 1 and len(b) > 1 else (math.nan, -math.inf, math.inf)
            results.append({
                "driver": key[0], "scenario": key[1], "metric": column, "label": label,
                "episodes": [len(a), len(b)], "reference": interval_a, "other": interval_b, "difference": difference,
                "agree": difference[1] <= 0.0 <= difference[2],
            })
    return results


def format_table(rows: Sequence[dict], names: tuple[str, str]) -> str:
    def cell(interval: Sequence[float], digits: int) -> str:
        return f"{interval[0]:.{digits}f} [{interval[1]:.{digits}f}, {interval[2]:.{digits}f}]"

    lines = [f"| driver | scenario | metric | episodes | {names[0]} | {names[1]} | difference | agree |", "|---" * 8 + "|"]
    for row in rows:
        digits = 3 if row["metric"] != "mean_speed" else 2
        lines.append(f"| {row['driver']} | {row['scenario']} | {row['label']} | {row['episodes'][0]} / {row['episodes'][1]} | "
                     f"{cell(row['reference'], digits)} | {cell(row['other'], digits)} | {cell(row['difference'], digits)} | "
                     f"{'yes' if row['agree'] else 'no'} |")
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("reference", type=Path, help="evaluation folder of the reference world (highway-env)")
    parser.add_argument("other", type=Path, help="evaluation folder to compare (the batched simulator)")
    parser.add_argument("--out", type=Path, default=None, help="write compare_worlds.json and .md here")
    parser.add_argument("--allow-different-scenarios", action="store_true",
                        help="compare runs whose scenario settings differ beyond the world (or are not recorded)")
    args = parser.parse_args(argv)
    try:
        check_alike(args.reference, args.other, allow_different_scenarios=args.allow_different_scenarios)
        rows = compare(args.reference, args.other)
    except ValueError as error:
        return _refuse(str(error))
    if not rows:
        return _refuse(f"no (driver, scenario) with finished episodes in both {args.reference} and {args.other}")
    table = format_table(rows, (args.reference.name, args.other.name))
    if args.out is not None:
        try:
            args.out.mkdir(parents=True, exist_ok=True)
            (args.out / "compare_worlds.json").write_text(json.dumps({"reference": str(args.reference), "other": str(args.other),
                                                                      "rows": rows}, indent=2) + "\n")
            (args.out / "compare_worlds.md").write_text(table + "\n")
        except OSError as error:
            return _refuse(f"--out {args.out} must be a folder this process can create and write to; got {error}")
    print(table)
    return 0


def _refuse(message: str) -> int:
    """Print ``message`` as the script's error; the exit status of a refusal."""
    print(f"compare_worlds: error: {message}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
