"""Re-read the crash scenes of batched-simulator episodes at the impact and after the collision push.

Runs ``mmpc.highway.run_lockstep`` of the mmpc found on the path (a worktree of an older commit
put first on PYTHONPATH, or this one) for the given scenario and seeds, and prints, per crashed
episode, the scene as read after the push (how mmpc read it before 2026-11-27) and at the impact.
In a tree without ``World.observe_impact`` the push is taken back here, as that method does.

    PYTHONPATH=<tree> python retally.py SCENARIO.yaml SEEDS [--set key=value ...] [--json OUT]
"""

import argparse
import json
import logging
import sys

import torch

from mmpc.collisions import crash_scene, is_ego_fault
from mmpc.highway import run_lockstep
from mmpc.highway.worlds import BatchedWorld
from mmpc.scenario import load_scenario
from mmpc.sim import SimEpisodes

READINGS: dict[int, dict] = {}  # seed -> {"pushed": Crash, "impact": Crash}


def _scene(observation, scenario):
    ego, vehicles = observation.ego[0].tolist(), observation.vehicles[0]
    if observation.vehicle_mask is not None:
        vehicles = vehicles[observation.vehicle_mask[0]]
    return crash_scene(tuple(ego[:4]), vehicles.tolist(), scenario.vehicle, scenario.road.lane_width)


def _patch_old_tree() -> None:
    """An older tree reads the crash with ``world.observe([i])`` after the step: record the pushes
    each step applies and hand the runner the scene without them."""
    step, observe = SimEpisodes.step, BatchedWorld.observe

    def recording_step(self, command, running=None):
        before = self.state
        pushes = torch.where((before.impact_pending & before.alive)[..., None], before.impact, 0.0)
        step(self, command, running)
        self.pushes = pushes if running is None else torch.where(running[:, None, None], pushes, 0.0)

    def impact_observe(self, active):
        batch, singles = observe(self, active)
        if len(active) != 1 or not self.crashed[active[0]]:
            return batch, singles
        i = active[0]
        pushed = singles[0]
        push = self.sim.pushes[i]
        ego, vehicles = pushed.ego.clone(), pushed.vehicles.clone()
        ego[0, :2] -= push[0]
        vehicles[0, :, :2] -= push[1:]
        impact = pushed._replace(ego=ego, vehicles=vehicles)
        READINGS[self.seeds[i] if hasattr(self, "seeds") else int(self.sim.seeds[i])] = {
            "pushed": _scene(pushed, self.scenario), "impact": _scene(impact, self.scenario)}
        return batch, [impact]

    SimEpisodes.step, BatchedWorld.observe = recording_step, impact_observe


def _patch_this_tree() -> None:
    observe_impact = BatchedWorld.observe_impact

    def recording(self, index):
        impact = observe_impact(self, index)
        READINGS[self.seeds[index]] = {"pushed": _scene(self.observe([index])[1][0], self.scenario),
                                       "impact": _scene(impact, self.scenario)}
        return impact

    BatchedWorld.observe_impact = recording


def _seeds(text: str) -> list[int]:
    seeds = []
    for part in text.split(","):
        low, _, high = part.partition("-")
        seeds.extend(range(int(low), int(high or low) + 1))
    return seeds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenario")
    parser.add_argument("seeds")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--json")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    torch.set_num_threads(1)
    import yaml
    overrides = {key: yaml.safe_load(value) for key, _, value in (item.partition("=") for item in args.set)}
    overrides["sim"] = "batched"
    scenario = load_scenario(args.scenario, overrides)
    (_patch_this_tree if hasattr(BatchedWorld, "observe_impact") else _patch_old_tree)()
    results = run_lockstep(scenario, _seeds(args.seeds))
    rows = []
    for result in results:
        if not result.metrics["collisions"]:
            continue
        seed = result.seed
        reading = READINGS[seed]
        row = {"seed": seed, "time": result.metrics["crash_time"]}
        for name in ("pushed", "impact"):
            crash = reading[name]
            row[name] = {"part": crash.part, "fault": int(is_ego_fault(crash.part)), "along": round(crash.along, 2),
                         "across": round(crash.across, 2), "ego_offset": round(crash.ego_offset, 2),
                         "other_heading_deg": round(crash.other_heading_deg, 1)}
        rows.append(row)
    print("| seed | t [s] | after the push: part, ahead, +y, ego offset | at the impact: part, ahead, +y, ego offset |")
    print("|---|---:|---|---|")
    for row in rows:
        p, i = row["pushed"], row["impact"]
        print(f"| {row['seed']} | {row['time']:.1f} | {p['part']}, {p['along']}, {p['across']}, {p['ego_offset']} "
              f"| {i['part']}, {i['along']}, {i['across']}, {i['ego_offset']} |")
    print(f"{len(rows)} crashes in {len(results)} episodes", file=sys.stderr)
    if args.json:
        with open(args.json, "w") as handle:
            json.dump({"scenario": args.scenario, "seeds": args.seeds, "set": args.set, "crashes": rows}, handle, indent=1)


if __name__ == "__main__":
    main()
