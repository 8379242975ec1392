"""The verified search's node collisions on one seed: each crashed node's commands replayed with the
assumption monitor (did a car leave its set before the crash?) and the verdicts of its commands.
Usage: node_crashes.py SCENARIO SEED DURATION"""
import sys
import torch
from mmpc.collisions import crash_scene
from mmpc.evaluate.ceiling import CeilingConfig, _Search
from mmpc.scenario import load_scenario
from mmpc.sim import SimEpisodes
from mmpc.verify import AssumptionMonitor, TrafficAssumptions, Verifier

name, seed, duration = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
scenario = load_scenario(name, {"duration": duration, "sim": "batched"})
steps = int(round(duration * scenario.frequency))
found = []


class Watched(_Search):
    def _advance(self, beam, children, picked, kept, checks):
        alive_before = beam.alive[picked // children.acceleration.shape[1]] & kept
        super()._advance(beam, children, picked, kept, checks)
        crashed = self.sim.state.crashed[:, 0] & alive_before
        for node in crashed.nonzero().squeeze(1).tolist():
            found.append(self.beam.commands[node, :self.steps].clone())


search = Watched(scenario, [seed], CeilingConfig(), steps)
for _ in range(steps):
    search.step()
unique = {tuple(map(tuple, c.tolist())): c for c in found}
print(f"{len(found)} crashed nodes, {len(unique)} distinct command sequences")
verifier = Verifier.for_scenario(scenario, compile=False)
for commands in unique.values():
    episodes = SimEpisodes(scenario, [seed])
    monitor = AssumptionMonitor(scenario.road, scenario.period, TrafficAssumptions.for_scenario(scenario))
    broke_any, unverified = [], []
    for k, (a, s) in enumerate(commands.tolist()):
        ego, vehicles, mask = episodes.road_state()
        broke = monitor.observe(torch.tensor([0]), ego, vehicles, mask)
        if bool(broke.any()):
            broke_any.append((k, broke[0].nonzero().squeeze(1).tolist()))
        verdict = verifier.check(ego, vehicles, mask, torch.tensor([[a]]), torch.tensor([[s]]))
        if not bool(verdict.verified[0, 0]):
            unverified.append(k)
        episodes.step(torch.tensor([[a, s]]))
        if bool(episodes.crashed[0]):
            ego, vehicles, mask = (field[0] for field in episodes.road_state(at_impact=True))
            others = [tuple(car) for car, present in zip(vehicles.tolist(), mask.tolist()) if present]
            crash = crash_scene(tuple(ego[:4].tolist()), others, scenario.vehicle, scenario.road.lane_width)
            print(f"crash at step {k}: cars outside their sets before it {broke_any}; unverified commands at steps "
                  f"{unverified}; {crash}; ego {[round(v, 2) for v in ego.tolist()]}; last commands "
                  f"{[tuple(round(v, 2) for v in c) for c in commands[k - 4:k + 1].tolist()]}")
            break
