"""The task return of a ceiling search (``scripts/ceiling.py --rank task_return``) and of its driver
beside drivers evaluated on the same seeds and duration (an ``mmpc evaluate`` folder), each paired
per seed against a reference driver of that folder (always-defer), over the seeds both hold.

    python docs/experiments/2026-11-29-rl-grid/ceiling_gains.py runs/ceiling_task/ceiling.jsonl#cruise \
        runs/grid/cruise_ceiling_seeds --reference safe-expert:cruise_task
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from mmpc.evaluate import read_episodes
from mmpc.evaluate.intervals import mean_ci


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("ceiling", help="ceiling.jsonl#SCENARIO (the rows of one scenario and kind verified)")
    parser.add_argument("evaluation", type=Path, help="an mmpc evaluate folder of the same seeds and duration")
    parser.add_argument("--reference", required=True, help="the reference driver of the evaluation folder")
    parser.add_argument("--kind", default="verified")
    args = parser.parse_args()
    path, _, scenario = args.ceiling.partition("#")
    rows = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
    rows = {row["seed"]: row for row in rows if row["kind"] == args.kind and (not scenario or row["scenario"] == scenario)
            and not row["crashed"]}
    episodes = [row for row in read_episodes(args.evaluation / "episodes.csv") if row["status"] == "ok"]
    returns: dict[str, dict[int, float]] = {}
    for episode in episodes:
        returns.setdefault(episode["driver"], {})[episode["seed"]] = episode["task_return"]
    if args.reference not in returns:
        raise SystemExit(f"no {args.reference} in {args.evaluation}; drivers there: {sorted(returns)}")
    seeds = sorted(rows.keys() & returns[args.reference].keys())
    if not seeds:
        raise SystemExit("the ceiling and the evaluation share no seed")
    reference = [returns[args.reference][seed] for seed in seeds]
    series = {f"ceiling ({args.kind}, ranked by the task return)": [rows[s]["task_return"] for s in seeds],
              f"the ceiling's driver ({rows[seeds[0]]['driver']} on {Path(rows[seeds[0]]['scenario']).stem})":
                  [rows[s]["driver_task_return"] for s in seeds]}
    series.update({driver: [values[s] for s in seeds] for driver, values in returns.items() if set(seeds) <= values.keys()})
    print(f"{len(seeds)} seeds {seeds[0]}-{seeds[-1]}; task return per episode, paired against {args.reference}")
    print("| episode | task return | vs reference, per seed | relative |\n|---|---:|---:|---:|")
    table = {}
    for label, values in series.items():
        mean, interval = mean_ci(values)
        gain, gain_interval = mean_ci([v - r for v, r in zip(values, reference)])
        base = sum(reference) / len(reference)
        table[label] = {"task_return": mean, "ci": interval, "gain": gain, "gain_ci": gain_interval, "relative": gain / base}
        print(f"| {label} | {mean:.1f} [{interval[0]:.1f}, {interval[1]:.1f}] | {gain:+.2f} [{gain_interval[0]:+.2f}, "
              f"{gain_interval[1]:+.2f}] | {gain / base:+.1%} |")
    print(json.dumps({"seeds": seeds, "reference": args.reference, "table": table}))


if __name__ == "__main__":
    main()
