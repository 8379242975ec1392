"""The ``mmpc`` command line: ``mmpc solve``, ``mmpc bench-solver``, ``mmpc drive``."""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import sys
import tempfile
from pathlib import Path
from typing import Optional, Sequence

import torch
import yaml

from mmpc.bench_solver import SolverBenchmark, run as run_solver_benchmark
from mmpc.config import OptimizerConfig
from mmpc.files import TEMPORARY_PREFIX
from mmpc.goals import CruiseGoals, HighSpeedGoals
from mmpc.meta_costs import CruiseCost, HighSpeedCost
from mmpc.optimizer import BatchOptimizer
from mmpc.plotting import plot_candidates
from mmpc.problem import ProblemBatch
from mmpc.ranking import select_best
from mmpc.result import Status
from mmpc.scenes import demo_scene


#: Modules that add their own subcommands: each has ``add_subcommands(subparsers)`` and keeps
#: its heavy imports (CasADi, Ray, stable-baselines3, Minari) inside the command functions.
COMMAND_MODULES: tuple[str, ...] = ("mmpc.evaluate_cli", "mmpc.imitation.cli", "mmpc.rl.cli", "mmpc.bench")


def _int_list(text: str) -> tuple[int, ...]:
    try:
        values = tuple(int(v) for v in text.split(",") if v)
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers; got {text!r}") from error
    if not values or min(values) < 0:
        raise argparse.ArgumentTypeError(f"expected non-negative integers; got {text!r}")
    return values


def _seed_list(text: str) -> tuple[int, ...]:
    """``"0-19"``, ``"0,3,7"`` or a mix (``"0-4,9"``) -> seeds."""
    seeds: list[int] = []
    try:
        for part in (p for p in text.split(",") if p):
            low, _, high = part.partition("-")
            seeds.extend(range(int(low), int(high) + 1) if high else [int(low)])
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"expected seeds like 0-19 or 0,3,7; got {text!r}") from error
    if not seeds or min(seeds) < 0:
        raise argparse.ArgumentTypeError(f"expected non-negative seeds like 0-19 or 0,3,7; got {text!r}")
    return tuple(dict.fromkeys(seeds))


def _override(text: str) -> tuple[str, object]:
    """``"traffic.lane_changes=true"`` -> ("traffic.lane_changes", True) (the value is YAML)."""
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE such as traffic.lane_changes=true; got {text!r}")
    return key, yaml.safe_load(value)


def _solve(args: argparse.Namespace) -> int:
    """One batch solve of the built-in demo scene; table + plot + JSON."""
    dtype = {"float32": torch.float32, "float64": torch.float64}[args.dtype]
    config = OptimizerConfig.from_yaml(args.config) if args.config else OptimizerConfig()
    optimizer = BatchOptimizer(config, dtype=dtype)
    scene = demo_scene(optimizer.config.num_steps, optimizer.config.horizon)
    if args.scenario == "cruise":
        sampler, meta_cost = CruiseGoals(v_cruise=15.0, num_goals=args.goals), CruiseCost(15.0)
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

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    plot = plot_candidates(out / "solve.png", problem, result, scene.road, best=best_index,
                           ellipse=(optimizer.config.ellipse_a, optimizer.config.ellipse_b),
                           title=f"mmpc solve ({args.scenario}): {args.goals} goal-directed optimizations, best in red")
    (out / "solve.json").write_text(json.dumps({"scenario": args.scenario, "best": best_index,
                                                "best_feasible": bool(best.feasible[0]), "candidates": rows}, indent=2))
    print(f"wrote {plot} and {out / 'solve.json'}")
    return 0


def _bench_solver(args: argparse.Namespace) -> int:
    spec = SolverBenchmark(
        batches=args.batches, obstacles=args.obstacles, devices=tuple(args.devices.split(",")),
        variants=tuple(args.variants.split(",")),
        threads=args.threads, repeats=args.repeats, max_seconds_per_row=args.max_seconds_per_row,
        environments=args.environments,
    )
    report = run_solver_benchmark(spec, Path(args.out))
    print(f"wrote {Path(args.out) / 'bench_solver.json'} ({len(report['rows'])} rows) and bench_solver.png")
    return 0


