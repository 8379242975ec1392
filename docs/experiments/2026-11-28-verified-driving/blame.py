"""Blame: which single car makes the MPC's own command fail the check. Usage: python blame.py 71168 8 (first seed, episodes; high speed, 20 s)"""
import sys, collections, torch, statistics as st
from mmpc.scenario import load_scenario
from mmpc.highway.runner import run_lockstep
from mmpc.drivers import make_driver
from mmpc.verify import guard as G
torch.set_num_threads(1)
scen = load_scenario("high_speed", {"sim": "batched", "duration": 20.0})
seeds = list(range(int(sys.argv[1]), int(sys.argv[1]) + int(sys.argv[2])))
W = scen.road.lane_width
blame = collections.Counter(); examples = collections.defaultdict(list); multi = collections.Counter()
orig_choose = G.Guard.choose
def choose(self, ego, vehicles, mask, ids, acc, steer, alternatives=None):
    V = self.verifier
    if mask is None: mask = torch.ones(vehicles.shape[:2], dtype=torch.bool)
    first = V.check(ego, vehicles, mask, acc[:, None].to(ego.dtype), steer[:, None].to(ego.dtype)).verified[:, 0]
    for e in (~first).nonzero().squeeze(1).tolist():
        cars = mask[e].nonzero().squeeze(1).tolist()
        E = len(cars)
        m = torch.zeros(E, vehicles.shape[1], dtype=torch.bool)
        for i, j in enumerate(cars): m[i, j] = True
        r = V.check(ego[e:e+1].expand(E, -1), vehicles[e:e+1].expand(E, -1, -1), m, acc[e].to(ego.dtype).expand(E, 1), steer[e].to(ego.dtype).expand(E, 1)).verified[:, 0]
        blockers = [cars[i] for i in (~r).nonzero().squeeze(1).tolist()]
        multi[min(len(blockers), 3)] += 1
        le = round(float(ego[e, 1]) / W)
        for j in blockers:
            dx = float(vehicles[e, j, 0] - ego[e, 0]); lj = round(float(vehicles[e, j, 1]) / W)
            rel = 'same' if lj == le else ('nbr' if abs(lj - le) == 1 else 'far')
            pos = 'ahead' if dx > 5 else ('behind' if dx < -5 else 'beside')
            k = f'{rel}-{pos}'
            blame[k] += 1
            examples[k].append((float(ego[e, 3]), dx, float(vehicles[e, j, 2]), float(ego[e, 1]) - le * W, float(steer[e])))
    return orig_choose(self, ego, vehicles, mask, ids, acc, steer, alternatives)
G.Guard.choose = choose
res = run_lockstep(scen, seeds, driver=make_driver("verified:mpc", scen))
print('speed', st.mean(r.metrics['mean_speed'] for r in res))
print('blockers per failed step', dict(multi))
for k, c in blame.most_common():
    ex = examples[k]
    print(f'{k:12s} {c:5d}  ego v {st.mean(e[0] for e in ex):5.1f}  dx {st.mean(e[1] for e in ex):6.1f}  car v {st.mean(e[2] for e in ex):5.1f}  |ego off lane| {st.mean(abs(e[3]) for e in ex):4.2f}')
    if k == 'same-ahead':
        import numpy as np
        a = np.array(ex)
        need = a[:, 0]**2/10 - a[:, 2]**2/12
        print('   dx - (ve^2/10 - vl^2/12): quantiles', np.quantile(a[:, 1] - need, [0.1, 0.5, 0.9]).round(1))
