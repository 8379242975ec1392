"""Command line of :mod:`mmpc.imitation`: ``mmpc imitate {demos, bc, dagger, proposer, export}`` (a
cloned policy is evaluated by ``mmpc evaluate --driver mpc,bc:RUN/policy.pt``, a mode proposer by
``--driver mpc,proposer:RUN/proposer.pt``). Heavy imports (Minari,
stable-baselines3, TensorBoard) happen inside the commands."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from mmpc.cli.arguments import add_compile, add_config, add_device, add_set, add_sim, apply_compile, scenario_overrides, split_overrides


def _scenario(args: argparse.Namespace, overrides: dict):
    """The verb's scenario, refused before any folder is made where this machine lacks its data."""
    from mmpc.config import ConfigError
    from mmpc.scenario import load_scenario

    apply_compile(args.compile)
    scenario = load_scenario(args.scenario, overrides)
    if args.duration is not None:
        if not args.duration > 0:
            raise ValueError(f"--duration must be > 0 s; got {args.duration}")
        scenario = scenario.replace(duration=args.duration)
    missing = scenario.missing_data()
    if missing is not None:
        raise ConfigError(f"scenario {scenario.name!r}: {missing}")
    return scenario


def _demos(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from mmpc.imitation.dataset import DemonstrationsError
    from mmpc.imitation.demos import generate_demonstrations

    if args.episodes < 1:
        print(f"mmpc imitate demos: error: --episodes must be >= 1; got {args.episodes}", file=sys.stderr)
        return 2
    torch.set_num_threads(args.threads)
    scenario = _scenario(args, scenario_overrides(args))
    seeds = list(range(args.seed_start, args.seed_start + args.episodes))
    with tqdm(total=len(seeds), desc=f"demos {scenario.name}", unit="ep") as bar:  # closed before an interrupt's message
        def progress(finished: int, total: int) -> None:
            if finished > bar.n:
                bar.update(finished - bar.n)

        try:
            report = generate_demonstrations(scenario, seeds, Path(args.out), workers=args.workers,
                                             lockstep=args.lockstep, threads=args.threads,
                                             expert=args.expert, on_progress=progress)
        except DemonstrationsError as error:
            bar.close()
            print(f"mmpc imitate demos: error: {error}", file=sys.stderr)
            return 2
    print(f"{len(report.seeds)} episodes ({len(report.generated)} driven now, {len(report.reused)} from an earlier run); "
          f"Minari dataset {report.dataset_id} {'written' if report.rebuilt else 'up to date'} at {report.dataset_path}")
    print(f"load it with: MINARI_DATASETS_PATH={(Path(args.out) / 'minari').resolve()} python -c "
          f"\"import minari; print(minari.load_dataset('{report.dataset_id}'))\"")
    return 0


def _bc(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from mmpc.config import load_config
    from mmpc.imitation.bc import TrainConfig, TrainingDiverged, run_bc

    torch.set_num_threads(args.threads)
    overrides = dict(args.set)
    if args.epochs is not None:
        overrides["epochs"] = args.epochs
    config = load_config(TrainConfig, args.config, overrides)
    with tqdm(total=config.epochs, desc="bc", unit="epoch") as bar:  # closed before an error's message
        def on_epoch(epoch: int, train_loss: float, val_loss: float) -> None:
            bar.update(1)
            bar.set_postfix_str(f"train {train_loss:.4f} val {val_loss:.4f}")

        try:
            report = run_bc(Path(args.dataset), Path(args.out), config, on_epoch=on_epoch)
        except TrainingDiverged as error:
            bar.close()
            print(f"mmpc imitate bc: error: {error}", file=sys.stderr)
            return 2
    print(f"{report['samples']} samples from {report['episodes']} episodes; best epoch {report['best_epoch']}: "
          f"validation loss {report['val_loss']:.4f} (standardised), RMSE acceleration "
          f"{report['val_rmse_acceleration']:.3f} m/s^2, steering {report['val_rmse_steering']:.4f} rad")
    print(f"wrote {Path(args.out) / 'policy.pt'}, train.json and TensorBoard events in {Path(args.out) / 'tb'}")
    return 0


def _dagger(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from mmpc.config import load_config
    from mmpc.imitation.dagger import DaggerConfig, run_dagger

    torch.set_num_threads(args.threads)
    overrides, routed_scenario = split_overrides(args.set, "scenario")
    if args.iterations is not None:
        overrides["iterations"] = args.iterations
    if args.duration is not None:
        overrides["duration"] = args.duration
    config = load_config(DaggerConfig, args.config, overrides)
    args.duration = None  # the config carries it
    scenario = _scenario(args, scenario_overrides(args, list(routed_scenario.items())))
    with tqdm(total=config.iterations + 1, desc="dagger", unit="round") as bar:
        def on_round(entry: dict) -> None:
            bar.update(1)
            if entry.get("source") == "mixture":
                bar.set_postfix_str(f"beta {entry['beta']:.3g}: collisions {entry['collisions']}/{entry['episodes']}, "
                                    f"meta cost {entry['meta_cost_mean']:.2f}, samples {entry['samples']}")

        try:
            report = run_dagger(scenario, Path(args.out), config, dataset_dir=Path(args.dataset) if args.dataset else None,
                                on_round=on_round)
        except ValueError as error:
            bar.close()
            print(f"mmpc imitate dagger: error: {error}", file=sys.stderr)
            return 2
    for entry in report["rounds"]:
        driven = ""
        if entry.get("source") == "mixture":
            driven = f"beta {entry['beta']:.3g} (expert drove {entry['expert_share']:.0%} of the steps): "
        if "collisions" in entry:
            driven += f"collisions {entry['collisions']}/{entry['episodes']}, meta cost {entry['meta_cost_mean']:.2f}; "
        check = ""
        if "check_collisions" in entry:
            check = (f"; policy alone: collisions {entry['check_collisions']}/{config.check_episodes}, "
                     f"meta cost {entry['check_meta_cost_mean']:.2f}")
        print(f"round {entry['round']}: {driven}{entry['samples']} samples, validation loss {entry['val_loss']:.4f}{check}")
    print(f"wrote {Path(args.out) / 'policy.pt'} (round {report['best_round']}), dagger.json, data.npz and TensorBoard "
          f"events in {Path(args.out) / 'tb'}")
    return 0


def _proposer(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from mmpc.config import load_config
    from mmpc.files import OutputFolderError
    from mmpc.imitation.dataset import DemonstrationsError
    from mmpc.imitation.proposer_dagger import ProposerDaggerConfig, run_proposer_dagger

    torch.set_num_threads(args.threads)
    overrides, routed_scenario = split_overrides(args.set, "scenario")
    if args.rounds is not None:
        overrides["rounds"] = args.rounds
    config = load_config(ProposerDaggerConfig, args.config, overrides)
    scenario = _scenario(args, scenario_overrides(args, list(routed_scenario.items())))
    with tqdm(total=config.episodes, desc="labelling round", unit="ep") as bar:  # closed before an interrupt's message
        def on_progress(finished: int, total: int) -> None:
            bar.update(finished - bar.n)  # on_round resets the bar between rounds

        def on_round(entry: dict) -> None:
            bar.write(_round_line(entry, config.train.keep))
            bar.reset()

        try:
            report = run_proposer_dagger(scenario, Path(args.out), config, on_round=on_round, on_progress=on_progress)
        except (ValueError, DemonstrationsError, OutputFolderError) as error:
            bar.close()
            print(f"mmpc imitate proposer: error: {error}", file=sys.stderr)
            return 2
    print(f"wrote {Path(args.out) / 'proposer.pt'} (round {report['best_round']}), proposer.json, labels/ (a Minari "
          f"dataset per round) and TensorBoard events in {Path(args.out) / 'tb'}")
    print(f"drive it: mmpc evaluate --driver mpc,proposer:{Path(args.out) / 'proposer.pt'} --scenarios {scenario.name}")
    return 0


def _round_line(entry: dict, keep: int) -> str:
    """One round of ``proposer.json`` as a line of text."""
    speed = f" ({entry['labels_per_s']:.0f} labels/s)" if entry.get("labels_per_s") else ""
    line = (f"round {entry['round']}: beta {entry['beta']:.3g}, {entry['states']} labelled states{speed}, "
            f"held-out top-{keep} agreement {entry['top_k_agreement']:.3f}")
    if "check" in entry:
        check, expert = entry["check"], entry["expert_check"]
        line += (f"; alone on {check['episodes']} held-out episodes: collisions {check['collisions']}, meta cost "
                 f"{check['meta_cost_mean']:.2f} (expert {expert['collisions']}, {expert['meta_cost_mean']:.2f}), "
                 f"escalated {check['escalated_share']:.1%} of the steps")
    return line


def _export(args: argparse.Namespace) -> int:
    import math

    from mmpc.imitation.export import export_sb3

    path = export_sb3(Path(args.policy), Path(args.out), math.log(args.std))
    print(f"wrote {path}: stable_baselines3 ActorCriticPolicy.load({str(path)!r}); "
          "PPO starts from it with mmpc.imitation.export.ppo_from_policy")
    return 0


def _scenario_arguments(parser: argparse.ArgumentParser) -> None:

    parser.add_argument("--scenario", default="cruise", help="scenario name in configs/scenarios or a YAML path (default cruise)")
    parser.add_argument("--duration", type=float, default=None, help="episode length [s] (default: the scenario's)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (per worker) (default 1)")
    add_sim(parser)
    add_compile(parser)
    add_device(parser)


def add_subcommands(sub) -> None:
    """Add ``mmpc imitate {demos, bc, dagger, proposer, export}``."""
    from mmpc.imitation.dataset import EXPERTS

    imitate = sub.add_parser("imitate", help="imitation learning from the MPC: demos, bc, dagger, proposer, export")
    commands = imitate.add_subparsers(dest="imitate_command", required=True)

    demos = commands.add_parser("demos", help="expert (MPC) demonstrations as a Minari dataset; re-run to resume")
    _scenario_arguments(demos)
    add_set(demos, "scenario")
    demos.add_argument("--episodes", type=int, default=20, help="number of episodes (default 20)")
    demos.add_argument("--seed-start", type=int, default=1000,
                       help="first seed; episodes use consecutive seeds (default 1000, apart from evaluation seeds)")
    demos.add_argument("--workers", type=int, default=1, help="parallel processes (default 1)")
    demos.add_argument("--lockstep", type=int, default=4,
                       help="episodes per optimizer call (chunk k = seeds with seed // lockstep == k) (default 4)")
    demos.add_argument("--expert", choices=EXPERTS, default="verified:mpc",
                       help="who drives: verified:mpc, the MPC behind the check (mmpc.verify: every recorded action keeps "
                            "a verified way out; the default), or mpc, the MPC alone (default verified:mpc)")
    demos.add_argument("--verified", dest="expert", action="store_const", const="verified:mpc",
                       help="the default now; same as --expert verified:mpc")
    demos.add_argument("--out", default="runs/demos", help="demonstrations directory (default runs/demos)")
    demos.set_defaults(func=_demos, kept="the finished episodes stay staged in {out}")

    bc = commands.add_parser("bc", help="behaviour cloning of an MLP policy from a demonstrations directory")
    bc.add_argument("--dataset", required=True, help="an `mmpc imitate demos --out` directory")
    bc.add_argument("--out", default="runs/bc", help="run folder, new or empty: policy.pt, train.json, tb/ (default runs/bc)")
    add_config(bc, "training config (mmpc.imitation.bc.TrainConfig)")
    bc.add_argument("--epochs", type=int, default=None, help="override the config's epochs")
    bc.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    bc.set_defaults(func=_bc)

    dagger = commands.add_parser("dagger", help="DAgger with the MPC labelling the learner's states in batches; "
                                                "re-run to resume")
    _scenario_arguments(dagger)
    dagger.add_argument("--iterations", type=int, default=None, help="rounds after round 0 (default: the config's)")
    dagger.add_argument("--dataset", default=None, help="round 0 from this `mmpc imitate demos` directory (default: the expert drives)")
    add_config(dagger, "DAgger config (mmpc.imitation.dagger.DaggerConfig); the scenario's as scenario.KEY, "
                       "e.g. --set train.epochs=10 --set scenario.traffic.lane_changes=false")
    dagger.add_argument("--out", default="runs/dagger", help="run folder (default runs/dagger)")
    dagger.set_defaults(func=_dagger, kept="the finished rounds are kept in {out}")

    proposer = commands.add_parser("proposer", help="a mode proposer trained on the expert's rankings, with DAgger on "
                                                    "the scenario's world (--sim batched for scale); re-run to resume")
    _scenario_arguments(proposer)
    proposer.add_argument("--rounds", type=int, default=None, help="rounds after round 0 (default: the config's)")
    add_config(proposer, "proposer DAgger config (mmpc.imitation.proposer_dagger.ProposerDaggerConfig); the "
                         "scenario's as scenario.KEY, e.g. --set episodes=256 --set train.epochs=20")
    proposer.add_argument("--out", default="runs/proposer", help="run folder (default runs/proposer)")
    proposer.set_defaults(func=_proposer, kept="finished rounds and staged episodes are kept in {out}")

    export = commands.add_parser("export", help="a cloned policy as a stable-baselines3 policy (PPO can start from it)")
    export.add_argument("--policy", required=True, help="RUN/policy.pt")
    export.add_argument("--out", required=True, help="output file, e.g. RUN/sb3_policy.zip")
    export.add_argument("--std", type=float, default=0.1, help="initial exploration std of the Gaussian (default 0.1)")
    export.set_defaults(func=_export)
