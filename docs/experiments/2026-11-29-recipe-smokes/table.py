"""The smoke runs' table from their TensorBoard event files and crashes.csv (issue 66's acceptance).

    python docs/experiments/2026-11-29-recipe-smokes/table.py RUN [RUN ...]
"""

import csv
import sys
from pathlib import Path

import yaml

from mmpc.rl.report import read_scalars

print("| run | agent steps | finished episodes | training collisions | crashes.csv rows | verified share: mean of the log windows (min) | fail-safe rate: mean (max) |")
print("|---|---:|---:|---:|---:|---:|---:|")
for run in map(Path, sys.argv[1:]):
    scalars = read_scalars(run)
    last = {tag: max(points)[1] for tag, points in scalars.items()}
    share = [value for _, value in scalars["safety/verified_share"]]  # one value per log window (equal sizes)
    failsafe = [value for _, value in scalars["safety/failsafe_rate"]]
    with open(run / "crashes.csv") as file:
        crashes = sum(1 for _ in csv.DictReader(file))
    trained = yaml.safe_load((run / "config.yaml").read_text()).get("trained_timesteps")
    print(f"| {run.name} | {trained} | {last['safety/episodes']:.0f} | {last['safety/crashes']:.0f} | {crashes} "
          f"| {sum(share) / len(share):.4f} ({min(share):.4f}) | {100 * sum(failsafe) / len(failsafe):.2f} % "
          f"({100 * max(failsafe):.2f} %) |")
