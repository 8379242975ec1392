"""``mmpc drive``: one closed-loop episode (highway-env by default) (metrics, steps.csv, video, top-down plot), or
with ``--seeds`` an evaluation over seeds with one folder per episode."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from mmpc.cli.arguments import (add_compile, add_device, add_set, add_sim, apply_compile, driver_help, scenario_overrides,
                                 seed_list, unwritable)
from mmpc.collisions import CRASH_COLUMNS


def run(args: argparse.Namespace) -> int:
    """One episode (video, table, outputs) or, with --seeds, an evaluation over seeds."""
    from tqdm import tqdm

    from mmpc.config import ConfigError
    from mmpc.evaluate.evaluation import build_driver, check_drivers, check_scenarios
    from mmpc.scenario import load_scenario

    if args.seed is not None and args.seeds is not None:
        print("mmpc drive: error: give --seed (one episode) or --seeds (an evaluation), not both", file=sys.stderr)
        return 2
    torch.set_num_threads(args.threads)
    apply_compile(args.compile)
    scenarios = []
    for name in args.scenario.split(","):
        scenario = load_scenario(name, scenario_overrides(args))
        if args.duration is not None:
            scenario = scenario.replace(duration=args.duration)
        scenarios.append(scenario)
    try:  # before the output folder is made
        check_scenarios(scenarios)
        if args.seeds is None and len(scenarios) == 1:  # one episode: the driver built here drives it
            driver = build_driver(args.driver, scenarios[0])
        else:
            check_drivers(scenarios, (args.driver,))
    except ConfigError as error:
        print(f"mmpc drive: error: {error}", file=sys.stderr)
        return 2
    out = Path(args.out)
    problem = unwritable(out)  # before driving: an episode's outputs are written at its end
    if problem is not None:
        print(f"mmpc drive: error: --out {out} must be a folder this process can create and write to; got {problem}",
              file=sys.stderr)
        return 2
    if args.seeds is not None:
        from mmpc.evaluate import EvaluationConfig, EvaluationFolderError, evaluate, format_table

        episodes = len(scenarios) * len(args.seeds)
        config = EvaluationConfig(drivers=(args.driver,), seeds=args.seeds, workers=args.workers, threads=args.threads,
                                  episode_layout="{scenario}/seed_{seed}", report=False,
                                  collision_videos=all(s.sim == "highway-env" for s in scenarios))
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
    from mmpc.highway.runner import Observer, run_episode, write_outputs

    class Progress(Observer):
        def applied(self, step) -> None:
            bar.update(1)

    scenario = scenarios[0]
    seed = scenario.seeds[0] if args.seed is None else args.seed
    video = None if args.no_video or scenario.sim == "batched" else out / "episode.mp4"
    if video is None and not args.no_video:
        print("mmpc drive: no video on the batched simulator (highway-env draws it; --sim highway-env)", file=sys.stderr)
    steps = round(scenario.duration * scenario.frequency)
    with tqdm(total=steps, desc=f"{scenario.name} seed {seed}", unit="step") as bar:
        result = run_episode(scenario, seed, driver=driver, video=video, observers=[Progress()])
    paths = write_outputs(result, out)
    shown = {key: value for key, value in result.metrics.items() if not (key in CRASH_COLUMNS and value is None)}
    width = max(map(len, shown))
    for key, value in shown.items():  # the crash's scene only after a crash
        print(f"{key:<{width}}  {value:.3f}" if isinstance(value, float) else f"{key:<{width}}  {value}")
    print("wrote " + ", ".join(str(p) for p in paths + ([video] if video else [])))
    return 0


def add_subcommand(sub: argparse._SubParsersAction) -> None:
    """Add ``mmpc drive``."""
    drive = sub.add_parser("drive", help="closed-loop highway-env episode: metrics, steps.csv, video, top-down plot")
    drive.add_argument("--scenario", "--config", default="cruise", metavar="NAME_OR_PATH",
                       help="the scenario config: a name in configs/scenarios (cruise, high_speed, ...) or a YAML path; "
                            "comma-separated with --seeds (default cruise)")
    drive.add_argument("--driver", default="mpc", metavar="SPEC", help=f"who drives (default mpc): {driver_help()}")
    drive.add_argument("--seed", type=int, default=None, help="episode seed (default: the scenario's first seed)")
    drive.add_argument("--seeds", type=seed_list, default=None,
                       help="evaluate these seeds instead (e.g. 0-19): a table, summary.json, one folder per episode, "
                            "a video only for episodes with a collision")
    drive.add_argument("--duration", type=float, default=None, help="episode length [s] (default: the scenario's)")
    add_set(drive, "scenario", example=", e.g. highway-env's own faster traffic: "
                                       "--set traffic.target_speeds=null --set name=cruise_default_traffic")
    add_sim(drive)
    add_compile(drive)
    add_device(drive)
    drive.add_argument("--no-video", action="store_true", help="skip episode.mp4 (single episode)")
    drive.add_argument("--workers", type=int, default=1, help="parallel episodes with --seeds (default 1)")
    drive.add_argument("--threads", type=int, default=1, help="torch threads per episode (default 1)")
    drive.add_argument("--out", default="runs/drive", help="output folder (default runs/drive)")
    drive.set_defaults(func=run)
