"""The check with one or two braking levels on 32 tuning episodes (71168-71199, high speed, 15 s). Usage: python braking_levels.py 5,3"""
import torch, time, sys
from mmpc.scenario import load_scenario
from mmpc.highway.runner import run_lockstep
from mmpc.drivers import make_driver
from mmpc.verify import FailSafes, Verifier
from mmpc.sim.traffic import sim_config
torch.set_num_threads(1)
scen = load_scenario("high_speed", {"sim": "batched", "duration": 15.0})
decs = tuple(float(x) for x in sys.argv[1].split(','))
d = make_driver("verified:mpc", scen)
d.verifier = Verifier(scen.road, sim_config(scen), failsafes=FailSafes(decelerations=decs), ego_size=scen.vehicle)
t_check = [0.0]
orig = d.verifier.check
def timed(*a, **k):
    t = time.perf_counter(); r = orig(*a, **k); t_check[0] += time.perf_counter() - t; return r
d.verifier.check = timed
t = time.perf_counter()
res = run_lockstep(scen, list(range(71168, 71200)), driver=d)
wall = time.perf_counter() - t
import statistics as st
print(decs, 'wall', round(wall, 1), 'check s', round(t_check[0], 1), 'speed', round(st.mean(r.metrics['mean_speed'] for r in res), 2),
      'verified', round(st.mean(r.metrics['verified_share'] for r in res), 3), 'failsafe', st.mean(r.metrics['failsafe_steps'] for r in res),
      'crashes', sum(r.metrics['collisions'] for r in res))
