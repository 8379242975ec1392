"""highway-env's task return of the ceilings' best episodes (issue 67, deliverable 3's reference).

Replays every seed's commands of `python scripts/ceiling.py` (``ceiling.jsonl``) on the batched world,
all seeds at once, and sums the task reward (:func:`mmpc.rl.reward.task_rewards`, HighwayEnv's
defaults) over the frames. The search ranked by distance, not by this reward: its episodes are a
reference the task's own ceiling is at or above. A replay that does not drive the distance the search
recorded (the scenario changed since) is refused.

    python docs/experiments/2026-11-29-rl-grid/ceiling_task_return.py runs/ceiling/high_speed/ceiling.jsonl --kind verified
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from mmpc.evaluate.intervals import mean_ci
from mmpc.highway.batched_world import BatchedWorld
from mmpc.rl.config import RewardConfig
from mmpc.rl.reward import task_rewards
from mmpc.scenario import load_scenario
from mmpc.sim import SimEpisodes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("ceiling", type=Path)
    parser.add_argument("--kind", default="verified", choices=("verified", "unprotected"))
    args = parser.parse_args()
    rows = [json.loads(line) for line in args.ceiling.read_text().splitlines() if line.strip()]
    rows = [row for row in rows if row["kind"] == args.kind and not row["crashed"]]
    names = {row["scenario"] for row in rows}
    if len(names) != 1:
        raise SystemExit(f"one scenario per file; got {sorted(names)}")
    steps = len(rows[0]["commands"])
    scenario = load_scenario(names.pop()).replace(sim="batched", duration=steps / 10.0)
    world = BatchedWorld(SimEpisodes(scenario, [row["seed"] for row in rows]), kinematics=False)
    everyone = torch.arange(len(rows))
    commands = torch.tensor([row["commands"] for row in rows], dtype=torch.float64)  # (E, T, 2)
    start_x = world.sim.state.x[:, 0].double().clone()
    total = torch.zeros(len(rows), dtype=torch.float64)
    for step in range(steps):
        world.apply(everyone, commands[:, step, 0], commands[:, step, 1])
        total += task_rewards(world.ego_terms(everyone), RewardConfig(), scenario).double().cpu()
    distance = (world.sim.state.x[:, 0].double() - start_x).cpu().numpy()
    recorded = np.array([row["distance"] for row in rows])
    if not np.allclose(distance, recorded, atol=0.5):
        worst = int(np.argmax(np.abs(distance - recorded)))
        raise SystemExit(f"seed {rows[worst]['seed']}: replay drove {distance[worst]:.2f} m, the search {recorded[worst]:.2f} m")
    mean, interval = mean_ci(total.tolist())
    print(f"{args.ceiling}: {len(rows)} seeds x {steps / 10:.0f} s, kind {rows[0]['kind']}, "
          f"task return {mean:.1f} [{interval[0]:.1f}, {interval[1]:.1f}] of {steps}, "
          f"distance {distance.mean():.1f} m (recorded {recorded.mean():.1f})")
    for row, value in zip(rows, total.tolist()):
        print(f"  {row['seed']}: {value:.1f}")


if __name__ == "__main__":
    main()
