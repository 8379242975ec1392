"""Which goals the expert drives: per goal of the scenario's set, how often it is chosen, how often
the solver finds it feasible, and in how many steps it was the only feasible goal (without it the
step would have fallen back). Table and JSON.

    python scripts/goal_usage.py --scenario high_speed --seeds 70000-70063 --out runs/goal_usage

Episodes run in one lockstep group on the batched simulator (IDM traffic) with the compiled expert.
Goals are labelled by family: the sampler's base goals, the near-lane goals (slot j of the window
of lanes around the ego, at each average speed) and the stop goals (slot j of their lanes).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from mmpc.cli.arguments import compile_at_once, seed_list
from mmpc.goals import NearLaneGoals
from mmpc.highway.runner import Observer, run_lockstep
from mmpc.scenario import ScenarioConfig, load_scenario


def goal_labels(scenario: ScenarioConfig, num_goals: int) -> list[str]:
    """One label per goal of the MPC's set (the sampler's goals, then the stop goals)."""
    sampler = scenario.objective.goal_sampler(scenario.road, scenario.optimizer.horizon)
    labels: list[str] = []
    if isinstance(sampler, NearLaneGoals):
        base = sampler.base(torch.zeros(1, 6), scenario.road).shape[1]
        slots = scenario.lanes if sampler.lanes_around is None else min(2 * sampler.lanes_around + 1, scenario.lanes)
        labels += [f"base {k}" for k in range(base)]
        labels += [f"near-lane slot {slot} at {speed:g} m/s" for slot in range(slots) for speed in sampler.speeds]
    else:
        labels += [f"base {k}" for k in range(sampler(torch.zeros(1, 6), scenario.road).shape[1])]
    labels += [f"stop slot {k}" for k in range(num_goals - len(labels))]
    return labels


class _Usage(Observer):
    """The chosen goal and the solver's feasible set of every decision."""

    def __init__(self) -> None:
        self.chosen: list[np.ndarray] = []
        self.feasible: list[np.ndarray] = []
        self.fallback: list[np.ndarray] = []

    def decided(self, observation, decision, active) -> None:
        self.chosen.append(decision.goal_index.numpy().copy())
        self.feasible.append(decision.candidates.feasible.cpu().numpy().copy())
        self.fallback.append(decision.fallback.numpy().copy())


def measure(scenario: ScenarioConfig, seeds: Sequence[int]) -> dict:
    """Drive ``seeds`` in lockstep and count, per goal, choices, feasibility and sole feasibility."""
    usage = _Usage()
    results = run_lockstep(scenario, list(seeds), observers=[usage])
    chosen, feasible = np.concatenate(usage.chosen), np.concatenate(usage.feasible)  # (steps,), (steps, G)
    fallback = np.concatenate(usage.fallback)
    driven = chosen[~fallback]
    only = feasible & (feasible.sum(axis=1, keepdims=True) == 1)
    labels = goal_labels(scenario, feasible.shape[1])
    goals = [{"goal": g, "label": label, "chosen": int((driven == g).sum()), "feasible_share": float(feasible[:, g].mean()),
              "only_feasible": int(only[:, g].sum())} for g, label in enumerate(labels)]
    return {"scenario": scenario.name, "seeds": f"{min(seeds)}-{max(seeds)}", "episodes": len(results),
            "steps": int(chosen.size), "fallback_steps": int(fallback.sum()),
            "collisions": int(sum(r.metrics["collisions"] for r in results)), "goals": goals}


def format_table(report: dict) -> str:
    steps = max(report["steps"], 1)
    lines = [f"{report['scenario']}, seeds {report['seeds']}: {report['steps']} steps, {report['fallback_steps']} fallback "
             f"steps, {report['collisions']} collisions", "| goal | label | chosen | chosen % | feasible % | only feasible |",
             "|---:|---|---:|---:|---:|---:|"]
    lines += [f"| {g['goal']} | {g['label']} | {g['chosen']} | {100 * g['chosen'] / steps:.1f} | {100 * g['feasible_share']:.1f} "
              f"| {g['only_feasible']} |" for g in report["goals"]]
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="high_speed", help="scenario name or YAML path (IDM traffic)")
    parser.add_argument("--seeds", type=seed_list, default=tuple(range(70000, 70064)), help="episode seeds (default 70000-70063)")
    parser.add_argument("--duration", type=float, default=None, help="episode length [s] (default: the scenario's)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--out", default="runs/goal_usage", help="folder of goal_usage_<scenario>.json")
    args = parser.parse_args(argv)
    compile_at_once()
    torch.set_num_threads(args.threads)
    scenario = load_scenario(args.scenario, {"sim": "batched"})
    if args.duration is not None:
        scenario = scenario.replace(duration=args.duration)
    report = measure(scenario, args.seeds)
    print(format_table(report))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"goal_usage_{scenario.name}.json"
    path.write_text(json.dumps(report, indent=1) + "\n")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
