"""Benchmark: the check's share of a verified decision, and of the gymnasium entry point's step.

Two tables, one torch thread unless ``--threads``, every solve and (``compiled`` rows) the check
compiled before timing:

1. **decision**: ``verified:DRIVER`` drives E episodes in lockstep in the batched simulator
   (``--scenario``, ``--duration``); per E and check (``eager``, ``compiled``: its fail-safe rollout
   and occupancy sets, :class:`mmpc.verify.compiling.CheckCompiling`): the decision's
   time per environment-step (the driver's solve and the check together, as episodes record
   ``solve_ms``), the check's part and its share;
2. **gym** (``--gym-steps``): ``gym.make("mmpc/SafeHighway-v0")`` (E = 1) in each world, verified
   (the default) and not, and verified solving at the agent's decisions only (``replan: decision``):
   agent steps per second after a warm-up of ``--gym-warmup`` steps, and the time per agent step of
   the world's frames.

Every row is written to ``--out`` (JSON) with the machine and settings.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np
import torch

from mmpc.cli.arguments import compile_at_once, seed_list

CHECKS = ("eager", "compiled")
WORLDS = ("highway-env", "batched")
#: (env.verify, env.replan) of the gym rows: the default, without the check, and solving at decisions only.
GYM_VARIANTS = ((True, "frame"), (False, "frame"), (True, "decision"))


class Stopwatch:
    """Seconds and calls spent in a wrapped callable."""

    def __init__(self) -> None:
        self.seconds, self.calls = 0.0, 0

    def wrap(self, function: Callable) -> Callable:
        def timed(*args, **kwargs):
            start = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                self.seconds += time.perf_counter() - start
                self.calls += 1

        return timed


def decision_rows(scenario_name: str, driver_spec: str, env_counts: Sequence[int], seeds: Sequence[int],
                  duration: float, checks: Sequence[str] = CHECKS) -> list[dict]:
    """Table 1: per E and check (eager, compiled), the decision's and the check's time per environment-step."""
    from mmpc.drivers import make_driver
    from mmpc.drivers.verified import VerifiedDriver
    from mmpc.highway.runner import run_lockstep
    from mmpc.scenario import load_scenario
    from mmpc.verify import Verifier

    rows = []
    for num_envs in env_counts:
        if num_envs > len(seeds):
            raise ValueError(f"E = {num_envs} needs {num_envs} seeds; got {len(seeds)}")
        for check in checks:
            scenario = load_scenario(scenario_name, {"sim": "batched"})
            verifier = Verifier.for_scenario(scenario, compile=check == "compiled")
            driver = VerifiedDriver(make_driver(driver_spec, scenario), verifier)
            warm_up = load_scenario(scenario_name, {"sim": "batched", "duration": 2.0})
            run_lockstep(warm_up, list(seeds[:num_envs]), driver=driver)  # compiles every layout
            watch = Stopwatch()
            verifier.check = watch.wrap(verifier.check)
            scenario = load_scenario(scenario_name, {"sim": "batched", "duration": duration})
            results = run_lockstep(scenario, list(seeds[:num_envs]), driver=driver)
            driver.close()
            steps = len(results[0].records)  # lockstep: the decisions of all E at once
            decision_s = sum(record.solve_ms for record in results[0].records) / 1e3
            rows.append({
                "table": "decision", "scenario": scenario_name, "driver": f"verified:{driver_spec}", "envs": num_envs,
                "check": check, "steps": steps, "decision_ms": decision_s / steps * 1e3,
                "check_ms": watch.seconds / steps * 1e3, "checks_per_step": watch.calls / steps,
                "check_share": watch.seconds / decision_s,
            })
            print(format_decision_row(rows[-1]), flush=True)
    return rows


def gym_rows(steps: int, warmup: int, seed: int) -> list[dict]:
    """Table 2: ``mmpc/SafeHighway-v0`` agent steps per second in each world, verified and not."""
    import gymnasium as gym

    import mmpc.rl  # noqa: F401 (registers the environments)
    from mmpc.highway.batched_world import BatchedWorld
    from mmpc.highway.highway_env_world import HighwayEnvWorld
    from mmpc.rl.config import RL_SCENARIO
    from mmpc.scenario import load_scenario

    rows = []
    for world in WORLDS:
        for verify, replan in GYM_VARIANTS:
            env = gym.make("mmpc/SafeHighway-v0", scenario=load_scenario(RL_SCENARIO, {"sim": world}),
                           config={"verify": verify, "replan": replan})
            rng = np.random.default_rng(seed)
            next_seed = seed

            def run(count: int) -> None:
                nonlocal next_seed
                for _ in range(count):
                    _, _, terminated, truncated, _ = env.step(int(rng.integers(env.action_space.n)))
                    if terminated or truncated:
                        next_seed += 1
                        env.reset(seed=next_seed)

            env.reset(seed=next_seed)
            run(warmup)
            world_class = BatchedWorld if world == "batched" else HighwayEnvWorld
            watch = Stopwatch()
            original = world_class.apply
            world_class.apply = watch.wrap(original)
            try:
                start = time.perf_counter()
                run(steps)
                elapsed = time.perf_counter() - start
            finally:
                world_class.apply = original
                env.close()
            rows.append({"table": "gym", "world": world, "verify": verify, "replan": replan, "steps": steps,
                         "agent_steps_per_s": steps / elapsed, "step_ms": elapsed / steps * 1e3,
                         "world_ms_per_step": watch.seconds / steps * 1e3})
            print(format_gym_row(rows[-1]), flush=True)
    return rows


def format_decision_row(row: dict) -> str:
    return (f"decision  E={row['envs']:<4} {row['check']:<8} decision {row['decision_ms']:7.2f} ms/step  check "
            f"{row['check_ms']:6.2f} ms ({row['checks_per_step']:.2f} calls)  share {row['check_share']:5.1%}")


def format_gym_row(row: dict) -> str:
    return (f"gym       {row['world']:<11} verify={str(row['verify']):<5} replan={row['replan']:<8} "
            f"{row['agent_steps_per_s']:6.2f} agent steps/s  "
            f"{row['step_ms']:7.1f} ms/step, the world's frames {row['world_ms_per_step']:5.1f} ms")


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenario", default="high_speed", help="scenario of the decision table (default high_speed)")
    parser.add_argument("--driver", default="mpc", help="the driver behind the check (default mpc)")
    parser.add_argument("--envs", default="1,16,256", help="comma-separated E of the decision table ('' skips it)")
    parser.add_argument("--seeds", default="71168-71423", help="episode seeds, at least max E (default 71168-71423)")
    parser.add_argument("--duration", type=float, default=10.0, help="timed episode length [s] (default 10)")
    parser.add_argument("--checks", default=",".join(CHECKS), help="the decision table's checks (default eager,compiled)")
    parser.add_argument("--gym-steps", type=int, default=60, help="timed agent steps per gym row (0 skips the table)")
    parser.add_argument("--gym-warmup", type=int, default=150, help="agent steps before timing (compiles; default 150)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    parser.add_argument("--out", default="benchmarks/bench_check.json", help="JSON report")
    args = parser.parse_args(argv)
    try:
        env_counts = [int(value) for value in args.envs.split(",") if value.strip()]
        seeds = seed_list(args.seeds)
        checks = [value for value in args.checks.split(",") if value]
        if not checks or set(checks) - set(CHECKS):
            raise ValueError(f"--checks takes names of {list(CHECKS)}; got {args.checks!r}")
        if any(count < 1 for count in env_counts) or args.gym_steps < 0 or args.gym_warmup < 0 or not args.duration > 0:
            raise ValueError(f"E >= 1, --gym-steps and --gym-warmup >= 0, --duration > 0; got {args.envs!r}, "
                             f"{args.gym_steps}, {args.gym_warmup}, {args.duration}")
    except ValueError as error:
        print(f"bench_check: error: {error}", file=sys.stderr)
        return 2
    compile_at_once()
    torch.set_num_threads(args.threads)
    rows = decision_rows(args.scenario, args.driver, env_counts, seeds, args.duration, checks) if env_counts else []
    if args.gym_steps:
        rows += gym_rows(args.gym_steps, args.gym_warmup, seeds[0])
    report = {"benchmark": "check", "machine": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(),
              "load_average_1min": os.getloadavg()[0], "torch": torch.__version__, "torch_threads": args.threads,
              "settings": vars(args), "rows": rows}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
