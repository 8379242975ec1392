"""Evaluation benchmark: episodes per minute with 1 and more local workers, and lockstep
batching (one driver call per step for E episodes) against one call per episode.

Both comparisons run side by side in one process on the same seeds, each from an empty output
folder; the machine load (``os.getloadavg``) is recorded before and after, since the ratios
depend on free cores. Wall times include everything the user waits for: starting the worker
processes (``workers > 1``; one worker runs in this process), building drivers, simulating,
solving and writing ``episodes.csv``. ``steady`` rates leave the start-up out: completed
episodes after the first one per worker over the time from the first completion to the last.
"""

from __future__ import annotations

import argparse
import sys
import json
import os
import platform
import statistics
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import torch

from mmpc.cli.arguments import compile_at_once, int_list
from mmpc.evaluate import EvaluationConfig, evaluate
from mmpc.scenario import load_scenario


@dataclass(frozen=True)
class EvaluateBenchmark:
    """What to measure.

    Attributes:
        scenario: shipped scenario name or YAML path.
        duration: episode length [s] (simulated).
        driver: driver spec.
        episodes: episodes per throughput row (seeds 0 .. episodes-1).
        workers: worker counts of the throughput rows (1 runs in this process).
        rounds: throughput rounds; each runs every worker count once (alternating, so a change
            of machine load hits all counts alike); speedups are medians over rounds.
        lockstep: E, the concurrent episodes of the lockstep comparison (0 skips it).
        threads: torch threads per task.
    """

    scenario: str = "cruise"
    duration: float = 5.0
    driver: str = "mpc"
    episodes: int = 16
    workers: tuple[int, ...] = (1, 2)
    rounds: int = 1
    lockstep: int = 16
    threads: int = 1

    def __post_init__(self) -> None:
        if not self.duration > 0:
            raise ValueError(f"`duration` must be > 0 s; got {self.duration}")
        if self.episodes < 1 or not self.workers or min(self.workers) < 1:
            raise ValueError(f"`episodes` and `workers` must be >= 1; got {self.episodes}, {self.workers}")
        if self.rounds < 1:
            raise ValueError(f"`rounds` must be >= 1; got {self.rounds}")
        if self.lockstep < 0 or self.threads < 1:
            raise ValueError(f"`lockstep` must be >= 0 and `threads` >= 1; got {self.lockstep}, {self.threads}")


def _timed(scenario, config: EvaluationConfig, folder: Path) -> dict:
    """One evaluation from an empty folder: wall time, completion times, rows."""
    finished: list[float] = []
    start = time.perf_counter()
    evaluation = evaluate([scenario], folder, config, on_episode=lambda row: finished.append(time.perf_counter() - start))
    wall = time.perf_counter() - start
    errors = [row for row in evaluation.rows if row["status"] != "ok"]
    if errors:
        raise RuntimeError(f"benchmark episodes failed: {errors[0]['error']}")
    return {"wall": wall, "finished": sorted(finished), "rows": evaluation.rows}


def _steady_rate(finished: list[float], workers: int) -> float:
    """Episodes per minute after start-up: the episodes after each worker's first, over the time
    from the first completion to the last."""
    if len(finished) <= workers or finished[-1] <= finished[workers - 1]:
        return float("nan")
    return 60.0 * (len(finished) - workers) / (finished[-1] - finished[workers - 1])


def run(spec: EvaluateBenchmark, out: Path) -> dict:
    """Run the benchmark; write ``bench_evaluate.json`` into ``out``; return the report."""
    scenario = load_scenario(spec.scenario).replace(duration=spec.duration)
    torch.set_num_threads(spec.threads)
    report: dict = {
        "spec": {**spec.__dict__, "workers": list(spec.workers)},
        "machine": {"platform": platform.platform(), "processor": platform.processor(), "cpus": os.cpu_count(),
                    "torch": torch.__version__},
        "load_before": list(os.getloadavg()),
        "throughput": [],
    }
    seeds = tuple(range(spec.episodes))
    with tempfile.TemporaryDirectory(prefix="bench_evaluate_") as scratch:
        for round_ in range(spec.rounds):
            order = spec.workers if round_ % 2 == 0 else tuple(reversed(spec.workers))
            for workers in order:
                timing = _timed(scenario, EvaluationConfig(drivers=(spec.driver,), seeds=seeds, workers=workers,
                                                           threads=spec.threads, lockstep=1, report=False),
                                Path(scratch) / f"round_{round_}_workers_{workers}")
                report["throughput"].append({
                    "round": round_, "workers": workers, "episodes": spec.episodes, "wall_s": timing["wall"],
                    "episodes_per_min": 60.0 * spec.episodes / timing["wall"],
                    "steady_episodes_per_min": _steady_rate(timing["finished"], workers),
                    "first_episode_s": timing["finished"][0], "load_1min": os.getloadavg()[0],
                })
        if spec.lockstep:
            rows = {}
            lock_seeds = tuple(range(spec.lockstep))
            for label, group in (("one_call_per_episode", 1), ("lockstep", spec.lockstep)):
                timing = _timed(scenario, EvaluationConfig(drivers=(spec.driver,), seeds=lock_seeds, workers=1,
                                                           threads=spec.threads, lockstep=group, report=False),
                                Path(scratch) / label)
                rows[label] = {
                    "episodes": spec.lockstep, "group": group, "wall_s": timing["wall"],
                    "s_per_episode": timing["wall"] / spec.lockstep,
                    "solve_ms_per_episode_step": sum(r["solve_ms_per_episode_mean"] for r in timing["rows"]) / spec.lockstep,
                    "solve_ms_per_call": sum(r["solve_ms_mean"] for r in timing["rows"]) / spec.lockstep,
                    "mean_speed": [r["mean_speed"] for r in timing["rows"]],
                }
            one, batched = rows["one_call_per_episode"], rows["lockstep"]
            report["lockstep"] = {
                **rows,
                "speedup_per_episode": one["s_per_episode"] / batched["s_per_episode"],
                "solve_speedup_per_episode_step": one["solve_ms_per_episode_step"] / batched["solve_ms_per_episode_step"],
                "max_mean_speed_difference": max(abs(a - b) for a, b in zip(one["mean_speed"], batched["mean_speed"])),
            }
    for row in report["throughput"]:
        base = next((b for b in report["throughput"] if b["workers"] == 1 and b["round"] == row["round"]), None)
        if base is not None:
            row["speedup"] = row["episodes_per_min"] / base["episodes_per_min"]
            row["steady_speedup"] = row["steady_episodes_per_min"] / base["steady_episodes_per_min"]
    report["speedup_median"] = {
        str(workers): statistics.median(r["speedup"] for r in report["throughput"] if r["workers"] == workers and "speedup" in r)
        for workers in spec.workers if any(r["workers"] == workers and "speedup" in r for r in report["throughput"])
    }
    report["load_after"] = list(os.getloadavg())
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_evaluate.json").write_text(json.dumps(report, indent=2) + "\n")
    return report


