"""verified:mpc with traffic that reads the ego as an IDM follower (the check then applies the follower rule) against the shipped reading. Usage: follower_cost.py SCENARIO N DUR SEED0"""
import sys, time, statistics as st, torch
from mmpc.scenario import load_scenario
from mmpc.highway.runner import run_lockstep
from mmpc.drivers import make_driver
torch.set_num_threads(1)
name, n, dur, seed0 = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4])
for flag in (False, True):
    scen = load_scenario(name, {"sim": "batched", "duration": dur, "traffic.ego_as_follower": flag})
    res = run_lockstep(scen, list(range(seed0, seed0 + n)), driver=make_driver("verified:mpc", scen))
    m = [r.metrics for r in res]
    print(f"{name} ego_as_follower={flag}: speed {st.mean(x['mean_speed'] for x in m):.2f} meta {st.mean(x['meta_cost_mean'] for x in m):.2f} "
          f"collisions {sum(x['collisions'] for x in m)} verified {st.mean(x['verified_share'] for x in m):.3f} failsafe {sum(x['failsafe_steps'] for x in m)}")
