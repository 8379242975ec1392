"""Where a verified agent step's time goes at E = 256 in decision mode (the shipped recipes'
`replan: decision`): the layer's guard, its solves, the rest; compiled (MMPC_COMPILE=1), one thread.

    MMPC_COMPILE=1 python docs/experiments/2026-11-29-layer-check-cost/probe.py [CONFIG] [E] [STEPS] [WARMUP] [on|off] [WARM_ITERATIONS]
"""

import collections
import dataclasses
import sys
import time

import numpy as np
import torch

import mmpc.rl.safety as safety
from mmpc.config import load_config
from mmpc.rl.config import RLConfig
from mmpc.rl.vec_env import SafeVecEnv
from mmpc.verify import Guard

torch.set_num_threads(1)
config_name = sys.argv[1] if len(sys.argv) > 1 else "high_speed"
num_envs = int(sys.argv[2]) if len(sys.argv) > 2 else 256
steps = int(sys.argv[3]) if len(sys.argv) > 3 else 8
WARMUP = int(sys.argv[4]) if len(sys.argv) > 4 else 3
VERIFY = sys.argv[5] != "off" if len(sys.argv) > 5 else True
WARM = int(sys.argv[6]) if len(sys.argv) > 6 else None  # mpc.warm_iterations; default: the scenario's
TIMES = collections.defaultdict(float)
COUNTS = collections.Counter()


def timed(owner, name, key):
    function = getattr(owner, name)

    def wrapper(*args, **kwargs):
        start = time.perf_counter()
        try:
            return function(*args, **kwargs)
        finally:
            TIMES[key] += time.perf_counter() - start
            COUNTS[key] += 1
    setattr(owner, name, wrapper)


timed(safety, "guarded_command", "guarded_command")
timed(Guard, "choose", "guard.choose")
from mmpc.verify import Verifier

for name in ("check", "_occupancy", "_meets", "_entry_floor"):
    timed(Verifier, name, f"verifier.{name}")
config = load_config(RLConfig, None if config_name == "defaults" else config_name)
config = dataclasses.replace(config, env=dataclasses.replace(config.env, verify=VERIFY))
if WARM is not None:
    config = dataclasses.replace(config, scenario=config.scenario.replace(
        mpc=dataclasses.replace(config.scenario.mpc, warm_iterations=WARM)))
venv = SafeVecEnv(num_envs, config.scenario.replace(sim="batched"), config.env, config.reward)
timed(venv.layer.mpc, "score", "mpc.score")
score = venv.layer.mpc.score


def counted_score(problem, *args, **kwargs):
    scored = score(problem, *args, **kwargs)
    kind = "warm" if args and args[0] is not None else "cold"
    TIMES[f"score solve_ms ({kind})"] += scored.solve_ms / 1e3
    TIMES[f"score compile_ms ({kind})"] += scored.compile_ms / 1e3
    COUNTS[f"score solve_ms ({kind})"] += 1
    COUNTS[f"rows ({kind})"] += problem.num_problems
    COUNTS[f"iterations ({kind})"] += int(scored.result.problem_iterations().sum())
    return scored


venv.layer.mpc.score = counted_score
timed(venv.layer, "plan", "layer.plan")
timed(venv.layer, "decision_solve", "layer.decision_solve")
timed(venv.layer, "frame", "layer.frame")
rng = np.random.default_rng(0)
venv.seed(0)
venv.reset()
total = 0.0
for step in range(WARMUP + steps):
    if step == WARMUP:
        TIMES.clear()
        COUNTS.clear()
    start = time.perf_counter()
    venv.step(rng.integers(0, config.env.num_discrete_goals, num_envs))
    if step >= WARMUP:
        total += time.perf_counter() - start
print(f"{config_name} E={num_envs} verify={config.env.verify} replan={config.env.replan} "
      f"warm_iterations={config.scenario.mpc.warm_iterations}: "
      f"{num_envs * steps / total:.1f} agent steps/s, {total / steps * 1e3:.0f} ms per vector step")
for key, value in sorted(TIMES.items(), key=lambda item: -item[1]):
    print(f"  {key:28s} {value / steps * 1e3:8.1f} ms per vector step ({COUNTS[key] / steps:.1f} calls)")
for key in sorted(COUNTS):
    if key.startswith(("rows", "iterations")):
        print(f"  {key:28s} {COUNTS[key] / steps:8.1f} per vector step")
