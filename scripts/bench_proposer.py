"""Solve time per decision: the MPC expert vs the mode proposer's driver, side by side in one run.

Every driver drives the same seeded episodes on the batched simulator, E of them per call (the
lockstep batch of ``mmpc evaluate``), for ``--duration`` seconds; the figure is the drivers' own
``solve_ms`` per decision (the whole decision: goal set, proposal, optimizer, ranking, escalations),
after a warm-up episode that compiles every layout. Prints a table and writes JSON.

    python scripts/bench_proposer.py --scenario high_speed --proposer high_speed --envs 1,50,256 --keep 3,4 --out runs/bench_proposer
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
from pathlib import Path

import torch

from mmpc.cli.arguments import compile_at_once
from mmpc.drivers import Driver, MPCDriver
from mmpc.highway import run_lockstep
from mmpc.imitation.proposer import load_proposer
from mmpc.imitation.proposer_driver import SHIPPED_PROPOSERS, ProposerDriver, shipped_proposers
from mmpc.scenario import ScenarioConfig, build_mpc, load_scenario


def solve_ms(scenario: ScenarioConfig, driver: Driver, seeds: list[int]) -> tuple[float, int]:
    """Mean ``solve_ms`` per decision of ``driver`` over one lockstep run of ``seeds``, and the decisions."""
    times = []
    for result in run_lockstep(scenario, seeds, driver=driver):
        times += [record.solve_ms for record in result.records]
    return statistics.mean(times), len(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="high_speed")
    parser.add_argument("--proposer", default="high_speed", help="a checkpoint or a shipped name")
    parser.add_argument("--envs", default="1,50,256", help="environments per call, comma-separated")
    parser.add_argument("--keep", default="3,4", help="proposer goals kept besides the forced ones, comma-separated")
    parser.add_argument("--duration", type=float, default=5.0, help="seconds driven per measurement")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    compile_at_once()
    torch.set_num_threads(args.threads)
    scenario = load_scenario(args.scenario).replace(sim="batched", duration=args.duration)
    path = Path(args.proposer)
    proposer = load_proposer(path if path.is_file() or args.proposer not in shipped_proposers()
                             else SHIPPED_PROPOSERS / f"{args.proposer}.pt")
    mpc = build_mpc(scenario)
    drivers = {"mpc": lambda: MPCDriver(mpc, period=scenario.period)}
    for keep in (int(k) for k in args.keep.split(",")):
        drivers[f"proposer keep {keep}"] = lambda keep=keep: ProposerDriver(mpc, proposer, keep=keep)
    rows = []
    print(f"{'E':>5} {'driver':<18} {'ms / decision':>14} {'ms / env-step':>14} {'speed-up':>9} {'escalated':>9}")
    for envs in (int(e) for e in args.envs.split(",")):
        seeds = list(range(70000, 70000 + envs))
        reference = None
        for name, make in drivers.items():
            driver = make()
            solve_ms(scenario.replace(duration=0.3), driver, seeds)  # compiles this batch's layouts
            driver = make()
            ms, decisions = solve_ms(scenario, driver, seeds)
            reference = ms if reference is None else reference
            escalated = getattr(driver, "escalated_rows", 0) / max(getattr(driver, "decided_rows", 1), 1)
            rows.append({"envs": envs, "driver": name, "ms_per_decision": ms, "ms_per_env_step": ms / envs,
                         "speedup": reference / ms, "escalated_share": escalated, "decisions": decisions})
            print(f"{envs:>5} {name:<18} {ms:>14.1f} {ms / envs:>14.2f} {reference / ms:>8.2f}x {escalated:>9.1%}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result = {"machine": {"platform": platform.platform(), "torch": torch.__version__, "threads": args.threads,
                          "compiled": mpc.optimizer.compiled},
              "settings": vars(args), "rows": rows}
    (out / "bench_proposer.json").write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out / 'bench_proposer.json'}")


if __name__ == "__main__":
    main()
