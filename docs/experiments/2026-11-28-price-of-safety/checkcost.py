"""Time of the check per decision at E environments: share of verified:mpc's decide."""
import sys, time, torch, statistics as st
from mmpc.scenario import load_scenario
from mmpc.highway.runner import run_lockstep
from mmpc.drivers import make_driver
from mmpc.verify import verifier as V
torch.set_num_threads(1)
E, dur = int(sys.argv[1]), float(sys.argv[2])
scen = load_scenario(sys.argv[3] if len(sys.argv) > 3 else "high_speed", {"sim": "batched", "duration": dur})
spent = {"check": 0.0, "calls": 0, "frames": []}
orig = V.Verifier.check
def timed(self, ego, vehicles, mask, a, s):
    t = time.perf_counter(); r = orig(self, ego, vehicles, mask, a, s); spent["check"] += time.perf_counter() - t; spent["calls"] += 1
    spent["frames"].append(self.frames(ego, vehicles, mask)); return r
V.Verifier.check = timed
d = make_driver("verified:mpc", scen)
t = time.perf_counter(); res = run_lockstep(scen, list(range(71168, 71168 + E)), driver=d); wall = time.perf_counter() - t
steps = sum(len(r.records) for r in res) / E
decide = sum(sum(rec.solve_ms for rec in r.records) for r in res) / E / 1e3  # per-episode decision time incl check
print(f"E={E}: wall {wall:.1f} s, steps {steps:.0f}, decision time {decide:.2f} s/episode-run, check {spent['check']:.2f} s "
      f"({spent['check'] / decide * 100:.0f} % of decisions), calls {spent['calls']}, frames mean {st.mean(spent['frames']):.0f}")
