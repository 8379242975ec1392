"""What a fixed goal choice earns behind the verified layer (issue 67, the cruise line).

Each policy asks for the same discrete action at every decision (lane offset x speed of the
recipe's goal grid, or the expert), behind the layer as the agents are; the episodes run through
the runner on named tuning seeds and report highway-env's task return, paired per seed against
always-defer (the expert action). It says which goals a learner would have to find.

    python docs/experiments/2026-11-29-rl-grid/fixed_goals.py --config cruise_task --scenario cruise \
        --seeds 90100-90163 --duration 40 --out docs/experiments/2026-11-29-rl-grid/fixed_goals_cruise.txt
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import statistics
from pathlib import Path

from mmpc.cli.arguments import seed_list
from mmpc.config import load_config
from mmpc.highway.runner import run_lockstep
from mmpc.rl.config import RLConfig
from mmpc.rl.driver import ExpertChoice, SafeAgentDriver
from mmpc.rl.runs import TrainedRun
from mmpc.scenario import load_scenario


def mean_band(values: list[float]) -> tuple[float, float]:
    """Mean and the half-width of its normal 95 % interval."""
    return statistics.fmean(values), 1.96 * statistics.stdev(values) / math.sqrt(len(values))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="cruise_task", help="RL recipe: its goal grid and layer")
    parser.add_argument("--scenario", default="cruise")
    parser.add_argument("--seeds", default="90100-90163")
    parser.add_argument("--duration", type=float, default=40.0)
    parser.add_argument("--sim", default="batched", choices=("batched", "highway-env"), help="the world")
    parser.add_argument("--actions", default=None, help="comma-separated action indices (default: every goal)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()

    scenario = dataclasses.replace(load_scenario(args.scenario), duration=args.duration, sim=args.sim)
    seeds = seed_list(args.seeds)
    recipe = load_config(RLConfig, args.config)
    env = dataclasses.replace(recipe.env, replan="decision", expert_action=True)
    run = TrainedRun(None, "stand-in", "safe", False, dataclasses.replace(recipe, scenario=scenario, env=env))
    goals = [(offset, speed) for offset in env.lane_offsets for speed in env.speeds]
    actions = [int(a) for a in args.actions.split(",")] if args.actions else list(range(len(goals)))

    def drive(action: int) -> list[dict]:
        driver = SafeAgentDriver(run._replace(model=ExpertChoice(action)), scenario)
        return [r.metrics for r in run_lockstep(scenario, seeds, driver=driver)]

    base = drive(len(goals))
    lines = [f"{args.scenario}, {args.config}, seeds {args.seeds} x {args.duration:g} s, {args.sim}, behind the verified layer",
             f"{'policy':<26} {'task return':>18} {'vs always-defer':>22} {'speed':>7} {'collisions':>10} {'to right lane':>13}"]

    def row(name: str, metrics: list[dict]) -> str:
        ret = [m["task_return"] for m in metrics]
        diff = [m["task_return"] - b["task_return"] for m, b in zip(metrics, base)]
        (mean, band), (dmean, dband) = mean_band(ret), mean_band(diff)
        ref = statistics.fmean(b["task_return"] for b in base)
        speed = statistics.fmean(m["mean_speed"] for m in metrics)
        collisions = sum(m["collisions"] for m in metrics)
        right = statistics.fmean(m["right_lane_distance_mean"] for m in metrics)
        return (f"{name:<26} {mean:8.1f} +- {band:5.1f}   {100 * dmean / ref:+6.1f} % +- {100 * dband / ref:4.1f}"
                f" {speed:7.2f} {collisions:10d} {right:11.1f} m")

    lines.append(row("always defer (expert)", base))
    print("\n".join(lines), flush=True)
    for action in actions:
        offset, speed = goals[action]
        lines.append(row(f"offset {offset:+d}, {speed:g} m/s", drive(action)))
        print(lines[-1], flush=True)
    if args.out:
        args.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
