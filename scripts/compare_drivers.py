"""Is a driver better than a reference on the same seeds? Per-seed (paired) differences of the
task return, speed, meta cost, fallbacks, right-lane distance and clearance, with 95 % intervals.

Made for a safe agent against always-defer (or any driver against another), each evaluated on
the same seeds, possibly in separate folders and on scenarios of the same traffic::

    mmpc evaluate --driver safe-expert:cruise_task --scenarios cruise --seeds 62976-63231 --sim batched --lockstep 256 --out runs/cmp/defer
    mmpc evaluate --driver sb3:runs/rl/cruise_task/model.zip --scenarios cruise --seeds 62976-63231 --sim batched --lockstep 256 --out runs/cmp/agent
    python scripts/compare_drivers.py runs/cmp/defer agent=runs/cmp/agent --out runs/cmp

A spec is ``[LABEL=]FOLDER[#DRIVER[#SCENARIO]]``: the folder's ``episodes.csv``, narrowed to one
driver and scenario where it holds several. The first spec is the reference. The label (default
``DRIVER on SCENARIO``) keys the results, so two compared runs of one label are refused.

Pairs are of the same traffic only on the same scenario: each folder's ``scenarios.json`` records
the settings its episodes were run with, and runs whose settings differ (another duration, a
``--set``) are refused unless ``--allow-different-scenarios`` says that is meant (the settings that
differ are printed then). Names alone may differ.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from typing import NamedTuple

from mmpc.evaluate import paired_differences, read_episodes
from mmpc.evaluate.report import PAIRED_METRICS, check_paired_metrics
from mmpc.evaluate.store import scenario_differences


class Selection(NamedTuple):
    """The rows of one driver on one scenario, named by a spec.

    Fields:
        label: the driver's name in the table.
        folder: the evaluation folder.
        scenario: the scenario's name.
        rows: its episodes.csv rows.
    """

    label: str
    folder: Path
    scenario: str
    rows: list[dict]


def select(spec: str) -> Selection:
    """The rows of one driver on one scenario of a spec ``[LABEL=]FOLDER[#DRIVER[#SCENARIO]]``."""
    label, _, where = spec.partition("=") if "=" in spec.split("#")[0] else ("", "", spec)
    folder, *narrow = where.split("#")
    if len(narrow) > 2:
        raise ValueError(f"{spec!r}: expected [LABEL=]FOLDER[#DRIVER[#SCENARIO]]")
    rows = read_episodes(Path(folder) / "episodes.csv")
    if not rows:
        raise ValueError(f"{spec!r}: no episodes in {Path(folder) / 'episodes.csv'}")
    for column, wanted in zip(("driver", "scenario"), narrow):
        rows = [row for row in rows if row[column] == wanted]
        if not rows:
            raise ValueError(f"{spec!r}: no episodes of {column} {wanted!r} in {folder}")
    groups = sorted({(row["driver"], row["scenario"]) for row in rows})
    if len(groups) > 1:
        raise ValueError(f"{spec!r}: {folder} holds {len(groups)} driver x scenario groups {groups}; "
                         "name one as FOLDER#DRIVER#SCENARIO")
    driver, scenario = groups[0]
    return Selection(label or f"{driver} on {scenario}", Path(folder), scenario, rows)


def check_labels(compared: list[Selection]) -> None:
    """Refuse two compared runs of one label (a label keys the results, so the second would
    replace the first); the reference's label may be a compared run's (one driver, two folders)."""
    labels = [selection.label for selection in compared]
    for label in dict.fromkeys(label for label in labels if labels.count(label) > 1):
        runs = ", ".join(str(s.folder) for s in compared if s.label == label)
        raise ValueError(f"the compared runs must have distinct labels (a label keys the results); {label!r} names "
                         f"{labels.count(label)} of them ({runs}): give each its own as LABEL=FOLDER")


def cell(entry: dict) -> str:
    """``difference +- half (relative %)`` of one metric."""
    difference, interval, relative = entry["difference"], entry["difference_ci"], entry["relative"]
    if difference is None:
        return "-"
    text = f"{difference:+.3g}" if interval is None else f"{difference:+.3g} ± {(interval[1] - interval[0]) / 2:.2g}"
    return text + ("" if relative is None else f" ({relative:+.1%})")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("reference", help="[LABEL=]FOLDER[#DRIVER[#SCENARIO]] of the reference driver")
    parser.add_argument("others", nargs="+", help="the drivers compared with it, same form")
    parser.add_argument("--metrics", default=",".join(PAIRED_METRICS), help="episodes.csv columns (default: %(default)s)")
    parser.add_argument("--allow-different-scenarios", action="store_true",
                        help="compare runs whose scenario settings differ (or are not recorded); the differences are printed")
    parser.add_argument("--out", default=None, help="write compare_drivers.json here")
    args = parser.parse_args(argv)
    keys = [key for key in args.metrics.split(",") if key]
    try:
        check_paired_metrics(keys)
    except ValueError as error:
        return _refuse(f"--metrics: {error}")
    try:
        reference = select(args.reference)
        compared = [select(spec) for spec in args.others]
        check_labels(compared)
        differences = {selection.label: scenario_differences(reference.folder, reference.scenario, selection.folder,
                                                             selection.scenario) for selection in compared}
        for label, lines in differences.items():
            if lines and not args.allow_different_scenarios:
                raise ValueError(f"{label} ran another scenario than {reference.label} ({'; '.join(lines)}), so its "
                                 "seeds are not the same traffic; pass --allow-different-scenarios if that is meant")
        results = {}
        for selection in compared:
            results[selection.label] = paired_differences(reference.rows, selection.rows, keys)
            if not results[selection.label]["episodes"]:
                raise ValueError(f"{selection.label} and {reference.label} finished no seed in common "
                                 f"({_seeds(selection.rows)} against {_seeds(reference.rows)}); compare runs of the same seeds")
    except (ValueError, FileNotFoundError) as error:
        return _refuse(str(error))
    print(f"differences against {reference.label}, per seed, 95 % intervals")
    for label, lines in differences.items():
        for line in lines:
            print(f"  {label}: scenario differs from the reference's: {line}")
    print("| driver | paired episodes | collisions (reference) | " + " | ".join(keys) + " |")
    print("|---|---:|---:|" + "---:|" * len(keys))
    for label, result in results.items():
        print(f"| {label} | {result['episodes']} | {result['collisions']} ({result['reference_collisions']}) | "
              + " | ".join(cell(result[key]) for key in keys) + " |")
        if result["unpaired_seeds"]:
            print(f"  {label}: {len(result['unpaired_seeds'])} seeds finished in one folder only, left out")
    if args.out:
        path = Path(args.out) / "compare_drivers.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"reference": reference.label, "results": results,
                                    "scenario_differences": differences}, indent=1))
        print(f"wrote {path}")
    return 0


def _refuse(message: str) -> int:
    """Print ``message`` as the script's error; the exit status of a refusal."""
    print(f"compare_drivers: error: {message}", file=sys.stderr)
    return 2


def _seeds(rows: list[dict]) -> str:
    """The finished seeds of ``rows`` in words."""
    seeds = sorted(row["seed"] for row in rows if row.get("status", "ok") == "ok")
    return f"{len(seeds)} finished seeds" + (f" {seeds[0]}-{seeds[-1]}" if seeds else "")


if __name__ == "__main__":
    sys.exit(main())
