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
    from mmpc.rl.runs import shipped_models

    rl = sub.add_parser("rl", help="safe RL: train, evaluate and report stable-baselines3 agents behind the layer")
    subparsers = rl.add_subparsers(dest="rl_command", required=True)
    train = subparsers.add_parser(
        "train", help="train an SB3 agent on the safe layer (or plain highway-env): TensorBoard, checkpoints, eval.json")
    train.add_argument("--algo", choices=sorted(ALGORITHMS), default=None, help="dqn, ppo or sac (required, but with --resume)")
    add_config(train, "RL config (mmpc.rl.config.RLConfig; scenario keys as scenario.KEY)")
    add_sim(train)
    add_compile(train)
    add_device(train)
    train.add_argument("--timesteps", type=int, required=True,
                       help="agent steps, summed over the vectorized environments; rounded up to whole rollouts "
                            "(PPO: n_steps x n_envs, DQN and SAC: train_freq x n_envs), config.yaml records "
                            "trained_timesteps")
    train.add_argument("--out", required=True,
                       help="run directory, new or empty (config.yaml, tb/, checkpoints/, model.zip, crashes.csv, eval.json)")
    train.add_argument("--env", choices=("safe", "plain", "highway"), default=None,
                       help="safe: the agent picks goals through the safety layer (default); plain: no layer, "
                            "highway-env's meta-actions on the scenario's world (--sim batched trains fast); highway: "
                            "plain highway-env")
    train.add_argument("--seed", type=int, default=None,
                       help="seed of the model and the training environments, in [0, 2^32 - 1] (default 0)")
    train.add_argument("--resume", action="store_true",
                       help="go on with the run in --out from its latest checkpoint up to --timesteps in all, with the "
                            "settings its config.yaml records (no --algo, --config, --set, --sim, --env or --seed)")
    train.add_argument("--eval-episodes", type=int, default=None, help="override train.eval_episodes of the config")
    train.add_argument("--no-eval", action="store_true", help="skip the final evaluation")
    train.add_argument("--progress", action="store_true", help="show SB3's progress bar")
    train.set_defaults(func=_train)

    evaluate = subparsers.add_parser(
        "evaluate", help="evaluate a trained run's model on its fixed evaluation seeds in highway-env",
        description="Evaluate a trained agent on its run's fixed evaluation seeds, in highway-env (the reference world, "
                    "whichever world it trained in). Every frame of every episode goes through the MPC safety layer: on "
                    "a CPU a 40 s episode takes minutes (a shipped agent's 100 episodes take hours); --episodes 5 "
                    "gives a first look. `mmpc evaluate --sim batched --driver sb3:MODEL` drives an agent on the "
                    "batched simulator.")
    evaluate.add_argument("--model", required=True, metavar="MODEL.zip|NAME",
                          help=f"a run's model.zip (or a checkpoint) written by mmpc rl train, or a shipped agent's name "
                               f"({', '.join(shipped_models()) or 'none'})")
    evaluate.add_argument("--episodes", type=int, default=None,
                          help="override train.eval_episodes of the run's config (the default, comparable with its "
                               "eval.json; minutes per episode on a CPU)")
    evaluate.add_argument("--out", default=None, help="write the summary here, a JSON file (default: print only)")
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
    from mmpc.rl.config import RLConfig
    from mmpc.rl.runs import recorded_run
    from mmpc.rl.train import train

    if args.timesteps < 1:
        print("mmpc rl train: error: --timesteps must be >= 1", file=sys.stderr)
        return 2
    apply_compile(args.compile)
    if args.resume:
        given = [flag for flag, value in (("--algo", args.algo), ("--config", args.config), ("--set", args.set),
                                          ("--sim", args.sim), ("--env", args.env), ("--seed", args.seed))
                 if value is not None and value != []]
        if given:
            print(f"mmpc rl train: error: --resume takes the run's settings from {args.out}/config.yaml; drop "
                  f"{', '.join(given)}", file=sys.stderr)
            return 2
        record = recorded_run(Path(args.out))
        if record is None:
            print(f"mmpc rl train: error: --resume needs a training run in --out; {args.out} holds no readable "
                  "config.yaml of one", file=sys.stderr)
            return 2
        algo, env_kind, seed, config = record.algo, record.env_kind, record.seed, record.config
    else:
        if args.algo is None:
            print("mmpc rl train: error: --algo is required (dqn, ppo or sac)", file=sys.stderr)
            return 2
        algo, env_kind, seed = args.algo, args.env or "safe", 0 if args.seed is None else args.seed
        overrides = dict(args.set)
        if args.sim is not None:
            if env_kind == "highway" and args.sim == "batched":
                print("mmpc rl train: error: --env highway trains on plain highway-env; on the batched simulator the "
                      "unprotected baseline is --env plain", file=sys.stderr)
                return 2
            overrides["scenario.sim"] = args.sim
        config = load_config(RLConfig, args.config, overrides)
    if args.eval_episodes is not None:
        if args.eval_episodes < 1:
            print("mmpc rl train: error: --eval-episodes must be >= 1", file=sys.stderr)
            return 2
        config = _with_episodes(config, args.eval_episodes)
    # settings it cannot start with (ConfigError) and a folder it may not write to (OutputFolderError) are refused
    # before it writes anything, and mmpc.cli.main prints them as one line
    summary = train(config, algo, args.timesteps, Path(args.out), env_kind=env_kind, seed=seed,
                    progress_bar=args.progress, evaluate_after=not args.no_eval, resume=args.resume)
    if summary:
        print(format_summary(summary))
    print(f"wrote {args.out}/model.zip, {args.out}/tb/, {args.out}/crashes.csv"
          + ("" if args.no_eval else f", {args.out}/eval.json"))
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from mmpc.cli.arguments import apply_compile, unwritable
    from mmpc.config import require, with_overrides
    from mmpc.files import atomic_write_text
    from mmpc.rl.config import require_same_agent_inputs
    from mmpc.rl.runs import load_run
    from mmpc.rl.train import evaluate_run

    if args.episodes is not None and args.episodes < 1:
        print(f"mmpc rl evaluate: error: --episodes must be >= 1; got {args.episodes}", file=sys.stderr)
        return 2
    out = None if args.out is None else Path(args.out)
    if out is not None:  # before the episodes: the summary is written at their end
        problem = "it is a folder" if out.is_dir() else unwritable(out.parent)
        if problem is not None:
            print(f"mmpc rl evaluate: error: --out {out} must be a file in a folder this process can create and write "
                  f"to; got {problem}", file=sys.stderr)
            return 2
    apply_compile(args.compile)
    run = load_run(args.model)
    config = with_overrides(run.config, dict(args.set))
    require_same_agent_inputs(run.config, config)
    # the run's own world is no request: an agent trained on the batched simulator is evaluated in highway-env too
    asked = "scenario.sim" in dict(args.set) or config.scenario.sim != run.config.scenario.sim
    require(config.scenario.sim == "highway-env" or not asked,
            f"`scenario.sim` must be 'highway-env'; got {config.scenario.sim!r}: mmpc rl evaluate drives every agent "
            "in highway-env, the reference world its eval.json and the plain highway-env baseline were measured in; "
            "`mmpc evaluate --sim batched --driver sb3:MODEL` drives it on the batched simulator")
    config = config if args.episodes is None else _with_episodes(config, args.episodes)
    episodes, duration = config.train.eval_episodes, config.scenario.duration
    print(f"evaluating {args.model}: {episodes} episodes x {duration:g} s in highway-env ({episodes * duration:,.0f} s "
          f"driven, {min(config.train.eval_envs, episodes)} at a time; on a CPU each episode takes minutes, --episodes N "
          "for fewer)", file=sys.stderr)
    with tqdm(total=episodes, desc="episodes", unit="ep") as bar:
        summary = evaluate_run(run.model, config, env_kind=run.env_kind, continuous=run.continuous,
                               on_episode=lambda row: bar.update(1))
    summary = {"algo": run.algo, "env": run.env_kind, "model": str(args.model), **summary}
    print(format_summary(summary))
    if out is not None:
        atomic_write_text(out, json.dumps(summary, indent=2) + "\n")
        print(f"wrote {out}")
    return 0


def _report(args: argparse.Namespace) -> int:
    from mmpc.cli.arguments import unwritable
    from mmpc.rl.report import plot_curves, results_table

    runs = {}
    for item in args.runs:
        label, sep, run = item.partition("=")
        if not sep or not label or not run:
            print(f"mmpc rl report: error: expected LABEL=RUN_DIR; got {item!r}", file=sys.stderr)
            return 2
        if label in runs:
            print(f"mmpc rl report: error: the label {label!r} names two runs ({runs[label]}, {run}); give every run "
                  "its own label", file=sys.stderr)
            return 2
        runs[label] = run
    out = Path(args.out)
    problem = unwritable(out)
    if problem is not None:
        print(f"mmpc rl report: error: --out {out} must be a folder this process can create and write to; got {problem}",
              file=sys.stderr)
        return 2
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
