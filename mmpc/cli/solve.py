"""``mmpc solve``: one batch solve of the built-in demo scene; a table of the candidates, a plot and JSON."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from mmpc.cli.arguments import add_config, unwritable
from mmpc.config import load_config
from mmpc.goals import CruiseGoals, HighSpeedGoals
from mmpc.meta_costs import CruiseCost, HighSpeedCost
from mmpc.plotting import plot_candidates
from mmpc.problem import ProblemBatch
from mmpc.ranking import select_best
from mmpc.result import Status
from mmpc.scenes import demo_scene
from mmpc.solver.config import OptimizerConfig
from mmpc.solver.optimizer import BatchOptimizer


def run(args: argparse.Namespace) -> int:
    """One batch solve of the built-in demo scene; table + plot + JSON."""
    dtype = {"float32": torch.float32, "float64": torch.float64}[args.dtype]
    config = load_config(OptimizerConfig, args.config, dict(args.set))
    out = Path(args.out)
    problem = unwritable(out)  # before solving: the outputs are written at the end
    if problem is not None:
        print(f"mmpc solve: error: --out {out} must be a folder this process can create and write to; got {problem}",
              file=sys.stderr)
        return 2
    optimizer = BatchOptimizer(config, dtype=dtype)
    scene = demo_scene(optimizer.config.num_steps, optimizer.config.horizon)
    if args.scenario == "cruise":
        sampler, meta_cost = CruiseGoals(v_cruise=15.0, horizon=optimizer.config.horizon, num_goals=args.goals), CruiseCost(15.0)
    else:
        sampler, meta_cost = HighSpeedGoals(num_goals=args.goals), HighSpeedCost(24.0)
    ego = scene.problem.ego.to(dtype)
    problem = ProblemBatch(ego, sampler(ego, scene.road), scene.problem.obstacles.to(dtype))
    with torch.inference_mode():
        result = optimizer(problem)
        cost = meta_cost(result.trajectories, scene.road)
        best = select_best(result, cost, optimizer.config)
    best_index = int(best.index[0])

    header = f"{'goal':>4} {'x [m]':>8} {'y [m]':>6} {'status':<24} {'meta cost':>10} {'min dist':>8} {'res obs':>9} {'res nonhol':>10} {'res acc':>9}"
    print(f"mmpc solve: {scene.name}; scenario {args.scenario}; {args.goals} goals, "
          f"{problem.obstacles.shape[1]} obstacles, {optimizer.config.iterations} iterations")
    print(header)
    print("-" * len(header))
    rows = []
    for g in range(problem.goals.shape[1]):
        row = {
            "goal": g,
            "goal_x": float(problem.goals[0, g, 0]),
            "goal_y": float(problem.goals[0, g, 1]),
            "status": Status.describe(int(result.status[0, g])),
            "meta_cost": float(cost[0, g]),
            "min_obstacle_distance": float(result.min_obstacle_distance[0, g]),
            "residual_obstacle": float(result.residual_obstacle[0, g]),
            "residual_nonholonomic": float(result.residual_nonholonomic[0, g]),
            "residual_acceleration": float(result.residual_acceleration[0, g]),
            "best": g == best_index,
        }
        rows.append(row)
        marker = " <- best" if row["best"] else ""
        print(f"{g:>4} {row['goal_x']:8.1f} {row['goal_y']:6.1f} {row['status']:<24} {row['meta_cost']:10.2f} "
              f"{row['min_obstacle_distance']:8.3f} {row['residual_obstacle']:9.2e} {row['residual_nonholonomic']:10.2e} "
              f"{row['residual_acceleration']:9.2e}{marker}")
    verdict = "feasible" if bool(best.feasible[0]) else "NO feasible candidate: least-infeasible fallback"
    print(f"best: goal {best_index} ({verdict}), meta cost {float(best.cost[0]):.2f}")

    plot = plot_candidates(out / "solve.png", problem, result, scene.road, best=best_index,
                           ellipse=optimizer.config.ellipse,
                           title=f"mmpc solve ({args.scenario}): {args.goals} goal-directed optimizations, best in red")
    (out / "solve.json").write_text(json.dumps({"scenario": args.scenario, "best": best_index,
                                                "best_feasible": bool(best.feasible[0]), "candidates": rows}, indent=2))
    print(f"wrote {plot} and {out / 'solve.json'}")
    return 0


def add_subcommand(sub: argparse._SubParsersAction) -> None:
    """Add ``mmpc solve``."""
    solve = sub.add_parser("solve", help="solve the built-in demo scene once: table of candidates + plot")
    solve.add_argument("--scenario", choices=("cruise", "high_speed"), default="cruise",
                       help="goal sampler and meta cost (default cruise)")
    solve.add_argument("--goals", type=int, default=11, help="number of goals G (default 11)")
    solve.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    add_config(solve, "optimizer config (mmpc.OptimizerConfig)")
    solve.add_argument("--out", default="runs/solve", help="output folder for solve.png and solve.json")
    solve.set_defaults(func=run)
