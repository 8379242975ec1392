"""Replay the episode and compare the verifier's model of the ego to the world's; at the last step, show the verdict."""
import sys, torch
from mmpc.scenario import load_scenario
from mmpc.highway.runner import run_lockstep, Observer
from mmpc.highway.batched_world import BatchedWorld
from mmpc.drivers import make_driver
from mmpc.verify.failsafe import Body, drive
from mmpc.verify.occupancy import occupancy
torch.set_num_threads(1)
seed, freq, dur = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])
scen = load_scenario(sys.argv[4] if len(sys.argv) > 4 else "high_speed_threats", {"sim": "batched", "duration": dur, "frequency": freq})
d = make_driver("verified:mpc", scen)
log = []
class Rec(Observer):
    def decided(self, obs, dec, active):
        log.append((obs.ego.clone(), obs.vehicles.clone(), obs.vehicle_mask.clone(), dec.acceleration.clone(), dec.steering.clone()))
res = run_lockstep(scen, [seed], driver=d, observers=[Rec()])[0]
ver = d.verifier
w = BatchedWorld.start(scen, [seed])
for t, (ego, veh, mask, a, s) in enumerate(log):
    obs, _ = w.observe([0])
    assert torch.allclose(obs.ego, ego), (obs.ego, ego)
    pred = drive(ver.body(ego), a.double() if False else a, s, ver.length, ver.sim)
    w.apply([0], a, s)
    st = w.sim.state
    print(f"t={t}: world x={float(st.x[0,0]):.2f} y={float(st.y[0,0]):.3f} h={float(st.heading[0,0]):.3f} v={float(st.speed[0,0]):.2f} | model x={float(pred.x[0]):.2f} y={float(pred.y[0]):.3f} h={float(pred.heading[0]):.3f} v={float(pred.speed[0]):.2f} crashed={bool(w.sim.crashed[0])}")
ego, veh, mask, a, s = log[-1]
v = ver.check(ego, veh, mask, a[:, None], s[:, None])
print("verdict", v)
