"""Compare the episodes.csv of every run folder of two behaviour.sh outputs.

    python same.py BEFORE AFTER

Rows sorted by (driver, scenario, seed); the timing and worker columns dropped. Exits 1 on any difference.
"""

import csv
import pathlib
import sys

TIMING = {"worker", "wall_s", "solve_ms_mean", "solve_ms_max", "solve_ms_per_episode_mean", "group"}


def rows(path: pathlib.Path) -> list[dict]:
    kept = ({key: value for key, value in row.items() if key not in TIMING} for row in csv.DictReader(open(path)))
    return sorted(kept, key=lambda row: (row["driver"], row["scenario"], int(row["seed"])))


def main(before: pathlib.Path, after: pathlib.Path) -> int:
    differing = 0
    for path in sorted(before.glob("*/episodes.csv")):
        old, new = rows(path), rows(after / path.parent.name / "episodes.csv")
        diffs = [(a["driver"], a["scenario"], a["seed"], key, a[key], b.get(key))
                 for a, b in zip(old, new) for key in a if a[key] != b.get(key)]
        same = len(old) == len(new) and not diffs
        differing += not same
        columns = len(old[0]) if old else 0
        print(f"{path.parent.name}: {len(old)} rows x {columns} columns: "
              f"{'identical' if same else f'{len(diffs)} differences, e.g. {diffs[:3]}'}")
    return 1 if differing else 0


if __name__ == "__main__":
    sys.exit(main(pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2])))