def _unwritable(out: Path) -> Optional[str]:
    """Why ``out`` cannot take outputs (created, then a probe file written and removed); ``None`` if it can."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=out, prefix=TEMPORARY_PREFIX):
            pass
    except OSError as error:
        return f"{type(error).__name__}: {error}"
    return None


def _drive(args: argparse.Namespace) -> int:
    """One episode (video, table, outputs) or, with --seeds, an evaluation over seeds."""
    from tqdm import tqdm

    from mmpc.scenario import load_scenario

    if args.seed is not None and args.seeds is not None:
        print("mmpc drive: error: give --seed (one episode) or --seeds (an evaluation), not both", file=sys.stderr)
        return 2
    torch.set_num_threads(args.threads)
    scenarios = []
    for name in args.scenario.split(","):
        scenario = load_scenario(name, dict(args.set))
        if args.duration is not None:
            scenario = scenario.replace(duration=args.duration)
        scenarios.append(scenario)
    out = Path(args.out)
    problem = _unwritable(out)  # before driving: an episode's outputs are written at its end
    if problem is not None:
        print(f"mmpc drive: error: --out {out} must be a folder this process can create and write to; got {problem}",
              file=sys.stderr)
        return 2
    if args.seeds is not None:
        from mmpc.evaluate import EvaluationConfig, EvaluationFolderError, evaluate, format_table

        episodes = len(scenarios) * len(args.seeds)
        config = EvaluationConfig(drivers=(args.driver,), seeds=args.seeds, workers=args.workers, threads=args.threads,
                                  episode_layout="{scenario}/seed_{seed}", collision_videos=True, report=False)
        with tqdm(total=episodes, desc="episodes", unit="ep") as bar:
            def progress(row: dict) -> None:
                bar.update(1)
                bar.set_postfix_str(f"{row['scenario']} seed {row['seed']}: {row['status']}, collisions {row['collisions']}")

            try:
                _, summary = evaluate(scenarios, out, config, on_episode=progress)
            except EvaluationFolderError as error:  # an earlier evaluation's files, damaged or of other scenarios
                bar.close()
                print(f"mmpc drive: error: {error}", file=sys.stderr)
                return 2
        print(format_table(summary))
        print(f"wrote {out / 'summary.json'}, {out / 'episodes.csv'} and one folder per episode under {out}")
        return 0
    if len(scenarios) != 1:
        print("mmpc drive: error: several scenarios need --seeds", file=sys.stderr)
        return 2
    from mmpc.drive import run_episode, write_outputs
    from mmpc.drivers import make_driver

    scenario = scenarios[0]
    driver = make_driver(args.driver, scenario)
    seed = scenario.seeds[0] if args.seed is None else args.seed
    video = None if args.no_video else out / "episode.mp4"
    steps = round(scenario.duration * scenario.frequency)
    with tqdm(total=steps, desc=f"{scenario.name} seed {seed}", unit="step") as bar:
        result = run_episode(scenario, seed, driver=driver, video=video, on_step=lambda record: bar.update(1))
    paths = write_outputs(result, out)
    width = max(map(len, result.metrics))
    for key, value in result.metrics.items():
        print(f"{key:<{width}}  {value:.3f}" if isinstance(value, float) else f"{key:<{width}}  {value}")
    print("wrote " + ", ".join(str(p) for p in paths + ([video] if video else [])))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mmpc", description="Multi-modal MPC by batch non-holonomic trajectory optimization.")
    parser.add_argument("--log-level", default="WARNING", help="logging level of the library (default WARNING)")
    sub = parser.add_subparsers(dest="command", required=True)

    solve = sub.add_parser("solve", help="solve the built-in demo scene once: table of candidates + plot")
    solve.add_argument("--scenario", choices=("cruise", "high_speed"), default="cruise",
                       help="goal sampler and meta cost (default cruise)")
    solve.add_argument("--goals", type=int, default=11, help="number of goals G (default 11)")
    solve.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    solve.add_argument("--config", default=None, help="optimizer YAML (e.g. configs/optimizer/default.yaml)")
    solve.add_argument("--out", default="runs/solve", help="output folder for solve.png and solve.json")
    solve.set_defaults(func=_solve)

    bench = sub.add_parser("bench-solver", help="ms per solve vs batch size; table, JSON, plot")
    bench.add_argument("--batches", type=_int_list, default=(1, 11, 64, 256, 1024, 4096), help="comma-separated batch sizes")
    bench.add_argument("--obstacles", type=_int_list, default=(6, 10), help="comma-separated obstacle counts")
    bench.add_argument("--devices", default="cpu,cuda", help="cpu and/or cuda (cuda skipped without a GPU)")
    bench.add_argument("--variants", default="eager,compiled", help="eager and/or compiled (torch.compile)")
    bench.add_argument("--threads", type=int, default=1, help="CPU threads (default 1)")
    bench.add_argument("--repeats", type=int, default=20, help="timed solves per row")
    bench.add_argument("--max-seconds-per-row", type=float, default=20.0, help="time budget per row")
    bench.add_argument("--environments", type=int, default=64,
                       help="E for the one-call-vs-one-call-per-environment comparison (0 skips)")
    bench.add_argument("--out", default="runs/bench_solver", help="output folder")
    bench.set_defaults(func=_bench_solver)

    drive = sub.add_parser("drive", help="closed-loop highway-env episode: metrics, steps.csv, video, top-down plot")
    drive.add_argument("--scenario", default="cruise",
                       help="name in configs/scenarios (cruise, high_speed, ...) or a YAML path; "
                            "comma-separated with --seeds (default cruise)")
    drive.add_argument("--driver", default="mpc",
                       help="who drives: mpc (default), frenet, standard-mpc, batch-nlp, bc:RUN/policy.pt, sb3:MODEL.zip")
    drive.add_argument("--seed", type=int, default=None, help="episode seed (default: the scenario's first seed)")
    drive.add_argument("--seeds", type=_seed_list, default=None,
                       help="evaluate these seeds instead (e.g. 0-19): a table, summary.json, one folder per episode, "
                            "a video only for episodes with a collision")
    drive.add_argument("--duration", type=float, default=None, help="episode length [s] (default: the scenario's)")
    drive.add_argument("--set", type=_override, action="append", default=[], metavar="KEY=VALUE",
                       help="override a scenario value (YAML; repeatable), e.g. highway-env's own faster traffic: "
                            "--set traffic.target_speeds=null --set name=cruise_default_traffic")
    drive.add_argument("--no-video", action="store_true", help="skip episode.mp4 (single episode)")
    drive.add_argument("--workers", type=int, default=1, help="parallel episodes with --seeds (default 1)")
    drive.add_argument("--threads", type=int, default=1, help="torch threads per episode (default 1)")
    drive.add_argument("--out", default="runs/drive", help="output folder (default runs/drive)")
    drive.set_defaults(func=_drive)

    for module in COMMAND_MODULES:
        importlib.import_module(module).add_subcommands(sub)
    return parser


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(levelname)s %(name)s: %(message)s")
    if getattr(args, "goals", 1) < 1:
        print("mmpc: error: --goals must be >= 1", file=sys.stderr)
        return 2
    for name in ("workers", "threads"):
        if getattr(args, name, None) is not None and getattr(args, name) < 1:
            print(f"mmpc: error: --{name} must be >= 1", file=sys.stderr)
            return 2
    if getattr(args, "duration", None) is not None and not args.duration > 0:
        print("mmpc: error: --duration must be > 0 s", file=sys.stderr)
        return 2
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
