"""``mmpc rl {train, evaluate, report}``: train stable-baselines3 agents on the safe action layer
(or on plain highway-env, the unprotected baseline), evaluate them on fixed seeds, report runs."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def add_subcommands(sub: argparse._SubParsersAction) -> None:
    """Add ``mmpc rl {train, evaluate, report}``."""
    from mmpc.cli.arguments import add_compile, add_config, add_device, add_set, add_sim
    from mmpc.rl.config import ALGORITHMS

    rl = sub.add_parser("rl", help="safe RL: train, evaluate and report stable-baselines3 agents behind the layer")
    subparsers = rl.add_subparsers(dest="rl_command", required=True)
    train = subparsers.add_parser(
        "train", help="train an SB3 agent on the safe layer (or plain highway-env): TensorBoard, checkpoints, eval.json")
    train.add_argument("--algo", choices=sorted(ALGORITHMS), required=True, help="dqn, ppo or sac")
    add_config(train, "RL config (mmpc.rl.config.RLConfig; scenario keys as scenario.KEY)")
    add_sim(train)
    add_compile(train)
    add_device(train)
    train.add_argument("--timesteps", type=int, required=True, help="agent steps, summed over the vectorized environments")
    train.add_argument("--out", required=True, help="run directory (config.yaml, tb/, checkpoints/, model.zip, eval.json)")
    train.add_argument("--env", choices=("safe", "highway"), default="safe",
                       help="safe: the agent picks goals through the safety layer (default); highway: plain highway-env")
    train.add_argument("--seed", type=int, default=0, help="seed of the model and the training environments")
    train.add_argument("--eval-episodes", type=int, default=None, help="override train.eval_episodes of the config")
    train.add_argument("--no-eval", action="store_true", help="skip the final evaluation")
    train.add_argument("--progress", action="store_true", help="show SB3's progress bar")
    train.set_defaults(func=_train)

    evaluate = subparsers.add_parser("evaluate", help="evaluate a trained run's model on its fixed evaluation seeds")
    evaluate.add_argument("--model", required=True, help="MODEL.zip written by mmpc rl train (or a checkpoint)")
    evaluate.add_argument("--episodes", type=int, default=None, help="override train.eval_episodes of the run's config")
    evaluate.add_argument("--out", default=None, help="write the summary here (default: print only)")
    add_set(evaluate, "run's RL config (not the road, observation or actions the agent was trained with)",
            example=", e.g. --set scenario.traffic.vehicles_count=30")
    add_compile(evaluate)
    add_device(evaluate)
    evaluate.set_defaults(func=_evaluate)

    report = subparsers.add_parser("report", help="TensorBoard curves (PNG) and evaluation table (markdown, JSON) of runs")
    report.add_argument("runs", nargs="+", metavar="LABEL=RUN_DIR", help="runs written by mmpc rl train, e.g. safe=runs/rl/safe_dqn")
    report.add_argument("--out", default="docs/rl", help="output folder (curves.png, results.md, results.json)")
    report.set_defaults(func=_report)


def _train(args: argparse.Namespace) -> int:
    from mmpc.cli.arguments import apply_compile
    from mmpc.config import load_config
    from mmpc.files import OutputFolderError
    from mmpc.rl.config import RLConfig
    from mmpc.rl.train import train

    if args.timesteps < 1:
        print("mmpc rl train: error: --timesteps must be >= 1", file=sys.stderr)
        return 2
    apply_compile(args.compile)
    overrides = dict(args.set)
    if args.sim is not None:
        if args.env == "highway" and args.sim == "batched":
            print("mmpc rl train: error: --env highway trains on plain highway-env; the batched simulator runs the "
                  "safe environments only (--env safe)", file=sys.stderr)
            return 2
        overrides["scenario.sim"] = args.sim
    config = load_config(RLConfig, args.config, overrides)
    if args.eval_episodes is not None:
        if args.eval_episodes < 1:
            print("mmpc rl train: error: --eval-episodes must be >= 1", file=sys.stderr)
            return 2
        config = _with_episodes(config, args.eval_episodes)
    try:
        summary = train(config, args.algo, args.timesteps, Path(args.out), env_kind=args.env, seed=args.seed,
                        progress_bar=args.progress, evaluate_after=not args.no_eval)
    except OutputFolderError as error:  # another run writes there, or an earlier run's files are there
        print(f"mmpc rl train: error: {error}", file=sys.stderr)
        return 2
    if summary:
        print(format_summary(summary))
    print(f"wrote {args.out}/model.zip, {args.out}/tb/" + ("" if args.no_eval else f", {args.out}/eval.json"))
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from mmpc.cli.arguments import apply_compile
    from mmpc.config import with_overrides
    from mmpc.rl.config import require_same_agent_inputs
    from mmpc.rl.runs import load_run
    from mmpc.rl.train import evaluate_run

    apply_compile(args.compile)
    run = load_run(args.model)
    config = with_overrides(run.config, dict(args.set))
    require_same_agent_inputs(run.config, config)
    config = config if args.episodes is None else _with_episodes(config, args.episodes)
    with tqdm(total=config.train.eval_episodes, desc="episodes", unit="ep") as bar:
        summary = evaluate_run(run.model, config, env_kind=run.env_kind, continuous=run.continuous,
                               on_episode=lambda row: bar.update(1))
    summary = {"algo": run.algo, "env": run.env_kind, "model": str(args.model), **summary}
    print(format_summary(summary))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(summary, indent=2) + "\n")
        print(f"wrote {args.out}")
    return 0


def _report(args: argparse.Namespace) -> int:
    from mmpc.rl.report import plot_curves, results_table

    runs = {}
    for item in args.runs:
        label, sep, run = item.partition("=")
        if not sep or not label or not run:
            print(f"mmpc rl report: error: expected LABEL=RUN_DIR; got {item!r}", file=sys.stderr)
            return 2
        runs[label] = run
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    table, figures = results_table(runs)
    (out / "results.md").write_text(table + "\n")
    (out / "results.json").write_text(json.dumps(figures, indent=2) + "\n")
    image = plot_curves(runs, out / "curves.png")
    print(table)
    print(f"wrote {image}, {out / 'results.md'}, {out / 'results.json'}")
    return 0


def _with_episodes(config, episodes: int):
    import dataclasses

    return dataclasses.replace(config, train=dataclasses.replace(config.train, eval_episodes=episodes))


def format_summary(summary: dict) -> str:
    """One line per figure of an evaluation summary."""
    rate = summary.get("intervention_rate")
    return "\n".join([
        f"{summary.get('algo', '?')} on {summary.get('env', '?')}: {summary['episodes']} episodes",
        f"  collision rate     {summary['collision_rate']:.3f}",
        f"  mean speed         {summary['mean_speed']:.2f} m/s",
        f"  mean return        {summary['mean_return']:.2f}",
        f"  intervention rate  {'n/a' if rate is None else f'{rate:.3f}'}",
    ])
