"""``mmpc evaluate``: drivers x scenarios x seeds on this machine or a Ray cluster (see
:mod:`mmpc.evaluate`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mmpc.cli.arguments import (add_compile, add_device, add_set, add_sim, apply_compile, driver_help, driver_specs,
                                 scenario_overrides, seed_list)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from mmpc.config import ConfigError
    from mmpc.evaluate import EvaluationConfig, EvaluationFolderError, evaluate, format_table, read_episodes
    from mmpc.evaluate.evaluation import check_scenarios
    from mmpc.files import OutputFolderError
    from mmpc.scenario import load_scenario

    apply_compile(args.compile)
    drivers = driver_specs(args.driver or ["mpc"])
    if not drivers:
        print("mmpc evaluate: error: --driver needs at least one driver spec", file=sys.stderr)
        return 2
    scenarios = []
    for name in (n for n in args.scenarios.split(",") if n):
        scenario = load_scenario(name, scenario_overrides(args))
        scenarios.append(scenario if args.duration is None else scenario.replace(duration=args.duration))
    if not scenarios:
        print("mmpc evaluate: error: --scenarios needs at least one scenario", file=sys.stderr)
        return 2
    try:  # before the output folder is made
        check_scenarios(scenarios)
    except ConfigError as error:  # it names the scenarios as loaded; say what was given
        raise ConfigError(f"--scenarios {args.scenarios}: {error}") from error
    if args.workers is None and args.ray is None:
        args.workers = 1
    if args.collision_videos and not args.episode_outputs:
        print("mmpc evaluate: error: --collision-videos needs --episode-outputs", file=sys.stderr)
        return 2
    if args.collision_videos and any(s.sim == "batched" for s in scenarios):
        print("mmpc evaluate: error: --collision-videos replays episodes in highway-env; the batched simulator "
              "draws none (run with --sim highway-env, or without --collision-videos)", file=sys.stderr)
        return 2
    try:
        config = EvaluationConfig(
            drivers=drivers, seeds=args.seeds, workers=args.workers, threads=args.threads, lockstep=args.lockstep,
            ray=args.ray, retries=args.retries,
            episode_layout="episodes/{driver}/{scenario}/seed_{seed}" if args.episode_outputs else None,
            collision_videos=args.collision_videos,
        )
    except ValueError as error:
        print(f"mmpc evaluate: error: {error}", file=sys.stderr)
        return 2
    out = Path(args.out)
    wanted = {(d, s.name, seed) for d in drivers for s in scenarios for seed in args.seeds}
    try:
        earlier = read_episodes(out / "episodes.csv")
    except EvaluationFolderError as error:
        print(f"mmpc evaluate: error: {error}", file=sys.stderr)
        return 2
    finished = {(r["driver"], r["scenario"], r["seed"]) for r in earlier if r["status"] == "ok"}
    with tqdm(total=len(wanted), initial=len(wanted & finished), desc="episodes", unit="ep") as bar:
        def progress(row: dict) -> None:
            bar.update(1)
            bar.set_postfix_str(f"{row['driver']} {row['scenario']} seed {row['seed']}: {row['status']}")

        try:
            evaluation = evaluate(scenarios, out, config, on_episode=progress)
        # a driver that cannot be built, scenarios.json damaged, of other scenarios or driver files, or another
        # evaluation writing there: the bar goes, the reason stays
        except (ConfigError, EvaluationFolderError, OutputFolderError) as error:
            bar.leave = False
            bar.close()
            print(f"mmpc evaluate: error: {error}", file=sys.stderr)
            return 2
    print(format_table(evaluation.summary))
    print(f"wrote {out / 'episodes.csv'}, {out / 'summary.json'}, {out / 'summary.md'}, {out / 'compare.png'} and "
          f"TensorBoard scalars under {out / 'tensorboard'}")
    errors = sum(entry["errors"] for entry in evaluation.summary)
    if errors:
        print(f"{errors} episodes ended in an error (rows with status=error); run the same command again to retry them",
              file=sys.stderr)
        return 1
    return 0


def add_subcommand(subparsers: argparse._SubParsersAction) -> None:
    """Add ``mmpc evaluate``."""
    parser = subparsers.add_parser(
        "evaluate", help="drivers x scenarios x seeds in parallel (local processes or Ray): episodes.csv, summary with 95%% "
                         "intervals, table, plot, TensorBoard; resumable",
    )
    parser.add_argument("--driver", action="append", metavar="SPEC",
                        help=f"driver(s), comma-separated or repeated; several give a side-by-side table (default mpc): "
                             f"{driver_help()}")
    parser.add_argument("--scenarios", "--config", default="cruise,high_speed", metavar="NAMES_OR_PATHS",
                        help="the scenario configs: comma-separated names in configs/scenarios or YAML paths, each with "
                             "its own name (default cruise,high_speed)")
    parser.add_argument("--seeds", type=seed_list, default=tuple(range(20)), help="seeds such as 0-999 or 0,3,7 (default 0-19)")
    parser.add_argument("--workers", type=int, default=None,
                        help="tasks in flight: local processes (default 1: in this process) or Ray tasks "
                             "(default with --ray: the cluster's CPUs)")
    parser.add_argument("--ray", default=None, metavar="ADDRESS",
                        help="run the tasks on Ray: auto (the running cluster), host:port, ray://host:port, or local "
                             "(start a local Ray with --workers CPUs); needs mmpc[ray]")
    parser.add_argument("--lockstep", type=int, default=8,
                        help="episodes driven together in one task, one driver call per step for all of them; groups are "
                             "seed // lockstep, whatever the backend (default 8)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads per task (default 1)")
    parser.add_argument("--retries", type=int, default=1,
                        help="re-runs of a group whose worker process died before it is recorded as errors (default 1)")
    parser.add_argument("--duration", type=float, default=None, help="episode length [s] (default: the scenario's)")
    add_set(parser, "scenarios", example=", as in mmpc drive")
    add_sim(parser)
    add_compile(parser)
    add_device(parser)
    parser.add_argument("--episode-outputs", action="store_true",
                        help="also write metrics.json, steps.csv and topdown.png per episode under OUT/episodes/")
    parser.add_argument("--collision-videos", action="store_true",
                        help="with --episode-outputs: replay episodes that collided with a video")
    parser.add_argument("--out", default="runs/evaluate", help="output folder; an earlier run there is resumed (default runs/evaluate)")
    parser.set_defaults(func=run, kept="the finished episodes are kept in {out}/episodes.csv")
