"""Where the smoke recipe's fail-safe frames fall: random agents behind the default layer in the smoke
recipe's 2 s episodes (batched world), the fail-safe share of each agent step of an episode.

    python docs/experiments/2026-11-29-recipe-smokes/failsafe_by_frame.py [EPISODES]
"""

import collections
import sys

import numpy as np
import torch

from mmpc.config import load_config
from mmpc.rl.config import RLConfig
from mmpc.rl.vec_env import SafeVecEnv

torch.set_num_threads(1)
config = load_config(RLConfig, "smoke")
count = int(sys.argv[1]) if len(sys.argv) > 1 else 64
venv = SafeVecEnv(count, config.scenario.replace(sim="batched"), config.env, config.reward)
venv.seed(71800)
venv.reset()
rng = np.random.default_rng(0)
failsafe, frames, step_of = collections.Counter(), collections.Counter(), [0] * count
for _ in range(3 * round(config.scenario.duration * config.scenario.frequency / config.env.decision_frames)):
    _, _, dones, infos = venv.step(rng.integers(0, config.env.num_discrete_goals, count))
    for row, info in enumerate(infos):
        failsafe[step_of[row]] += info["failsafe_frames"]
        frames[step_of[row]] += info["frames"]
        step_of[row] = 0 if dones[row] else step_of[row] + 1
for step in sorted(frames):
    print(f"agent step {step} of its episode: fail-safe {failsafe[step]} of {frames[step]} frames "
          f"({100 * failsafe[step] / frames[step]:.1f} %)")
