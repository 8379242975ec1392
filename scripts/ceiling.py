"""The ceilings: the best any driver could do on each seed, with and without the check.

A beam search that knows the future (:mod:`mmpc.evaluate.ceiling`) on the batched simulator, per
scenario and seed: the *verified* ceiling (every command keeps a verified way out) beside
``verified:mpc``, the *unprotected* ceiling (every command that does not collide) beside ``mpc``.
(unprotected - verified ceiling) is what the check's assumptions cost; (verified ceiling -
``verified:mpc``) is what a better causal driver could win back.

Rows go to ``--out``/ceiling.jsonl as each batch of seeds finishes; a run stopped half way and
started again with the same command skips the seeds it has (another setting is refused, saying
which). The table (and ``--out``/summary.json): per scenario and ceiling, the mean speed and meta
cost of the ceiling and of its driver with 95 % intervals, the paired gain, and on how many seeds
the ceiling is at or above its driver.

    python scripts/ceiling.py --scenarios high_speed,cruise --seeds 0-31 --duration 40 --out runs/ceiling
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Sequence

import torch

from mmpc.cli.arguments import COMPILE_CHOICES, apply_compile, seed_list, unwritable
from mmpc.evaluate.ceiling import RANKS, CeilingConfig, search_ceiling
from mmpc.evaluate.intervals import mean_ci
from mmpc.scenario import load_scenario

KINDS = ("verified", "unprotected")
ROWS = "ceiling.jsonl"
#: The settings a row is kept under; rows of another setting in one folder are refused.
SETTINGS = ("duration", "beam", "branch_period", "screened", "siblings", "rank")
#: A setting's value in folders written before it existed.
SETTING_DEFAULTS = {"rank": "scenario"}


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenarios", default="high_speed,cruise", help="comma-separated scenario names")
    parser.add_argument("--seeds", type=seed_list, default=seed_list("0-31"), help="episode seeds, e.g. 0-31")
    parser.add_argument("--kinds", default=",".join(KINDS), help=f"ceilings to search: {', '.join(KINDS)}")
    parser.add_argument("--duration", type=float, default=40.0, help="episode length [s]")
    parser.add_argument("--beam", type=int, default=CeilingConfig.beam, help="nodes kept per seed")
    parser.add_argument("--branch-period", type=float, default=CeilingConfig.branch_period,
                        help="the beam branches at least this often [s]")
    parser.add_argument("--screened", type=int, default=CeilingConfig.screened,
                        help="screened x beam best children per seed enter the check")
    parser.add_argument("--siblings", type=int, default=CeilingConfig.siblings,
                        help="children of one node kept before others'")
    parser.add_argument("--rank", choices=RANKS, default="scenario",
                        help="what the search maximises: the scenario's score (distance at high speed, the meta cost in "
                             "cruise), task_return (highway-env's reward summed over the frames) or distance, in any "
                             "scenario (default %(default)s)")
    parser.add_argument("--batch", type=int, default=8, help="seeds searched together")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--compile", choices=tuple(COMPILE_CHOICES), default="auto", help="compile the optimizer")
    parser.add_argument("--out", type=Path, default=Path("runs/ceiling"), help="folder of the rows and the summary")
    args = parser.parse_args(argv)
    kinds = [kind for kind in args.kinds.split(",") if kind]
    if not kinds or any(kind not in KINDS for kind in kinds):
        parser.error(f"--kinds takes {', '.join(KINDS)}; got {args.kinds!r}")
    args.kinds = kinds
    args.scenarios = [name for name in args.scenarios.split(",") if name]
    if not args.scenarios:
        parser.error("--scenarios names no scenario")
    for name in ("beam", "screened", "siblings", "batch", "threads"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1; got {getattr(args, name)}")
    if not (args.duration > 0 and args.branch_period > 0):
        parser.error(f"--duration and --branch-period must be > 0 s; got {args.duration}, {args.branch_period}")
    return args


def read_rows(path: Path, repair: bool = False) -> list[dict]:
    """The rows written so far. A line cut short by an interruption is dropped, saying so, and
    with ``repair`` the file is rewritten without it (rows appended after it would join it)."""
    if not path.exists():
        return []
    rows, lines = [], path.read_text(encoding="utf-8").splitlines()
    for number, line in enumerate(lines, 1):
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            print(f"{path}:{number}: an unfinished row, dropped (its seed is searched again)", file=sys.stderr)
    if repair and len(rows) < len(lines):
        path.write_text("".join(json.dumps(row) + "\n" for row in rows), encoding="utf-8")
    return rows


def settings_of(args: argparse.Namespace) -> dict:
    return {name: getattr(args, name) for name in SETTINGS}


def summarize(rows: list[dict]) -> list[dict]:
    """Per (scenario, kind): the ceiling's and its driver's means with 95 % intervals, the paired gains
    (ceiling - driver; a meta cost gained is negative)."""
    table = []
    for scenario, kind in dict.fromkeys((row["scenario"], row["kind"]) for row in rows):
        mine = sorted((row for row in rows if row["scenario"] == scenario and row["kind"] == kind), key=lambda r: r["seed"])
        entry = {"scenario": scenario, "kind": kind, "driver": mine[0]["driver"], "seeds": len(mine),
                 "ceiling_crashed": sum(row["crashed"] for row in mine),
                 "driver_crashed": sum(row["driver_crashed"] for row in mine),
                 "at_or_above_driver": sum(row["score"] >= row["driver_score"] - 1e-6 for row in mine),
                 "nodes_crashed": sum(row["nodes_crashed"] for row in mine)}
        for metric in ("mean_speed", "meta_cost") + (("task_return",) if all("task_return" in row for row in mine) else ()):
            entry[metric] = mean_ci([row[metric] for row in mine])
            entry[f"driver_{metric}"] = mean_ci([row[f"driver_{metric}"] for row in mine])
            entry[f"gain_{metric}"] = mean_ci([row[metric] - row[f"driver_{metric}"] for row in mine])
        table.append(entry)
    return table


def format_table(table: list[dict]) -> str:
    def cell(value) -> str:
        mean, interval = value
        if mean is None:
            return "-"
        return f"{mean:.2f}" if interval is None else f"{mean:.2f} [{interval[0]:.2f}, {interval[1]:.2f}]"

    lines = ["| scenario | ceiling | seeds | speed [m/s] | meta cost | task return | driver | driver speed | driver meta cost | "
             "driver task return | speed gain | meta cost gain | task return gain | ceiling >= driver | crashed (ceiling / driver) |",
             "|" + "---|" * 15]
    for entry in table:
        unknown = (None, None)
        lines.append(f"| {entry['scenario']} | {entry['kind']} | {entry['seeds']} | {cell(entry['mean_speed'])} | "
                     f"{cell(entry['meta_cost'])} | {cell(entry.get('task_return', unknown))} | {entry['driver']} | "
                     f"{cell(entry['driver_mean_speed'])} | {cell(entry['driver_meta_cost'])} | "
                     f"{cell(entry.get('driver_task_return', unknown))} | {cell(entry['gain_mean_speed'])} | "
                     f"{cell(entry['gain_meta_cost'])} | {cell(entry.get('gain_task_return', unknown))} | "
                     f"{entry['at_or_above_driver']}/{entry['seeds']} | {entry['ceiling_crashed']} / {entry['driver_crashed']} |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    scenarios = {name: load_scenario(name, {"duration": args.duration, "sim": "batched"}) for name in args.scenarios}
    problem = unwritable(args.out)
    if problem:
        print(f"ceiling: cannot write to {args.out}: {problem}", file=sys.stderr)
        return 2
    settings_path = args.out / "settings.json"
    if settings_path.exists():
        before = {**SETTING_DEFAULTS, **json.loads(settings_path.read_text(encoding="utf-8"))}
        differ = {key: (before.get(key), value) for key, value in settings_of(args).items() if before.get(key) != value}
        if differ:
            print(f"ceiling: {args.out} holds rows of other settings (was, now): {differ}; use another --out",
                  file=sys.stderr)
            return 2
    else:
        settings_path.write_text(json.dumps(settings_of(args), indent=2) + "\n", encoding="utf-8")
    apply_compile(args.compile)
    torch.set_num_threads(args.threads)
    path = args.out / ROWS
    done = {(row["scenario"], row["kind"], row["seed"]) for row in read_rows(path, repair=True)}
    for name, scenario in scenarios.items():
        for kind in args.kinds:
            todo = [seed for seed in args.seeds if (name, kind, seed) not in done]
            config = CeilingConfig(beam=args.beam, verify=kind == "verified", screened=args.screened,
                                   siblings=args.siblings, branch_period=args.branch_period, rank=args.rank)
            for first in range(0, len(todo), args.batch):
                seeds = todo[first:first + args.batch]
                start = time.perf_counter()
                found = search_ceiling(scenario, seeds, config)
                seconds = time.perf_counter() - start
                with path.open("a", encoding="utf-8") as rows:
                    for result in found:
                        row = {"scenario": name, "kind": kind, "driver": config.driver_spec, **result._asdict(),
                               "seconds": seconds / len(seeds), **settings_of(args)}
                        rows.write(json.dumps(row) + "\n")
                print(f"{name} {kind} seeds {seeds[0]}..{seeds[-1]}: {seconds:.0f} s; ceiling speed "
                      + " ".join(f"{r.mean_speed:.2f}" for r in found) + "; driver "
                      + " ".join(f"{r.driver_mean_speed:.2f}" for r in found) + "; task return ceiling "
                      + " ".join(f"{r.task_return:.1f}" for r in found) + ", driver "
                      + " ".join(f"{r.driver_task_return:.1f}" for r in found), flush=True)
    wanted = set(args.scenarios), set(args.kinds), set(args.seeds)
    rows = [row for row in read_rows(path)
            if row["scenario"] in wanted[0] and row["kind"] in wanted[1] and row["seed"] in wanted[2]]
    table = summarize(rows)
    (args.out / "summary.json").write_text(json.dumps({"settings": settings_of(args), "table": table,
                                                       "cpu_count": os.cpu_count()}, indent=2) + "\n", encoding="utf-8")
    print(format_table(table))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
