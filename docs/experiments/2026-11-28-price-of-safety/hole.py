"""Probe: the verified expert's collision at low frequency. Usage: python hole.py SEED FREQ DUR"""
import sys, torch
from mmpc.scenario import load_scenario
from mmpc.highway.runner import run_lockstep, Observer
from mmpc.drivers import make_driver
torch.set_num_threads(1)
seed, freq, dur = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])
scen = load_scenario(sys.argv[4] if len(sys.argv) > 4 else "high_speed_threats", {"sim": "batched", "duration": dur, "frequency": freq})
d = make_driver("verified:mpc", scen)
log = []
class Rec(Observer):
    def decided(self, obs, dec, active):
        log.append((obs.ego.clone(), obs.vehicles.clone(), obs.vehicle_mask.clone(), dec))
res = run_lockstep(scen, [seed], driver=d, observers=[Rec()])[0]
m = res.metrics
print({k: m[k] for k in m if 'coll' in k or 'crash' in k or 'verified' in k or 'failsafe' in k})
for t, (ego, veh, mask, dec) in enumerate(log[-4:]):
    e = ego[0]
    print(f"step {len(log)-4+t}: ego x={e[0]:.1f} y={e[1]:.2f} psi={e[2]:.3f} v={e[3]:.2f} a={e[4]:.2f} psidot={e[5]:.3f} | cmd a={float(dec.acceleration[0]):.2f} st={float(dec.steering[0]):.3f} ver={bool(dec.verified[0])} fs={bool(dec.failsafe[0])}")
    for j in range(veh.shape[1]):
        if mask[0, j] and abs(veh[0, j, 0] - e[0]) < 40:
            print(f"   car {j}: x={veh[0,j,0]-e[0]:+.1f} y={veh[0,j,1]:.2f} vx={veh[0,j,2]:.2f} vy={veh[0,j,3]:.2f}")