def format_report(report: dict) -> str:
    """The benchmark as a plain-text table."""
    spec = report["spec"]
    lines = [
        f"evaluation benchmark: {spec['driver']} on {spec['scenario']}, {spec['duration']:g} s episodes, "
        f"{spec['threads']} torch thread(s) per task; load {report['load_before'][0]:.2f} before, "
        f"{report['load_after'][0]:.2f} after (1-min average, {report['machine']['cpus']} CPUs)",
        "",
        f"{'round':>5} {'workers':>7} {'episodes':>8} {'wall s':>8} {'ep/min':>8} {'speedup':>8} {'steady ep/min':>14} "
        f"{'steady speedup':>15} {'load':>5}",
    ]
    for row in report["throughput"]:
        lines.append(f"{row['round']:>5d} {row['workers']:>7d} {row['episodes']:>8d} {row['wall_s']:>8.1f} "
                     f"{row['episodes_per_min']:>8.1f} {row.get('speedup', float('nan')):>8.2f} "
                     f"{row['steady_episodes_per_min']:>14.1f} {row.get('steady_speedup', float('nan')):>15.2f} "
                     f"{row['load_1min']:>5.2f}")
    lines.append("median speedup over rounds: " + ", ".join(f"{w} workers {v:.2f}x" for w, v in report["speedup_median"].items()))
    if "lockstep" in report:
        lock = report["lockstep"]
        lines += ["", f"{'':<22} {'episodes':>8} {'wall s':>8} {'s/episode':>10} {'solve ms/ep-step':>17} {'ms/call':>8}"]
        for label in ("one_call_per_episode", "lockstep"):
            row = lock[label]
            lines.append(f"{label + ' (' + str(row['group']) + ')':<22} {row['episodes']:>8d} {row['wall_s']:>8.1f} "
                         f"{row['s_per_episode']:>10.2f} {row['solve_ms_per_episode_step']:>17.1f} {row['solve_ms_per_call']:>8.1f}")
        lines.append(f"lockstep speedup per episode: {lock['speedup_per_episode']:.2f}x (solve time per episode-step "
                     f"{lock['solve_speedup_per_episode_step']:.2f}x); largest mean-speed difference between the two "
                     f"{lock['max_mean_speed_difference']:.2e} m/s")
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> int:
    bench = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    bench.add_argument("--scenario", default="cruise", help="scenario (default cruise)")
    bench.add_argument("--duration", type=float, default=5.0, help="episode length [s] (default 5)")
    bench.add_argument("--driver", default="mpc", help="driver spec (default mpc)")
    bench.add_argument("--episodes", type=int, default=16, help="episodes per throughput row (default 16)")
    bench.add_argument("--workers", dest="worker_counts", type=int_list, default=(1, 2),
                       help="comma-separated worker counts (default 1,2)")
    bench.add_argument("--rounds", type=int, default=1, help="throughput rounds, worker counts alternating (default 1)")
    bench.add_argument("--lockstep", type=int, default=16, help="concurrent episodes of the lockstep comparison (0 skips)")
    bench.add_argument("--threads", type=int, default=1, help="torch threads per task (default 1)")
    bench.add_argument("--out", default="runs/bench_evaluate", help="output folder for bench_evaluate.json")
    args = bench.parse_args(argv)
    compile_at_once()
    try:
        spec = EvaluateBenchmark(scenario=args.scenario, duration=args.duration, driver=args.driver, episodes=args.episodes,
                                 workers=args.worker_counts, rounds=args.rounds, lockstep=args.lockstep, threads=args.threads)
    except ValueError as error:
        print(f"bench_evaluate: error: {error}", file=sys.stderr)
        return 2
    report = run(spec, Path(args.out))
    print(format_report(report))
    print(f"wrote {Path(args.out) / 'bench_evaluate.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
