"""The grid's results table of one scenario from `mmpc evaluate` folders: each row one driver or
one agent over its training seeds (mean over the seeds and their band, min to max), the task return's
per-seed (paired) difference against the reference, speed and collisions.

    python docs/experiments/2026-11-29-rl-grid/table.py runs/grid/eval/cruise_batched \
        --reference "always defer=safe-expert:cruise_task" \
        --row "PPO behind the layer=sb3:runs/grid/cruise_task/ppo_0/model.zip|sb3:runs/grid/cruise_task/ppo_1/model.zip|..." \
        --row "verified expert=verified:mpc" --out runs/grid/eval/cruise_batched

A row ``LABEL=DRIVER[|DRIVER...]`` names drivers of the folders' ``episodes.csv`` (several folders
may be given: one evaluation per driver group); a row of several drivers is an agent's seeds.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from mmpc.evaluate import paired_differences, read_episodes
from mmpc.evaluate.intervals import mean_ci, wilson_ci


def parse_row(text: str) -> tuple[str, list[str]]:
    """``LABEL=DRIVER[|DRIVER...]`` -> (label, drivers)."""
    label, sep, drivers = text.partition("=")
    if not sep or not label or not drivers:
        raise ValueError(f"{text!r}: expected LABEL=DRIVER[|DRIVER...]")
    return label, drivers.split("|")


def rows_by_driver(folders: list[Path]) -> dict[str, list[dict]]:
    """driver -> its episode rows over every folder (one scenario each; a driver in two folders is refused)."""
    found: dict[str, list[dict]] = {}
    for folder in folders:
        episodes = read_episodes(folder / "episodes.csv")
        if not episodes:
            raise ValueError(f"no episodes in {folder / 'episodes.csv'}")
        scenarios = {row["scenario"] for row in episodes}
        if len(scenarios) != 1:
            raise ValueError(f"{folder} holds the scenarios {sorted(scenarios)}; the table is of one scenario")
        for driver in dict.fromkeys(row["driver"] for row in episodes):
            if driver in found:
                raise ValueError(f"{driver} is in two of the folders; give each driver's episodes once")
            found[driver] = [row for row in episodes if row["driver"] == driver]
    return found


def summarize_row(label: str, drivers: list[str], found: dict[str, list[dict]], reference: list[dict]) -> dict:
    """One table row: the drivers' finished episodes, their task return and speed (the mean over
    the drivers, each driver's mean in ``per_driver``), the paired task-return difference
    against ``reference`` per driver, and the collisions over all their episodes."""
    missing = [driver for driver in drivers if driver not in found]
    if missing:
        raise ValueError(f"{label}: no episodes of {missing} in the folders (drivers there: {sorted(found)})")
    per_driver = []
    for driver in drivers:
        done = [row for row in found[driver] if row["status"] == "ok"]
        paired = paired_differences(reference, done, ["task_return", "mean_speed"])
        if paired["unpaired_seeds"]:
            raise ValueError(f"{label}: {driver} and the reference did not finish the same seeds "
                             f"({len(paired['unpaired_seeds'])} finished by one only, e.g. {paired['unpaired_seeds'][:3]})")
        per_driver.append({
            "driver": driver, "episodes": len(done), "collisions": sum(int(row["collisions"]) for row in done),
            "task_return": float(np.mean([row["task_return"] for row in done])),
            "task_return_ci": mean_ci([row["task_return"] for row in done])[1],
            "mean_speed": float(np.mean([row["mean_speed"] for row in done])),
            "vs_reference": paired["task_return"]["difference"], "vs_reference_ci": paired["task_return"]["difference_ci"],
            "vs_reference_relative": paired["task_return"]["relative"], "reference_task_return": paired["task_return"]["reference"],
            "paired_episodes": paired["episodes"]})
    returns = [d["task_return"] for d in per_driver]
    relative = [d["vs_reference_relative"] for d in per_driver]
    episodes, collisions = sum(d["episodes"] for d in per_driver), sum(d["collisions"] for d in per_driver)
    return {"label": label, "drivers": drivers, "per_driver": per_driver, "episodes": episodes, "collisions": collisions,
            "collision_rate_ci": wilson_ci(collisions, episodes),
            "task_return": float(np.mean(returns)), "task_return_band": [min(returns), max(returns)],
            "vs_reference_relative": float(np.mean(relative)), "vs_reference_band": [min(relative), max(relative)],
            "every_driver_above_reference": all(d["vs_reference_ci"] is not None and d["vs_reference_ci"][0] > 0
                                                for d in per_driver),
            "mean_speed": float(np.mean([d["mean_speed"] for d in per_driver]))}


def markdown(rows: list[dict], reference_label: str) -> str:
    """The table: one line per row; a row of several drivers shows the mean and the band over them,
    a single driver its 95 % interval (the return's; the paired difference's)."""
    lines = [f"| driver | task return | vs {reference_label}, per seed | mean speed [m/s] | collisions |",
             "|---|---:|---:|---:|---:|"]
    for row in rows:
        single = row["per_driver"][0] if len(row["drivers"]) == 1 else None
        if single:
            low, high = single["task_return_ci"] or (None, None)
            ret = f"{row['task_return']:.1f}" + (f" ± {(high - low) / 2:.1f}" if low is not None else "")
            if row["label"] == reference_label:
                versus = ""
            else:
                ci = single["vs_reference_ci"]
                versus = f"{single['vs_reference_relative']:+.1%}" + (
                    f" ± {(ci[1] - ci[0]) / 2 / single['reference_task_return']:.1%}" if ci else "")
        else:
            band, rel = row["task_return_band"], row["vs_reference_band"]
            ret = f"{row['task_return']:.1f} ({band[0]:.1f}-{band[1]:.1f})"
            versus = f"{row['vs_reference_relative']:+.1%} ({rel[0]:+.1%} to {rel[1]:+.1%})"
        lines.append(f"| {row['label']} | {ret} | {versus} | {row['mean_speed']:.2f} | "
                     f"{row['collisions']} of {row['episodes']} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", type=Path, help="mmpc evaluate output folders, one scenario")
    parser.add_argument("--reference", required=True, help="LABEL=DRIVER: the paired differences' reference")
    parser.add_argument("--row", action="append", default=[], help="LABEL=DRIVER[|DRIVER...], repeatable")
    parser.add_argument("--out", type=Path, help="write table.md and table.json here")
    args = parser.parse_args(argv)
    try:
        found = rows_by_driver(args.folders)
        reference_label, (reference_driver, *extra) = parse_row(args.reference)
        if extra:
            raise ValueError(f"--reference names one driver, got {[reference_driver, *extra]}")
        if reference_driver not in found:
            raise ValueError(f"--reference: no episodes of {reference_driver} (drivers there: {sorted(found)})")
        reference = [row for row in found[reference_driver] if row["status"] == "ok"]
        rows = [summarize_row(label, drivers, found, reference)
                for label, drivers in [(reference_label, [reference_driver])] + [parse_row(r) for r in args.row]]
    except ValueError as error:
        print(f"table: error: {error}", file=sys.stderr)
        return 2
    text = markdown(rows, reference_label)
    print(text)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "table.md").write_text(text + "\n")
        (args.out / "table.json").write_text(json.dumps(rows, indent=1))
        print(f"wrote {args.out / 'table.md'}, {args.out / 'table.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
