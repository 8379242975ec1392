"""Is a driver better than a reference on the same seeds? Per-seed (paired) differences of the
task return, speed, meta cost, fallbacks, right-lane distance and clearance, with 95 % intervals.

Made for a safe agent against always-defer (or any driver against another), each evaluated on
the same seeds, possibly in separate folders and on scenarios of the same traffic::

    mmpc evaluate --driver safe-expert:cruise_task --scenarios cruise --seeds 62976-63231 --sim batched --lockstep 256 --out runs/cmp/defer
    mmpc evaluate --driver sb3:runs/rl/cruise_task/model.zip --scenarios cruise --seeds 62976-63231 --sim batched --lockstep 256 --out runs/cmp/agent
    python scripts/compare_drivers.py runs/cmp/defer agent=runs/cmp/agent --out runs/cmp

A spec is ``[LABEL=]FOLDER[#DRIVER[#SCENARIO]]``: the folder's ``episodes.csv``, narrowed to one
driver and scenario where it holds several. The first spec is the reference.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from mmpc.evaluate import paired_differences, read_episodes
from mmpc.evaluate.report import PAIRED_METRICS


def select(spec: str) -> tuple[str, list[dict]]:
    """(label, rows of one driver on one scenario) of a spec ``[LABEL=]FOLDER[#DRIVER[#SCENARIO]]``."""
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
    return label or f"{driver} on {scenario}", rows


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
    parser.add_argument("--out", default=None, help="write compare_drivers.json here")
    args = parser.parse_args(argv)
    keys = [key for key in args.metrics.split(",") if key]
    try:
        reference_label, reference = select(args.reference)
        compared = [select(spec) for spec in args.others]
        results = {label: paired_differences(reference, rows, keys) for label, rows in compared}
    except (ValueError, FileNotFoundError) as error:
        print(f"compare_drivers: error: {error}", file=sys.stderr)
        return 2
    print(f"differences against {reference_label}, per seed, 95 % intervals")
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
        path.write_text(json.dumps({"reference": reference_label, "results": results}, indent=1))
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
