"""Red team: train a PPO agent that drives one car of the traffic, within the rules, to make a
driver collide; then count its collisions over named seeds (:mod:`mmpc.rl.red_team`).

    python scripts/red_team.py --driver verified:mpc --steps 100000 --episodes 1000 --seeds 73024 --out runs/red_team/verified
    python scripts/red_team.py --driver mpc --steps 100000 --episodes 256 --seeds 74024 --out runs/red_team/mpc
    python scripts/red_team.py --driver verified:mpc --model runs/red_team/mpc/model.zip --episodes 256 --seeds 74280 --out runs/red_team/cross
    python scripts/red_team.py --driver verified:mpc --set traffic.ego_as_follower=true --seeds 84856 --out runs/red_team/cut_ins

Any driver spec of ``mmpc evaluate --driver`` can be the target. Prints a table and writes
``OUT/red_team.json`` (with ``OUT/model.zip`` and TensorBoard files under ``OUT/tb`` when it trains: the
episodes' return ``rollout/ep_rew_mean``, 100 per collision).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import torch

from mmpc.cli.arguments import add_set
from mmpc.drivers import make_driver
from mmpc.evaluate.intervals import wilson_ci
from mmpc.files import OutputFolderError
from mmpc.rl.folders import run_folder
from mmpc.rl.red_team import ACTION_NAMES, RedTeamVecEnv, score_red_team
from mmpc.scenario import load_scenario


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--driver", required=True, help="the driver under test, a spec of `mmpc evaluate --driver`")
    parser.add_argument("--scenario", default="high_speed", help="an IDM-traffic scenario (default high_speed)")
    add_set(parser, "scenario", " (e.g. traffic.ego_as_follower=true: its traffic may cut in ahead of the ego)")
    parser.add_argument("--duration", type=float, default=10.0, help="episode length [s] (default 10)")
    parser.add_argument("--steps", type=int, default=100_000, help="training steps, all environments together")
    parser.add_argument("--model", type=Path, help="evaluate this trained agent instead of training one")
    parser.add_argument("--envs", type=int, default=64, help="environments stepped together (default 64)")
    parser.add_argument("--episodes", type=int, default=1000, help="evaluation episodes (default 1000)")
    parser.add_argument("--seeds", type=int, required=True, help="first of the evaluation's consecutive seeds")
    parser.add_argument("--train-seed", type=int, default=0, help="seeds the training's episodes and PPO")
    parser.add_argument("--near-miss", type=float, default=0.1, help="weight of the near-miss reward (default 0.1)")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    args = parser.parse_args(argv)
    if args.steps < 1 or args.envs < 1 or args.episodes < 1:
        parser.error("--steps, --envs and --episodes must be >= 1")
    if args.seeds < 0 or args.train_seed < 0:
        parser.error(f"--seeds and --train-seed must be >= 0; got {args.seeds} and {args.train_seed}")
    if args.model is not None and not args.model.is_file():
        parser.error(f"--model {args.model} is not a file (a model.zip a red-team run wrote)")
    torch.set_num_threads(1)
    try:
        overrides = {**dict(args.set), "sim": "batched"}
        scenario = dataclasses.replace(load_scenario(args.scenario, overrides), duration=args.duration)
        driver = make_driver(args.driver, scenario)
    except ValueError as error:  # an unknown scenario or driver, or one the check cannot cover
        parser.error(str(error))
    try:
        with run_folder(args.out, ".red_team.lock", "another red-team run", fresh="a red-team run neither resumes nor "
                        "replaces one (its model.zip and red_team.json)"):
            return _run(args, scenario, driver)
    except OutputFolderError as error:
        print(f"red_team.py: error: {error}", file=sys.stderr)
        return 2


def _run(args: argparse.Namespace, scenario, driver) -> int:
    """Train (or load) the red team into the held folder ``args.out``, score it, write and print the results."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecMonitor

    start = time.perf_counter()
    if args.model is None:
        env = VecMonitor(RedTeamVecEnv(driver, scenario, args.envs, seed=args.train_seed, near_miss=args.near_miss))
        model = PPO("MlpPolicy", env, n_steps=128, batch_size=1024, learning_rate=3e-4, seed=args.train_seed,
                    tensorboard_log=str(args.out / "tb"), verbose=0)
        model.learn(total_timesteps=args.steps)
        model.save(args.out / "model.zip")
        trained = int(model.num_timesteps)
    else:
        model, trained = PPO.load(args.model), None
    train_s = time.perf_counter() - start
    seeds = list(range(args.seeds, args.seeds + args.episodes))
    score = score_red_team(model, driver, scenario, seeds, args.envs)
    row = {
        "driver": args.driver, "scenario": scenario.name, "overrides": dict(args.set), "duration_s": args.duration,
        "model": str(args.model or args.out / "model.zip"),
        "trained_steps": trained, "train_wall_s": round(train_s, 1), "eval_wall_s": round(time.perf_counter() - start - train_s, 1),
        "seeds": f"{seeds[0]}-{seeds[-1]}", **score._asdict(),
        "collision_rate": score.collisions / score.episodes, "collision_rate_ci": wilson_ci(score.collisions, score.episodes),
    }
    (args.out / "red_team.json").write_text(json.dumps(row, indent=2) + "\n")
    print(f"{'driver':<28}{'episodes':>9}{'collisions':>11}{'with red':>9}{'near misses':>12}{'red outside':>12}  rate [95% CI]")
    interval = row["collision_rate_ci"]
    print(f"{args.driver:<28}{score.episodes:>9}{score.collisions:>11}{score.red_collisions:>9}{score.near_misses:>12}"
          f"{score.red_left_assumptions:>12}  {row['collision_rate']:.4f} [{interval[0]:.4f}, {interval[1]:.4f}]")
    print("actions: " + ", ".join(f"{name} {score.actions[name]:.2f}" for name in ACTION_NAMES))
    print(f"wrote {args.out / 'red_team.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
