"""Benchmark: the batched simulator (:mod:`mmpc.sim`) against highway-env, side by side in one run.

Four tables, one torch thread unless ``--threads``:

1. **world alone**: environment-steps per second of one control step (the ego's command applied,
   the traffic moved, the window kept, the road-frame state read back for the driver) on the
   batched simulator for each E, and on highway-env (one episode after another, as the runner
   steps it: ``HighwayEpisode.apply`` + ``observe``), with constant commands;
2. **MPC in the loop**: the runner's world + the multi-modal MPC (one optimizer call for all E
   environments per step) on both worlds at each E: environment-steps per second, their ratio,
   the solve's share of the step, the optimizer iterations per environment-step and the minutes
   one process would take for 1,024 episodes of 40 s at that rate, for each schedule
   (``--mpc-schedules``): the paper's (every step cold, all iterations) and the scenario's as shipped
   (its warm starts);
3. **safe RL**: agent steps per second of the safe vector environment (:mod:`mmpc.rl`) on
   highway-env and on the batched simulator (``SafeVecEnv`` in each world), with the
   safety layer replanning at every frame and at the agent's decisions only;
4. **memory** (Linux): the simulator state's bytes per environment, and in a fresh process per E
   the peak resident memory while stepping E environments, whole and per environment above
   what the process held before building them.

Every row is written to ``OUT/bench_sim.json`` with the machine and settings.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import os
import platform
import subprocess
import statistics
import sys
import time
from pathlib import Path
from typing import Optional, Sequence

import torch

from mmpc.cli.arguments import compile_at_once, int_list
from mmpc.scenario import PAPER_SCHEDULE, ScenarioConfig, load_scenario

#: The world table's command of every ego, (acceleration [m/s^2], steering [rad]): a world's cost
#: does not depend on who drives (egos that crash keep being stepped in both worlds).
CONSTANT_COMMAND = (0.0, 0.0)
#: The worlds of the safe RL table.
RL_WORLDS = ("highway-env", "batched")


def _world_steps_per_second(world, num_envs: int, steps: int) -> float:
    """Environment-steps per second of ``world`` (a :mod:`mmpc.highway.worlds` world) under constant commands."""
    active = list(range(num_envs))
    acceleration = torch.full((num_envs,), CONSTANT_COMMAND[0])
    steering = torch.full((num_envs,), CONSTANT_COMMAND[1])
    world.observe(active)
    world.apply(active, acceleration, steering)  # warm-up
    start = time.perf_counter()
    for _ in range(steps):
        world.observe(active)
        world.apply(active, acceleration, steering)
    return num_envs * steps / (time.perf_counter() - start)


def world_rows(scenario: ScenarioConfig, envs: Sequence[int], steps: int, highway_envs: int) -> list[dict]:
    """Table 1: the batched world per E, and highway-env's per-environment rate."""
    from mmpc.highway import BatchedWorld, HighwayEnvWorld

    highway = HighwayEnvWorld.start(scenario, list(range(highway_envs)))
    try:
        reference = _world_steps_per_second(highway, highway_envs, steps)
    finally:
        highway.close()
    rows = [{"table": "world", "world": "highway-env", "num_envs": highway_envs, "env_steps_per_s": reference,
             "speedup": 1.0}]
    for num_envs in envs:
        rate = _world_steps_per_second(BatchedWorld.start(scenario, list(range(num_envs))), num_envs, steps)
        rows.append({"table": "world", "world": "batched", "num_envs": num_envs, "env_steps_per_s": rate,
                     "speedup": rate / reference})
    return rows


