"""What a frame of the highway-env world costs with highway-env's own Kinematics observation
(pandas, built at every ``env.step`` and once more when observed) against the deferred numpy one
(mmpc.highway.kinematics.DeferredKinematics), side by side in one run: the same seeds, the same
commands (hold speed, straight), the world's ``observe`` + ``apply`` per frame.

    python docs/experiments/2026-11-29-rl-grid/highway_env_frame_cost.py --seeds 90000-90007 --frames 100
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch
from highway_env.envs.common.observation import KinematicObservation

from mmpc.cli.arguments import seed_list
from mmpc.highway.highway_env_world import HighwayEnvWorld
from mmpc.scenario import load_scenario


class PandasKinematics(KinematicObservation):
    """highway-env's observation with the deferred one's ``compute``: what the world did before."""

    def compute(self) -> np.ndarray:
        return np.asarray(self.observe(), dtype=np.float32)


def frame_seconds(seeds: list[int], frames: int, pandas: bool) -> tuple[float, np.ndarray]:
    """Seconds per environment-frame of observe + apply, and the last Kinematics rows (E, 5, 5)."""
    world = HighwayEnvWorld.start(load_scenario("cruise"), seeds)
    if pandas:
        for episode in world.episodes:
            episode.unwrapped.observation_type = PandasKinematics(episode.unwrapped, vehicles_count=5)
    rows = list(range(len(seeds)))
    zeros = torch.zeros(len(seeds))
    start = time.perf_counter()
    for _ in range(frames):
        observation, _ = world.observe(rows)
        world.apply(rows, zeros, zeros)
    seconds = (time.perf_counter() - start) / (frames * len(seeds))
    last = np.asarray(world.observe(rows)[0].kinematics)
    world.close()
    return seconds, last


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=seed_list, default="90000-90007")
    parser.add_argument("--frames", type=int, default=100)
    args = parser.parse_args()
    torch.set_num_threads(1)
    pandas, pandas_rows = frame_seconds(args.seeds, args.frames, pandas=True)
    numpy_, numpy_rows = frame_seconds(args.seeds, args.frames, pandas=False)
    print("| Kinematics | ms per environment-frame |\n|---|---:|")
    print(f"| highway-env's (pandas, every env.step and when observed) | {pandas * 1e3:.2f} |")
    print(f"| deferred, numpy | {numpy_ * 1e3:.2f} |")
    print(f"ratio {pandas / numpy_:.2f}x; the last frame's rows equal: {np.array_equal(pandas_rows, numpy_rows)}")
    print(json.dumps({"seeds": [args.seeds[0], args.seeds[-1]], "frames": args.frames, "pandas_ms": pandas * 1e3,
                      "numpy_ms": numpy_ * 1e3, "equal": bool(np.array_equal(pandas_rows, numpy_rows))}))


if __name__ == "__main__":
    main()
