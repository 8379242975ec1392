"""How often the unprotected expert's own command would fail the check. Usage: python expert_way_out.py high_speed 71168 16 20 (scenario, first seed, episodes, seconds)"""
import sys, torch, statistics as st, json
from mmpc.scenario import load_scenario
from mmpc.highway.runner import run_lockstep
from mmpc.drivers import make_driver
from mmpc.verify import Verifier
torch.set_num_threads(1)
name, seed0, n, dur = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
scen = load_scenario(name, {"sim": "batched", "duration": dur})
V = Verifier.for_scenario(scen)
stats = {"steps": 0, "unverified": 0, "v_all": [], "v_unver": []}
class Tap:
    def __init__(s, d): s.d = d
    def __getattr__(s, k): return getattr(s.d, k)
    def reset(s, n): s.d.reset(n)
    def decide(s, o):
        dec = s.d.decide(o)
        o = o.to("cpu"); m = o.vehicle_mask if o.vehicle_mask is not None else torch.ones(o.vehicles.shape[:2], dtype=torch.bool)
        ok = V.check(o.ego, o.vehicles, m, dec.acceleration.cpu()[:, None].to(o.ego.dtype), dec.steering.cpu()[:, None].to(o.ego.dtype)).verified[:, 0]
        stats["steps"] += ok.numel(); stats["unverified"] += int((~ok).sum())
        stats["v_all"] += o.ego[:, 3].tolist(); stats["v_unver"] += o.ego[~ok, 3].tolist()
        return dec
res = run_lockstep(scen, list(range(seed0, seed0 + n)), driver=Tap(make_driver("mpc", scen)))
print(name, 'speed', round(st.mean(r.metrics['mean_speed'] for r in res), 2), 'steps', stats['steps'],
      'own command fails the check', round(stats['unverified'] / stats['steps'], 3),
      'mean v there', round(st.mean(stats['v_unver']), 2), 'overall', round(st.mean(stats['v_all']), 2))
