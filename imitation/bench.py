"""Inference cost per control step: the cloned policy vs the MPC expert on the same states
(``mmpc imitate bench``).

The expert drives one episode to collect states; then, state by state and side by side, the
expert's :meth:`~mmpc.drivers.MPCDriver.decide` and the policy's
:meth:`~mmpc.imitation.policy.PolicyDriver.decide` are timed on that state (E = 1, as in a
single closed loop), after a warm-up. The figures are the drivers' own ``solve_ms`` -- the
wall time of the whole decision (problem building, optimizer, ranking and command for the
expert; the neighbour selection, the road-frame features and the forward pass for the policy).
"""

from __future__ import annotations

import platform
import statistics
import time
from pathlib import Path

import torch

from mmpc.drivers import MPCDriver
from mmpc.imitation.policy import PolicyDriver, load_policy
from mmpc.imitation.rollout import rollout_lockstep
from mmpc.scenario import ScenarioConfig, build_mpc


def benchmark_inference(scenario: ScenarioConfig, checkpoint: Path, *, seed: int = 0, steps: int = 200, warmup: int = 10) -> dict:
    """Time both drivers on the first ``steps`` states of an expert episode.

    Returns:
        A JSON-able report: per driver mean / median / p95 ms per step, the ratio of the means
        and medians, the machine and torch threads.
    """
    if steps < 1 or warmup < 0:
        raise ValueError(f"`steps` must be >= 1 and `warmup` >= 0; got {steps}, {warmup}")
    expert = MPCDriver(build_mpc(scenario))
    policy = PolicyDriver(load_policy(checkpoint))
    scenario = scenario.replace(duration=min(scenario.duration, steps / scenario.frequency))
    with torch.inference_mode():
        states = rollout_lockstep(scenario, [seed], expert, keep_states=True)[0].states
        for state in states[:warmup]:
            expert.decide(state)
            policy.decide(state)
        times: dict[str, list[float]] = {"expert": [], "policy": []}
        for state in states:
            times["expert"].append(expert.decide(state).solve_ms)
            times["policy"].append(policy.decide(state).solve_ms)
    rows = {}
    for name, values in times.items():
        ordered = sorted(values)
        rows[name] = {"mean_ms": statistics.fmean(values), "median_ms": statistics.median(values),
                      "p95_ms": ordered[min(len(ordered) - 1, int(0.95 * len(ordered)))], "steps": len(values)}
    return {
        "scenario": scenario.name,
        "seed": seed,
        "policy": str(checkpoint),
        "rows": rows,
        "speedup_mean": rows["expert"]["mean_ms"] / rows["policy"]["mean_ms"],
        "speedup_median": rows["expert"]["median_ms"] / rows["policy"]["median_ms"],
        "torch_threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "machine": f"{platform.machine()} {platform.processor() or platform.platform()}",
        "date": time.strftime("%Y-%m-%d"),
    }


def format_report(report: dict) -> str:
    lines = [f"{'driver':<8} {'mean ms':>9} {'median ms':>10} {'p95 ms':>9} {'steps':>6}"]
    for name, row in report["rows"].items():
        lines.append(f"{name:<8} {row['mean_ms']:9.3f} {row['median_ms']:10.3f} {row['p95_ms']:9.3f} {row['steps']:6d}")
    lines.append(f"policy is {report['speedup_mean']:.0f}x cheaper per step (means), {report['speedup_median']:.0f}x (medians); "
                 f"{report['torch_threads']} torch thread(s)")
    return "\n".join(lines)