def _closed_loop(world, driver, num_envs: int, steps: int) -> tuple[float, float, float]:
    """(seconds per step, solve seconds per step, optimizer iterations per environment-step) of
    the runner's loop body, after one warm-up step, less the time the driver spent compiling new
    call layouts (a warm start's first steps compile the layouts of its warm and cold rows); NaN
    iterations: the driver reports none."""
    active = list(range(num_envs))
    driver.reset(num_envs)
    total = solve = 0.0
    iterations: list[float] = []
    for step in range(steps + 1):
        ended = world.done().tolist()
        running = [i for i in active if not ended[i]]
        if not running:
            break
        start = time.perf_counter()
        observation, _ = world.observe(running)
        decided = time.perf_counter()
        decision = driver.decide(observation)
        solved = time.perf_counter()
        world.apply(running, decision.acceleration, decision.steering)
        if step > 0:
            compiling = 0.0 if decision.plan is None else decision.plan.compile_ms / 1e3
            total += (time.perf_counter() - start - compiling) * num_envs / len(running)
            solve += (solved - decided - compiling) * num_envs / len(running)
            if decision.iterations is not None:
                iterations += decision.iterations.tolist()
    return total / steps, solve / steps, statistics.fmean(iterations) if iterations else math.nan


#: The MPC table's schedules: name -> scenario overrides (:func:`mmpc.scenario.load_scenario`).
SCHEDULES = {"paper": PAPER_SCHEDULE, "shipped": {}}
#: The evaluation the MPC table projects its rates onto: episodes x seconds.
EVALUATION = (1024, 40.0)


def mpc_rows(scenario_name: str, envs: Sequence[int], steps: int, schedules: Sequence[str] = ("shipped",)) -> list[dict]:
    """Table 2: both worlds with the MPC in the loop at each E (same driver, same seeds), for each
    of ``schedules`` (:data:`SCHEDULES`) of the scenario ``scenario_name``."""
    from mmpc.drivers import make_driver
    from mmpc.highway import BatchedWorld, HighwayEnvWorld

    scenarios = {name: load_scenario(scenario_name, {"sim": "batched", **SCHEDULES[name]}) for name in schedules}
    drivers = {name: make_driver("mpc", scenario) for name, scenario in scenarios.items()}
    rows = []
    for num_envs in envs:
        seeds = list(range(num_envs))
        for k, driver in drivers.items():
            scenario = scenarios[k]
            measured = {}
            for name, build in (("highway-env", HighwayEnvWorld.start), ("batched", BatchedWorld.start)):
                world = build(scenario, seeds)
                try:
                    measured[name] = _closed_loop(world, driver, num_envs, steps)
                finally:
                    world.close()
            reference = num_envs / measured["highway-env"][0]
            episodes, seconds = EVALUATION
            for name, (step_s, solve_s, iterations) in measured.items():
                rate = num_envs / step_s
                rows.append({"table": "mpc", "scenario": scenario_name, "world": name, "num_envs": num_envs, "schedule": k,
                             "warm_iterations": scenario.mpc.warm_iterations, "exit_checks": list(scenario.optimizer.exit_checks),
                             "warm_cold_every": scenario.mpc.warm_cold_every, "iterations_per_step": iterations,
                             "step_s": step_s, "solve_s": solve_s, "solve_share": solve_s / step_s,
                             "solve_ms_per_env_step": 1e3 * solve_s / num_envs, "env_steps_per_s": rate,
                             "evaluation_minutes": episodes * seconds * scenario.frequency / rate / 60, "speedup": rate / reference})
    return rows


