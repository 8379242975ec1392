"""Random commands behind the check in threatening traffic, across settings. Usage: sweep.py 'json overrides' N DUR"""
import sys, json, torch
from mmpc.scenario import load_scenario
from mmpc.highway.runner import run_lockstep
from mmpc.drivers.base import Decision, Driver, Observation
from mmpc.drivers.verified import VerifiedDriver
from mmpc.verify import Verifier
torch.set_num_threads(1)

class Random(Driver):
    name = "random"
    def __init__(self): self.g = torch.Generator().manual_seed(0)
    def decide(self, observation):
        n = observation.ego.shape[0]
        acc = torch.rand(n, generator=self.g) * 10 - 5
        steer = (torch.rand(n, generator=self.g) * 2 - 1) * 0.1
        return Decision.command_only(acc, steer, 0.0)

over = {"sim": "batched", "duration": float(sys.argv[3]), **json.loads(sys.argv[1])}
scenario = load_scenario(sys.argv[4] if len(sys.argv) > 4 else "high_speed_threats", over)
n = int(sys.argv[2])
driver = VerifiedDriver(Random(), Verifier.for_scenario(scenario))
res = run_lockstep(scenario, list(range(n)), driver=driver)
crashes = [(r.seed, r.metrics['collision_part'], r.metrics['crash_collider_outside'], r.metrics['failsafe_steps']) for r in res if r.metrics['collisions']]
import statistics as st
print(json.dumps(json.loads(sys.argv[1])), "collisions", len(crashes), "inside", sum(1 for c in crashes if not c[2]), crashes[:6],
      "v", round(st.mean(r.metrics['mean_speed'] for r in res), 2))
for r in res:
    if r.metrics['collisions']:
        v = [int(x.verified) for x in r.records]
        print(r.seed, r.metrics['crash_collider_outside'], ''.join(map(str, v)))
