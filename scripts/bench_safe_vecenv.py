"""Benchmark: E safe environments stepped with ONE batched solve per frame vs one solve per
environment (end to end).

Both vectorized environments are built from the same configuration and seeds and stepped with
the same actions, alternately, so the two figures come from the same machine state. Reported per
variant: wall time per vectorized step [s], agent steps per second (E / step time), optimizer
calls per step and the optimizer's share of the step time.
"""

from __future__ import annotations

import argparse
import sys
import json
import os
import platform
import time
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from mmpc.cli.arguments import compile_at_once
from mmpc.config import load_config
from mmpc.rl.config import RLConfig


def run_benchmark(config: RLConfig, *, num_envs: int = 64, steps: int = 3, seed: int = 0, threads: int = 1,
                  out: Optional[Path] = None) -> dict:
    """Time ``steps`` vectorized steps of ``num_envs`` safe environments, batched and per environment.

    Args:
        config: environment and scenario settings.
        num_envs: E.
        steps: timed vectorized steps per variant (after one warm-up step each).
        seed: seeds the environments and the random discrete actions.
        threads: torch CPU threads.
        out: write the report as JSON here.

    Returns:
        The report: machine, settings and one row per variant.
    """
    from stable_baselines3.common.vec_env import DummyVecEnv

    from mmpc.rl.envs import SafeHighwayEnv
    from mmpc.rl.safety import SafetyLayer
    from mmpc.rl.vec_env import SafeVecEnv

    if num_envs < 1 or steps < 1:
        raise ValueError(f"`num_envs` and `steps` must be >= 1; got {num_envs}, {steps}")
    torch.set_num_threads(threads)
    rng = np.random.default_rng(seed)
    actions = [rng.integers(0, config.env.num_discrete_goals, num_envs) for _ in range(steps + 1)]
    layer = SafetyLayer.for_scenario(config.scenario, config.env)  # the single environments share one optimizer
    variants = {
        "batched": SafeVecEnv(num_envs, config.scenario, config.env, config.reward),
        "per_env": DummyVecEnv([lambda: SafeHighwayEnv(config.scenario, config.env, config.reward, layer=layer)] * num_envs),
    }
    for venv in variants.values():
        venv.seed(seed)
        venv.reset()
    timings: dict[str, list[tuple[float, float, int]]] = {name: [] for name in variants}
    frames = config.env.decision_frames
    for step, action in enumerate(actions):
        for name, venv in variants.items():
            start = time.perf_counter()
            _, _, _, infos = venv.step(action)
            elapsed = time.perf_counter() - start
            # every environment reports the mean ms of the calls that served it
            calls = frames + int(config.env.solver_features)
            if name == "batched":
                solve_s = infos[0]["solve_ms"] * calls / 1e3
                count = calls
            else:
                solve_s = sum(info["solve_ms"] * calls for info in infos) / 1e3
                count = calls * num_envs
            if step > 0:  # step 0 warms up
                timings[name].append((elapsed, solve_s, count))
    for venv in variants.values():
        venv.close()
    rows = []
    for name, values in timings.items():
        step_s = float(np.mean([v[0] for v in values]))
        rows.append({
            "variant": name,
            "num_envs": num_envs,
            "step_s": step_s,
            "agent_steps_per_s": num_envs / step_s,
            "solver_calls_per_step": int(np.mean([v[2] for v in values])),
            "solver_share": float(np.mean([v[1] / v[0] for v in values])),
        })
    report = {
        "benchmark": "safe_vecenv",
        "machine": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "load_average_1min": os.getloadavg()[0],
        "torch": torch.__version__,
        "torch_threads": threads,
        "steps": steps,
        "decision_frames": frames,
        "goals_per_env": 1 + config.scenario.objective.goal_sampler(config.scenario.road, config.scenario.optimizer.horizon)(
            torch.zeros(1, 6), config.scenario.road).shape[1],
        "speedup": rows[1]["step_s"] / rows[0]["step_s"],
        "rows": rows,
    }
    if out is not None:
        out = Path(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(report, indent=2) + "\n")
    return report


def format_report(report: dict) -> str:
    """The report as a table."""
    lines = [f"{'variant':<10} {'E':>4} {'s/step':>8} {'agent steps/s':>14} {'solves/step':>12} {'solver share':>13}"]
    for row in report["rows"]:
        lines.append(f"{row['variant']:<10} {row['num_envs']:>4} {row['step_s']:>8.2f} {row['agent_steps_per_s']:>14.1f} "
                     f"{row['solver_calls_per_step']:>12} {row['solver_share']:>13.0%}")
    lines.append(f"batched is {report['speedup']:.2f}x faster per step (load average {report['load_average_1min']:.1f} "
                 f"on {report['cpu_count']} CPUs, {report['torch_threads']} torch thread(s))")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default=None, help="RL config name in configs/rl or a YAML path (default: RLConfig's defaults)")
    parser.add_argument("--envs", type=int, default=64, help="vectorized environments E (default 64)")
    parser.add_argument("--steps", type=int, default=3, help="timed vectorized steps per variant (default 3)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="benchmarks/bench_safe_vecenv.json", help="JSON report")
    args = parser.parse_args(argv)
    compile_at_once()
    report = run_benchmark(load_config(RLConfig, args.config), num_envs=args.envs, steps=args.steps, seed=args.seed,
                           threads=args.threads, out=Path(args.out))
    print(format_report(report))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