def rl_rows(envs: Sequence[int], steps: int, replans: Sequence[str], warmup: int, rl_config: Optional[str] = None,
            worlds: Sequence[str] = RL_WORLDS, verify: Sequence[bool] = (True, False)) -> list[dict]:
    """Table 4: agent steps per second of the safe RL vector environment (the RL config
    ``rl_config``, default the defaults; random goals of the grid, the same seeds and actions in
    every row) in each of ``worlds``, for each replanning mode (:attr:`mmpc.rl.config.SafeEnvConfig.replan`)
    and each ``verify`` (the check's cost: the rows with it against those without).
    ``warmup`` untimed steps come first; what later solves spend compiling new layouts is taken
    out of the time (it is paid once per layout in a run)."""
    import numpy as np

    from mmpc.config import load_config
    from mmpc.rl.config import RLConfig
    from mmpc.rl.vec_env import SafeVecEnv

    config = load_config(RLConfig, rl_config)
    rows = []
    for num_envs in envs:
        rng = np.random.default_rng(0)
        actions = [rng.integers(0, config.env.num_discrete_goals, num_envs) for _ in range(warmup + steps)]
        reference = None
        for world, replan, checked in itertools.product(worlds, replans, verify):
            env = dataclasses.replace(config.env, replan=replan, verify=checked,
                                      expert_action=config.env.expert_action and replan == "decision")
            venv = SafeVecEnv(num_envs, config.scenario.replace(sim=world), env, config.reward)
            mpc = venv.layer.mpc
            compile_ms = []
            score = mpc.score

            def timed_score(problem, *args, score=score, compile_ms=compile_ms):
                scored = score(problem, *args)
                compile_ms.append(scored.compile_ms)
                return scored

            mpc.score = timed_score
            venv.seed(0)
            venv.reset()
            elapsed, solved, frames = 0.0, 0, 0
            for step, action in enumerate(actions):
                compile_ms.clear()
                start = time.perf_counter()
                _, _, _, infos = venv.step(action)
                if step >= warmup:
                    elapsed += time.perf_counter() - start - sum(compile_ms) / 1e3
                    solved += sum(info["solved_frames"] for info in infos)
                    frames += sum(info["frames"] for info in infos)
            venv.close()
            rate = num_envs * steps / elapsed
            reference = reference or rate
            rows.append({"table": "rl", "config": rl_config or "defaults", "world": world, "replan": replan, "verify": checked,
                         "expert_action": env.expert_action, "num_envs": num_envs, "agent_steps_per_s": rate,
                         "solved_frame_share": solved / frames, "speedup": rate / reference})
    return rows


def _rss_bytes(field: str) -> int:
    """``VmRSS`` (now) or ``VmHWM`` (peak since the last reset) of this process, from Linux's /proc."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024
    raise RuntimeError(f"/proc/self/status has no {field}")


def memory_probe(scenario_name: str, num_envs: int, steps: int) -> dict:
    """Step ``num_envs`` environments in this process (after a warm-up with one): the state's
    bytes, the resident memory before building them and the peak while stepping them."""
    from mmpc.highway.batched_world import BatchedWorld

    scenario = load_scenario(scenario_name, {"sim": "batched"})

    def run(count: int) -> BatchedWorld:
        world = BatchedWorld.start(scenario, list(range(count)))
        for _ in range(steps):
            world.observe(list(range(count)))
            world.apply(list(range(count)), torch.zeros(count), torch.zeros(count))
        return world

    run(1)  # imports, lazy initialisation
    Path("/proc/self/clear_refs").write_text("5")  # resets the peak (VmHWM) to the current RSS
    before = _rss_bytes("VmRSS")
    world = run(num_envs)
    state_bytes = sum(field.element_size() * field.numel() for field in world.sim.state)
    return {"state_bytes": state_bytes, "rss_before_bytes": before, "peak_rss_bytes": _rss_bytes("VmHWM")}


def _probe(scenario_name: str, num_envs: int, steps: int) -> dict:
    command = [sys.executable, __file__, "--memory-probe", str(num_envs), "--scenario", scenario_name, "--steps", str(steps)]
    output = subprocess.run(command, check=True, capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    return json.loads(output.stdout.strip().splitlines()[-1])


def memory_rows(scenario_name: str, envs: Sequence[int], steps: int) -> list[dict]:
    """Table 3 (Linux): per-environment bytes of the state and of the peak resident memory above
    the process's memory before the environments were built; each E in a fresh process."""
    rows = []
    for num_envs in envs:
        probe = _probe(scenario_name, num_envs, steps)
        rows.append({"table": "memory", "num_envs": num_envs, "state_bytes_per_env": probe["state_bytes"] / num_envs,
                     "peak_rss_mib": probe["peak_rss_bytes"] / 2 ** 20,
                     "peak_added_bytes_per_env": (probe["peak_rss_bytes"] - probe["rss_before_bytes"]) / num_envs})
    return rows


