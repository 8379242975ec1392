"""Agent steps/s of the batched safe RL environment at E environments, the solve split out.

    python rl_steps.py E WARM_ITERATIONS STEPS [WARM_KEEP_SHARE [WARM_COLD_EVERY]]

The cruise task recipe (configs/rl/cruise_task.yaml) on the batched simulator, one torch thread,
random actions of the grid; 4 untimed agent steps, then STEPS timed ones. What solves spend
compiling new call layouts is taken out of the time (paid once per layout in a run). Prints one
JSON line: agent steps/s, the solve's and the rest's seconds, iterations per solved element, and
the layer's interventions, fallbacks and feasible goals over the timed steps; ``dec_*`` the
decision solves (the 38 goals: grid and standard), ``rep_*`` the replans between decisions.
"""

import collections
import dataclasses
import json
import sys
import time

import numpy as np
import torch

from mmpc.config import load_config
from mmpc.rl.config import RLConfig
from mmpc.rl.sim_vec_env import SafeSimVecEnv

torch.set_num_threads(1)
E, warm, steps = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
cold_every = int(sys.argv[5]) if len(sys.argv) > 5 else 10
config = load_config(RLConfig, "cruise_task")
share = float(sys.argv[4]) if len(sys.argv) > 4 else config.scenario.mpc.warm_keep_share
mpc_config = dataclasses.replace(config.scenario.mpc, warm_iterations=warm, warm_keep_share=share, warm_cold_every=cold_every)
venv = SafeSimVecEnv(E, config.scenario.replace(sim="batched", mpc=mpc_config), config.env, config.reward)
mpc = venv.layer.mpc
timers = collections.defaultdict(float)
score = mpc.score


def timed_score(problem, *args):
    start = time.perf_counter()
    scored = score(problem, *args)
    timers["score_wall"] += time.perf_counter() - start
    timers["compile"] += scored.compile_ms / 1e3
    timers["solve"] += scored.solve_ms / 1e3
    timers["elements"] += problem.goals.shape[0] * problem.goals.shape[1]
    timers["iters"] += float(scored.result.iterations.float().sum())
    kind = "dec" if problem.goals.shape[1] == 38 else "rep"
    timers[kind + "_solve"] += scored.solve_ms / 1e3
    timers[kind + "_elements"] += problem.goals.shape[0] * problem.goals.shape[1]
    timers[kind + "_iters"] += float(scored.result.iterations.float().sum())
    return scored


mpc.score = timed_score
venv.seed(0)
venv.reset()
rng = np.random.default_rng(0)
actions = [rng.integers(0, config.env.num_actions, E) for _ in range(4 + steps)]
for action in actions[:4]:
    venv.step(action)
timers.clear()
stats = collections.defaultdict(float)
start = time.perf_counter()
for action in actions[4:]:
    _, _, _, infos = venv.step(action)
    for info in infos:
        for key in ("intervention_frames", "fallback_frames", "frames", "feasible_goals"):
            stats[key] += info[key]
wall = time.perf_counter() - start - timers["compile"]
print(json.dumps({"E": E, "warm": warm, "share": share, "cold_every": cold_every, "agent_steps_per_s": E * steps / wall, "wall_s": wall,
                  "rest_s": wall - (timers["score_wall"] - timers["compile"]),
                  "iterations_per_element": timers["iters"] / max(timers["elements"], 1), **timers, **stats}))
