"""Benchmark: training throughput, agent steps per second of stable-baselines3's ``learn`` (the
environments and the learner together), per algorithm, environment kind and E.

Each row builds the recipe's training environments (:func:`mmpc.rl.train.make_training_env`) with
``train.n_envs = E``, trains one rollout to warm up (compiles, first solves), then times ``--steps``
agent steps (rounded up to whole rollouts: PPO's ``n_steps x E``, DQN's ``train_freq x E``). Rows
run one after another in this process, so their ratios come from one machine state.

    python scripts/bench_rl_train.py --config cruise_task --envs 64,256 --algos ppo,dqn --kinds safe \
        --steps 8192 --threads 1 --out benchmarks/bench_rl_train_cruise_task_cpu.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Optional

import torch

from mmpc.config import load_config
from mmpc.rl.config import RLConfig


def time_training(config: RLConfig, algo: str, kind: str, num_envs: int, steps: int, seed: int = 0) -> dict:
    """Agent steps per second of ``algo`` training ``steps`` agent steps (whole rollouts) on
    ``num_envs`` environments of ``kind``."""
    from mmpc.rl.runs import algorithm_class
    from mmpc.rl.train import algorithm_kwargs, make_training_env, rollout_steps

    config = dataclasses.replace(config, train=dataclasses.replace(config.train, n_envs=num_envs))
    kwargs = algorithm_kwargs(config, algo)
    if algo == "dqn":
        kwargs["learning_starts"] = 0  # time the learner from the first step, as after its warm-up
    env = make_training_env(config, env_kind=kind, continuous=False, seed=seed)
    try:
        model = algorithm_class(algo)("MlpPolicy", env, seed=seed, verbose=0, device="cpu", **kwargs)
        rollout = rollout_steps(model)
        steps = -(-steps // rollout) * rollout
        model.learn(rollout)
        start = time.perf_counter()
        model.learn(steps, reset_num_timesteps=False)
        seconds = time.perf_counter() - start
    finally:
        env.close()
    return {"algo": algo, "kind": kind, "envs": num_envs, "steps": steps, "seconds": seconds,
            "agent_steps_per_s": steps / seconds}


def main(argv: Optional[list[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="cruise_task", help="RL config (shipped name or YAML path)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config value")
    parser.add_argument("--sim", default="batched", choices=("batched", "highway-env"))
    parser.add_argument("--envs", default="64,256", help="E values, comma-separated")
    parser.add_argument("--algos", default="ppo,dqn")
    parser.add_argument("--kinds", default="safe", help="safe and/or plain, comma-separated")
    parser.add_argument("--steps", type=int, default=8192,
                        help="timed agent steps per row, rounded up to whole rollouts (after one warm-up rollout)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default=None, help="write the table as JSON here")
    args = parser.parse_args(argv)
    from mmpc.cli.arguments import override

    torch.set_num_threads(args.threads)
    overrides = dict(override(item) for item in args.set)
    overrides["scenario.sim"] = args.sim
    overrides["train.torch_threads"] = args.threads
    config = load_config(RLConfig, args.config, overrides)
    rows = []
    print(f"{'algo':>5} {'kind':>6} {'E':>5} {'steps':>7} {'s':>8} {'agent steps/s':>14}")
    for kind in args.kinds.split(","):
        for algo in args.algos.split(","):
            for num_envs in (int(e) for e in args.envs.split(",")):
                row = time_training(config, algo, kind, num_envs, args.steps)
                rows.append(row)
                print(f"{algo:>5} {kind:>6} {num_envs:>5} {row['steps']:>7} {row['seconds']:>8.1f} "
                      f"{row['agent_steps_per_s']:>14.1f}", flush=True)
    report = {"benchmark": "rl_train", "config": args.config, "set": args.set, "sim": args.sim, "threads": args.threads,
              "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "torch": torch.__version__},
              "rows": rows}
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(report, indent=2) + "\n")
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
