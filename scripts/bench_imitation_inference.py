"""Inference cost per control step: the cloned policy vs the MPC expert on the same states.

The expert drives one episode to collect states; then both drivers decide those states (E = 1,
as in a single closed loop), after a warm-up, in two orders measured in the same run:

- ``consecutive``: each driver decides ``block`` consecutive states in a row, then the other
  driver the same states (which driver starts alternates from block to block). Each driver runs
  as in its own closed loop, one decision after the other.
- ``interleaved``: state by state, the expert then the policy. Every policy call then follows a
  ~20 ms expert solve that has flushed the CPU caches, so this is the policy's cold-cache cost.

The figures are the drivers' own ``solve_ms`` -- the wall time of the whole decision (problem
building, optimizer, ranking and command for the expert; the neighbour selection, the
road-frame features and the forward pass for the policy).
"""

from __future__ import annotations

import argparse
import json
import sys
import platform
import statistics
import time
from pathlib import Path
from typing import Optional, Sequence

import torch

from mmpc.cli.arguments import compile_at_once, override
from mmpc.drivers import Driver, MPCDriver, Observation
from mmpc.imitation.policy import PolicyDriver, load_policy
from mmpc.imitation.rollout import rollout_lockstep
from mmpc.scenario import ScenarioConfig, build_mpc, load_scenario

#: The orders in which the drivers are timed (see the module docstring).
MODES = ("consecutive", "interleaved")


def _time_blocks(drivers: dict[str, Driver], states: list[Observation], block: int) -> dict[str, list[float]]:
    """``solve_ms`` of every driver on every state, ``block`` states per driver in a row."""
    times: dict[str, list[float]] = {name: [] for name in drivers}
    names = list(drivers)
    for index, start in enumerate(range(0, len(states), block)):
        for name in names if index % 2 == 0 else names[::-1]:
            times[name] += [drivers[name].decide(state).solve_ms for state in states[start:start + block]]
    return times


def _row(values: list[float]) -> dict:
    ordered = sorted(values)
    return {"mean_ms": statistics.fmean(values), "median_ms": statistics.median(values),
            "p95_ms": ordered[min(len(ordered) - 1, int(0.95 * len(ordered)))], "steps": len(values)}


def benchmark_inference(scenario: ScenarioConfig, checkpoint: Path, *, seed: int = 0, steps: int = 200, warmup: int = 10,
                        block: int = 50) -> dict:
    """Time both drivers on the first ``steps`` states of an expert episode.

    Args:
        scenario: the scenario (its MPC is the expert).
        checkpoint: the policy.
        seed: the episode whose states are timed.
        steps: states timed per driver and mode (fewer if the episode ends earlier).
        warmup: states decided by both drivers before timing.
        block: consecutive states per driver in the ``consecutive`` mode.

    Returns:
        A JSON-able report: per mode (:data:`MODES`) and driver mean / median / p95 ms per step,
        the ratios of the means and medians per mode, the machine and torch threads. The
        top-level ``rows``, ``speedup_mean`` and ``speedup_median`` are the ``consecutive`` mode's.
    """
    if steps < 1 or warmup < 0 or block < 1:
        raise ValueError(f"`steps` and `block` must be >= 1 and `warmup` >= 0; got {steps}, {block}, {warmup}")
    drivers: dict[str, Driver] = {"expert": MPCDriver(build_mpc(scenario), period=scenario.period),
                                  "policy": PolicyDriver(load_policy(checkpoint))}
    scenario = scenario.replace(duration=min(scenario.duration, steps / scenario.frequency))
    modes = {}
    with torch.inference_mode():
        states = rollout_lockstep(scenario, [seed], drivers["expert"], keep_states=True)[0].states
        _time_blocks(drivers, states[:warmup], 1)
        for mode, size in (("consecutive", block), ("interleaved", 1)):
            rows = {name: _row(values) for name, values in _time_blocks(drivers, states, size).items()}
            modes[mode] = {"block": size, "rows": rows,
                           "speedup_mean": rows["expert"]["mean_ms"] / rows["policy"]["mean_ms"],
                           "speedup_median": rows["expert"]["median_ms"] / rows["policy"]["median_ms"]}
    return {
        "scenario": scenario.name,
        "seed": seed,
        "policy": str(checkpoint),
        "hidden": list(drivers["policy"].policy.config.hidden),
        **{key: modes["consecutive"][key] for key in ("rows", "speedup_mean", "speedup_median")},
        "modes": modes,
        "torch_threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "machine": f"{platform.machine()} {platform.processor() or platform.platform()}",
        "date": time.strftime("%Y-%m-%d"),
    }


def format_report(report: dict) -> str:
    lines = [f"{'order':<12} {'driver':<8} {'mean ms':>9} {'median ms':>10} {'p95 ms':>9} {'steps':>6} {'ratio (means)':>14}"]
    for mode in MODES:
        entry = report["modes"][mode]
        for name, row in entry["rows"].items():
            ratio = f"{entry['speedup_mean']:.0f}x" if name == "policy" else ""
            lines.append(f"{mode:<12} {name:<8} {row['mean_ms']:9.3f} {row['median_ms']:10.3f} {row['p95_ms']:9.3f} "
                         f"{row['steps']:6d} {ratio:>14}")
    lines.append(f"policy is {report['speedup_mean']:.0f}x cheaper per step (means; consecutive decisions, as in a closed "
                 f"loop), {report['modes']['interleaved']['speedup_mean']:.0f}x right after each expert solve; "
                 f"{report['torch_threads']} torch thread(s)")
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> int:
    bench = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    bench.add_argument("--scenario", default="cruise", help="scenario name in configs/scenarios or a YAML path (default cruise)")
    bench.add_argument("--set", type=override, action="append", default=[], metavar="KEY=VALUE",
                       help="override a scenario value (YAML; repeatable)")
    bench.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    bench.add_argument("--policy", required=True, help="RUN/policy.pt")
    bench.add_argument("--seed", type=int, default=0, help="episode whose states are timed (default 0)")
    bench.add_argument("--steps", type=int, default=200, help="states timed (default 200)")
    bench.add_argument("--block", type=int, default=50,
                       help="consecutive states per driver in the 'consecutive' order (default 50)")
    bench.add_argument("--out", default="benchmarks/bench_imitation_inference.json", help="JSON output")
    args = bench.parse_args(argv)
    compile_at_once()
    torch.set_num_threads(args.threads)
    scenario = load_scenario(args.scenario, dict(args.set))
    report = benchmark_inference(scenario, Path(args.policy), seed=args.seed, steps=args.steps, block=args.block)
    print(format_report(report))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
