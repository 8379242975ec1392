# Usage: python calibrate_sets.py SCENARIO EPISODES SECONDS FIRST_SEED [DRIVER]  (batched world, tuning seeds)
"""Calibrate: how far do the batched sim's cars go outside their sets (traffic rules only)?"""
import torch, sys, collections
from mmpc.scenario import load_scenario
from mmpc.highway.runner import run_lockstep, Observer
from mmpc.drivers import make_driver
from mmpc.verify import TrafficAssumptions, occupancy
from mmpc.verify.monitor import footprints
from mmpc.verify.occupancy import held_variant
torch.set_num_threads(1)
a = TrafficAssumptions()
name = sys.argv[1]; n = int(sys.argv[2]); dur = float(sys.argv[3]); first = int(sys.argv[4])
scen = load_scenario(name, {"sim": "batched", "duration": dur})
road = scen.road
H = 30
times = torch.arange(H + 1) * scen.period
hist = collections.defaultdict(list)  # env -> list of (step, sets, mask, crashed?)
examples = []
need = collections.defaultdict(float); count = collections.Counter(); total = collections.Counter()
class Cal(Observer):
    step = 0
    def decided(self, obs, dec, active):
        ids = obs.ids().tolist()
        sets = occupancy(obs.ego, obs.vehicles, obs.vehicle_mask, road, times, a, fault_rule=False)
        fp = footprints(obs.vehicles, a)
        for row, env in enumerate(ids):
            for (k, old, oldmask, oldx, oldego, oldveh) in hist[env]:
                h = self.step - k
                if h < 1 or h > H: continue
                i = h - 1
                held = held_variant(old.ego_lanes, obs.ego[row:row+1, 1, None], road, a.lane_margin)
                m = oldmask & obs.vehicle_mask[row]
                jump = (obs.vehicles[row, :, 0] - oldx).abs() > 45.0 * h * scen.period + 5.0
                near = (oldx - oldego).abs() < 100.0
                m = m & ~jump & near
                # excess per side (>0 = outside)
                ex = {
                  'x_low': (old.x_low[0, :, i] - fp.x_low[row]),
                  'x_high': (fp.x_high[row] - old.x_high[0, :, i]),
                  'y_low': (old.y_low[0, held[0], :, i] - fp.y_low[row]),
                  'y_high': (fp.y_high[row] - old.y_high[0, held[0], :, i]),
                }
                for side, e in ex.items():
                    e = e[m]
                    total[(side, h)] += e.numel()
                    bad = e > 1e-4
                    count[(side, h)] += int(bad.sum())
                    if bad.any():
                        need[side] = max(need[side], float(e.max()))
                        if side.startswith("y") and h >= 10 and len(examples) < 25:
                            j = int(e.argmax()); idx = m.nonzero().squeeze(1)[j]
                            examples.append((side, h, round(float(e.max()),2), [round(float(t),2) for t in obs.ego[row,:4]], round(oldego,1), [round(float(t),2) for t in oldveh[idx]], [round(float(t),2) for t in obs.vehicles[row, idx]]))
            hist[env] = [x for x in hist[env] if self.step - x[0] < H] + [(self.step, type(sets)(*(f[row:row+1] for f in sets)), obs.vehicle_mask[row], obs.vehicles[row, :, 0].clone(), float(obs.ego[row, 0]), obs.vehicles[row].clone())]
        self.step += 1
driver = make_driver(sys.argv[5] if len(sys.argv) > 5 else "mpc", scen)
run_lockstep(scen, list(range(first, first + n)), driver=driver, observers=[Cal()])
for side in ('x_low', 'x_high', 'y_low', 'y_high'):
    print(side, 'max excess %.3f' % need[side], [(h, count[(side, h)]) for h in (1, 2, 5, 10, 20, 30)], 'of', total[(side, 1)])

for e in examples: print(e)