#: The printed tables: (the rows' ``table``, title, columns (header, width, the cell of a row)).
TABLES = (
    ("world", "world alone (constant commands): env-steps/s", (
        ("world", -12, lambda r: r["world"]), ("E", 6, lambda r: r["num_envs"]),
        ("env-steps/s", 12, lambda r: f"{r['env_steps_per_s']:.0f}"), ("x highway-env", 14, lambda r: f"{r['speedup']:.1f}"))),
    ("mpc", "MPC in the loop: env-steps/s, the solve's share of the step, one process's minutes per 1,024 episodes x 40 s; "
            "the paper's schedule or the scenario's as shipped (warm starts)", (
        ("scenario", -11, lambda r: r["scenario"]), ("world", -12, lambda r: r["world"]), ("E", 6, lambda r: r["num_envs"]),
        ("schedule", -8, lambda r: r["schedule"]), ("iter/step", 10, lambda r: f"{r['iterations_per_step']:.1f}"),
        ("solve ms/env-step", 18, lambda r: f"{r['solve_ms_per_env_step']:.2f}"), ("s/step", 8, lambda r: f"{r['step_s']:.3f}"),
        ("env-steps/s", 12, lambda r: f"{r['env_steps_per_s']:.1f}"), ("solve share", 12, lambda r: f"{r['solve_share']:.0%}"),
        ("min/1024x40s", 13, lambda r: f"{r['evaluation_minutes']:.1f}"), ("x highway-env", 14, lambda r: f"{r['speedup']:.1f}"))),
    ("rl", "safe RL vector environment: agent steps/s (env.decision_frames frames each; one solve for all E when any row solves)", (
        ("world", -12, lambda r: r["world"]), ("replan", -9, lambda r: r["replan"]),
        ("verify", -7, lambda r: "on" if r["verify"] else "off"), ("E", 6, lambda r: r["num_envs"]), ("agent steps/s", 14, lambda r: f"{r['agent_steps_per_s']:.1f}"),
        ("frames solved", 14, lambda r: f"{r['solved_frame_share']:.0%}"),
        ("x first row", 12, lambda r: f"{r['speedup']:.1f}"))),
    ("memory", "memory per environment", (
        ("E", 6, lambda r: r["num_envs"]), ("state [B/env]", 14, lambda r: f"{r['state_bytes_per_env']:.0f}"),
        ("process peak RSS [MiB]", 23, lambda r: f"{r['peak_rss_mib']:.0f}"),
        ("peak added [KiB/env]", 21, lambda r: f"{r['peak_added_bytes_per_env'] / 1024:.1f}"))),
)


