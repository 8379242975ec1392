"""Why does the verified expert drive slower? Per-step tally of the guard's choices. Usage: python guard_choices.py high_speed 16 20 71168 (scenario, episodes, seconds, first seed)"""
import sys, time, collections, torch, statistics as st
from mmpc.scenario import load_scenario
from mmpc.highway.runner import run_lockstep
from mmpc.drivers import make_driver
from mmpc.verify import guard as G
torch.set_num_threads(1)
scen_name, n, dur, seed0 = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4])
scen = load_scenario(scen_name, {"sim": "batched", "duration": dur})
seeds = list(range(seed0, seed0 + n))
tally = collections.Counter(); speeds = collections.defaultdict(list)
orig_choose = G.Guard.choose
def choose(self, ego, vehicles, mask, ids, acc, steer, alternatives=None):
    calls = []
    orig_check = self.verifier.check
    def rec(*a, **k):
        r = orig_check(*a, **k); calls.append(r); return r
    self.verifier.check = rec
    try:
        out = orig_choose(self, ego, vehicles, mask, ids, acc, steer, alternatives)
    finally:
        del self.verifier.check
    first = calls[0].verified[:, 0]
    rows = (~first).nonzero().squeeze(1)
    nalt = 8 if alternatives is not None else 0
    for e in range(ego.shape[0]):
        v = float(ego[e, 3]); b = min(int(v // 4) * 4, 24)
        if first[e]: cat = 'asked'
        elif out.failsafe[e]: cat = 'stored failsafe'
        else:
            r = (rows == e).nonzero()[0, 0]
            p = int(calls[1].verified[r].int().argmax())
            cat = f'brake {G.BRAKING[p]:.0f}' if p < 4 else ('alternative' if p < 4 + nalt else 'failsafe first')
        tally[cat] += 1; speeds[cat].append(v)
        # gap to nearest car ahead in ego lane (|dy|<2)
        m = mask[e] if mask is not None else torch.ones(vehicles.shape[1], dtype=torch.bool)
        dx = vehicles[e, :, 0] - ego[e, 0]; dy = (vehicles[e, :, 1] - ego[e, 1]).abs()
        ahead = m & (dx > 0) & (dy < 2.0)
        if not first[e] and ahead.any():
            j = torch.where(ahead, dx, torch.full_like(dx, 1e9)).argmin()
            tally_gap.append((v, float(dx[j]), float(vehicles[e, j, 2]), cat, float(acc[e])))
    return out
tally_gap = []
G.Guard.choose = choose
for spec in ("verified:mpc", "mpc"):
    d = make_driver(spec, scen)
    t = time.perf_counter(); res = run_lockstep(scen, seeds, driver=d); wall = time.perf_counter() - t
    ms = [r.metrics for r in res]
    print(spec, 'wall', round(wall, 1), 'speed', round(st.mean(m['mean_speed'] for m in ms), 2),
          'meta', round(st.mean(m['meta_cost'] for m in ms), 2) if 'meta_cost' in ms[0] else '', 'coll', sum(m['collisions'] for m in ms),
          {k: ms[0][k] for k in ms[0] if 'lane' in k})
total = sum(tally.values())
for k, c in tally.most_common(): print(f'{k:16s} {c:6d} {100*c/total:5.1f}%  mean v {st.mean(speeds[k]):.1f}')
import collections as C
h = C.Counter()
for v, gap, vl, cat, a in tally_gap:
    h[(cat, 'gap<20' if gap < 20 else 'gap<40' if gap < 40 else 'gap<60' if gap < 60 else 'gap>=60')] += 1
for k, c in sorted(h.items()): print(k, c)
print('not-verified with no car ahead in lane:', sum(1 for _ in range(0)) , total - tally['asked'] - len(tally_gap))
