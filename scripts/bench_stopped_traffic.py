"""Fail-safe grid: does every driver stop for stopped traffic on highway-env?

Scenes of :mod:`mmpc.highway.stopped_traffic` (a wall of stopped cars across a 3-lane road, one stopped
car on a 1-lane road, a car that cuts in and brakes hard; ego speeds 10-30 m/s; gaps of 1.3-5x
the braking distance at the optimizer's acceleration bound), each driven by the MPC, the MPC behind
the verification (``verified:mpc``), the Frenet baseline (whose fallback is the MPC's) and the safe RL
layer under a uniformly random agent.
Prints a table and writes JSON.

    python scripts/bench_stopped_traffic.py --out benchmarks/bench_stopped_traffic.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import torch

from mmpc.highway.runner import run_episode
from mmpc.scenario import load_scenario
from mmpc.highway.stopped_traffic import LAYOUTS, stopped_traffic_grid, stopped_traffic_scene

DRIVERS = ("mpc", "verified:mpc", "frenet", "safe_rl_random")


def drive_random_agent(scenario, seed: int) -> dict:
    """One episode of the discrete safe RL environment with uniformly random actions."""
    from mmpc.rl.envs import SafeHighwayEnv

    env = SafeHighwayEnv(scenario)
    env.action_space.seed(seed)
    env.reset(seed=seed)
    info, crashed, terminated, truncated = {}, False, False, False
    while not (terminated or truncated):
        _, _, terminated, truncated, info = env.step(int(env.action_space.sample()))
        crashed = crashed or bool(info["crashed"])
    ego = env.episode.ego
    env.close()
    return {"collisions": int(crashed), "final_speed": float(ego.speed), "x": float(ego.position[0])}


def drive(task: tuple) -> dict:
    """One (driver, scene) episode -> its row; an exception becomes a failed row with its message."""
    driver, base_name, layout, speed, ratio = task
    torch.set_num_threads(1)
    scene = stopped_traffic_scene(load_scenario(base_name), layout, speed, ratio)
    start = time.perf_counter()
    try:
        outcome = _drive(driver, scene)
    except Exception as error:  # noqa: BLE001 - reported in the table, the other episodes go on
        outcome = {"collisions": -1, "final_speed": float("nan"), "x": float("nan"), "error": repr(error)}
    passed = "error" not in outcome and scene.passed(outcome["collisions"], outcome["final_speed"])
    return {"driver": driver, "objective": base_name, "scene": scene.name, "layout": layout, "speed": speed,
            "ratio": ratio, "gap_m": round(scene.gap, 2), "duration_s": scene.scenario.duration, **outcome,
            "passed": passed, "wall_s": round(time.perf_counter() - start, 1)}


def _drive(driver: str, scene) -> dict:
    """One episode of ``driver`` in ``scene``: collisions, final speed and position, and for the
    planners their fallback steps and smallest normalised ellipse distance."""
    if driver == "safe_rl_random":
        return drive_random_agent(scene.scenario, seed=0)
    from mmpc.drivers import make_driver

    result = run_episode(scene.scenario, 0, driver=make_driver(driver, scene.scenario))
    last = result.records[-1]
    return {"collisions": int(result.metrics["collisions"]), "final_speed": last.v, "x": last.x,
            "fallback_steps": int(result.metrics["fallback_steps"]), "min_clearance": min(r.clearance for r in result.records)}


def format_table(rows: list[dict]) -> str:
    lines = ["| driver | objective | scene | gap [m] | collisions | final v [m/s] | passed | fallback steps |",
             "|---|---|---|---:|---:|---:|---|---:|"]
    for r in rows:
        lines.append(f"| {r['driver']} | {r['objective']} | {r['scene']} | {r['gap_m']:.1f} | {r['collisions']} | "
                     f"{r['final_speed']:.2f} | {'yes' if r['passed'] else 'NO'} | {r.get('fallback_steps', '-')} |")
    return "\n".join(lines)


def format_summary(rows: list[dict]) -> str:
    """Passed / total and collisions per driver, objective and layout."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["driver"], r["objective"], r["layout"]), []).append(r)
    lines = ["| driver | objective | layout | passed | collisions |", "|---|---|---|---:|---:|"]
    for (driver, objective, layout), group in sorted(groups.items(), key=lambda item: (item[0][:2], LAYOUTS.index(item[0][2]))):
        passed = sum(r["passed"] for r in group)
        collisions = sum(max(r["collisions"], 0) for r in group)
        lines.append(f"| {driver} | {objective} | {layout} | {passed} / {len(group)} | {collisions} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--drivers", default=",".join(DRIVERS), help=f"comma-separated, of {DRIVERS}")
    parser.add_argument("--objectives", default="cruise,high_speed", help="shipped scenarios whose objective and MPC drive")
    parser.add_argument("--speeds", default="10,20,30", help="ego speeds [m/s]")
    parser.add_argument("--ratios", default="1.3,2,5", help="gaps in braking distances")
    parser.add_argument("--workers", type=int, default=2, help="processes (default 2)")
    parser.add_argument("--out", default="benchmarks/bench_stopped_traffic.json", help="JSON report")
    args = parser.parse_args(argv)
    drivers = [d for d in args.drivers.split(",") if d]
    unknown = sorted(set(drivers) - set(DRIVERS))
    if unknown:
        parser.error(f"unknown drivers {unknown}; expected some of {DRIVERS}")
    speeds = tuple(float(v) for v in args.speeds.split(","))
    ratios = tuple(float(r) for r in args.ratios.split(","))
    tasks = []
    for base_name in args.objectives.split(","):
        for scene in stopped_traffic_grid(load_scenario(base_name), speeds, ratios):
            tasks += [(driver, base_name, scene.layout, scene.speed, scene.ratio) for driver in drivers]
    start = time.perf_counter()
    with ProcessPoolExecutor(args.workers) as pool:
        rows = []
        for row in pool.map(drive, tasks):
            rows.append(row)
            print(f"[{len(rows)}/{len(tasks)}] {row['driver']} {row['objective']} {row['scene']}: collisions "
                  f"{row['collisions']}, final v {row['final_speed']:.2f}", file=sys.stderr, flush=True)
    print(format_table(rows))
    print(format_summary(rows))
    failed = [r["scene"] + "/" + r["driver"] for r in rows if not r["passed"]]
    print(f"{len(rows) - len(failed)} of {len(rows)} episodes passed (no collision; at rest where every lane is blocked); "
          f"collisions {sum(r['collisions'] for r in rows)}; {time.perf_counter() - start:.0f} s")
    if failed:
        print("failed:", ", ".join(failed))
    for row in rows:
        if "error" in row:
            print(f"error in {row['scene']}/{row['driver']}: {row['error']}")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({"rows": rows, "argv": sys.argv[1:], "torch_threads": 1}, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