def format_rows(rows: Sequence[dict]) -> str:
    """The tables of :data:`TABLES` that have rows (a negative width aligns left)."""
    lines: list[str] = []
    for table, title, columns in TABLES:
        mine = [r for r in rows if r["table"] == table]
        if not mine:
            continue
        lines += ([""] if lines else []) + [title, " ".join(f"{header:{'<' if width < 0 else '>'}{abs(width)}}"
                                                            for header, width, _ in columns)]
        lines += [" ".join(f"{cell(r)!s:{'<' if width < 0 else '>'}{abs(width)}}" for _, width, cell in columns) for r in mine]
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenario", default="cruise", help="an IDM-traffic scenario (default cruise)")
    parser.add_argument("--envs", type=int_list, default=(1, 16, 256, 1024, 4096), help="E of the world table")
    parser.add_argument("--mpc-envs", type=int_list, default=(1, 16, 256, 1024), help="E of the MPC table (empty: skip)")
    parser.add_argument("--rl-envs", type=int_list, default=(16, 64), help="E of the safe RL vector environment table")
    parser.add_argument("--rl-steps", type=int, default=4, help="timed agent steps per RL row (default 4)")
    parser.add_argument("--rl-warmup", type=int, default=2, help="untimed agent steps before them (default 2)")
    parser.add_argument("--rl-replan", type=lambda text: tuple(text.split(",")), default=("frame", "decision"),
                        help="replanning modes of the RL table, comma-separated (default frame,decision)")
    parser.add_argument("--rl-worlds", type=lambda text: tuple(text.split(",")), default=RL_WORLDS,
                        help=f"worlds of the safe RL table (default {','.join(RL_WORLDS)})")
    parser.add_argument("--rl-verify", type=lambda text: tuple(part == "on" for part in text.split(",")), default=(True, False),
                        help="env.verify of the safe RL table's rows: on, off or on,off (default on,off: the check's cost)")
    parser.add_argument("--rl-config", default=None, help="RL config of the safe RL table (a shipped name or a YAML path; default: the defaults)")
    parser.add_argument("--no-rl", action="store_true", help="skip the safe RL table")
    parser.add_argument("--memory-envs", type=int_list, default=(1024, 4096), help="E of the memory table")
    parser.add_argument("--steps", type=int, default=20, help="timed steps per world row (default 20)")
    parser.add_argument("--mpc-steps", type=int, default=10,
                        help="timed steps per MPC row (default 10: a warm-start cycle at mpc.warm_cold_every 10)")
    parser.add_argument("--mpc-schedules", type=lambda text: tuple(text.split(",")), default=tuple(SCHEDULES),
                        help=f"the MPC table's schedules, comma-separated, of {list(SCHEDULES)} (default all)")
    parser.add_argument("--mpc-scenarios", type=lambda text: tuple(text.split(",")), default=None,
                        help="the MPC table's scenarios, comma-separated (default: --scenario)")
    parser.add_argument("--highway-envs", type=int, default=8, help="highway-env episodes timed for its rate (default 8)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--no-mpc", action="store_true", help="skip the MPC table")
    parser.add_argument("--no-memory", action="store_true", help="skip the memory table")
    parser.add_argument("--memory-probe", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--out", default="runs/bench_sim", help="output folder (default runs/bench_sim)")
    args = parser.parse_args(argv)
    compile_at_once()
    if args.memory_probe is not None:
        print(json.dumps(memory_probe(args.scenario, args.memory_probe, args.steps)))
        return 0
    if min(args.steps, args.mpc_steps, args.rl_steps, args.highway_envs, args.threads) < 1:
        parser.error("--steps, --mpc-steps, --rl-steps, --highway-envs and --threads must be >= 1")
    unknown = sorted(set(args.mpc_schedules) - set(SCHEDULES))
    if unknown or not args.mpc_schedules:
        parser.error(f"--mpc-schedules takes names of {list(SCHEDULES)}; got {list(args.mpc_schedules)}")
    torch.set_num_threads(args.threads)
    scenario = load_scenario(args.scenario, {"sim": "batched"})  # refused here if the batched simulator cannot run it
    rows = world_rows(scenario, args.envs, args.steps, args.highway_envs)
    if not args.no_mpc:
        for name in args.mpc_scenarios or (args.scenario,):
            rows += mpc_rows(name, args.mpc_envs, args.mpc_steps, args.mpc_schedules)
    if not args.no_rl:
        unknown = sorted(set(args.rl_worlds) - set(RL_WORLDS))
        if unknown or not args.rl_worlds:
            parser.error(f"--rl-worlds takes names of {list(RL_WORLDS)}; got {list(args.rl_worlds)}")
        rows += rl_rows(args.rl_envs, args.rl_steps, args.rl_replan, args.rl_warmup, args.rl_config, args.rl_worlds,
                        args.rl_verify)
    if not args.no_memory:
        rows += memory_rows(args.scenario, args.memory_envs, max(2, args.steps // 4))
    print(format_rows(rows))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report = {
        "machine": {"platform": platform.platform(), "processor": platform.processor(), "cpus": os.cpu_count(),
                    "torch": torch.__version__, "threads": args.threads},
        "settings": {key: value for key, value in vars(args).items() if key != "memory_probe"},
        "compile": os.environ.get("MMPC_COMPILE", "auto"),
        "rows": rows,
    }
    (out / "bench_sim.json").write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {out / 'bench_sim.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
