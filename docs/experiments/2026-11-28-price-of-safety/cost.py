"""The new check's price: verified:mpc with the check before and after this change, same tuning seeds. Usage: python cost.py SCENARIO EPISODES SECONDS FIRST_SEED"""
# The check before this pass: git show 6498250:mmpc/verify/verifier.py > old_verifier.py (beside this script)
import sys, time, importlib.util, statistics as st, torch
from mmpc.scenario import load_scenario
from mmpc.highway.runner import run_lockstep
from mmpc.drivers import make_driver
from mmpc.drivers.verified import VerifiedDriver
import mmpc.verify.verifier as new_mod
spec = importlib.util.spec_from_file_location("old_verifier", "old_verifier.py"); old_mod = importlib.util.module_from_spec(spec); spec.loader.exec_module(old_mod)
torch.set_num_threads(1)
name, n, dur, seed0 = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4])
scen = load_scenario(name, {"sim": "batched", "duration": dur})
seeds = list(range(seed0, seed0 + n))
for label, mod in (("before", old_mod), ("after", new_mod)):
    d = VerifiedDriver(make_driver("mpc", scen), mod.Verifier.for_scenario(scen))
    t = time.perf_counter(); res = run_lockstep(scen, seeds, driver=d); wall = time.perf_counter() - t
    m = [r.metrics for r in res]
    print(f"{name} {label}: wall {wall:.0f} s speed {st.mean(x['mean_speed'] for x in m):.2f} meta {st.mean(x['meta_cost_mean'] for x in m):.3f} "
          f"collisions {sum(x['collisions'] for x in m)} verified {st.mean(x['verified_share'] for x in m):.3f} failsafe {sum(x['failsafe_steps'] for x in m)}"
          + (f" (v-15)^2 {st.mean(x['speed_residual_mean'] for x in m):.2f}" if 'speed_residual_mean' in m[0] else ''))
