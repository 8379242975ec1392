"""Option (b): the ego may brake as hard as the other cars (6 m/s^2): its action range and the fail-safes at 6.
Usage: python brake6.py 71168 8 (first seed, episodes; high speed, batched, 20 s)"""
import sys, dataclasses, inspect, statistics as st, torch
from mmpc.sim.config import SimConfig
names = [p for p in inspect.signature(SimConfig).parameters]
defaults = list(SimConfig.__init__.__defaults__)
defaults[len(defaults) - len(names) + names.index("acceleration_range")] = (-6.0, 6.0)
SimConfig.__init__.__defaults__ = tuple(defaults)
assert SimConfig().acceleration_range == (-6.0, 6.0)
from mmpc.scenario import load_scenario
from mmpc.highway.runner import run_lockstep
from mmpc.drivers import make_driver
from mmpc.drivers.verified import VerifiedDriver
from mmpc.verify import FailSafes, Verifier
torch.set_num_threads(1)
seed0, n = int(sys.argv[1]), int(sys.argv[2])
scen = load_scenario("high_speed", {"sim": "batched", "duration": 20.0})
driver = VerifiedDriver(make_driver("mpc", scen), Verifier.for_scenario(scen, failsafes=FailSafes(decelerations=(6.0,))))
res = run_lockstep(scen, list(range(seed0, seed0 + n)), driver=driver)
ms = [r.metrics for r in res]
print("brake 6", "speed", round(st.mean(m["mean_speed"] for m in ms), 2), "verified", round(st.mean(m["verified_share"] for m in ms), 4),
      "collisions", sum(m["collisions"] for m in ms), "failsafe", sum(m["failsafe_steps"] for m in ms))
