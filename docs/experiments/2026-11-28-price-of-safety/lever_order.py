"""Lever: the planner's other verified candidates before braking on the asked steering. Usage: lever_order.py SCENARIO N DUR SEED0"""
import sys, time, statistics as st, torch
from mmpc.scenario import load_scenario
from mmpc.highway.runner import run_lockstep
from mmpc.drivers import make_driver
from mmpc.verify import guard as G
torch.set_num_threads(1)
name, n, dur, seed0 = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4])
scen = load_scenario(name, {"sim": "batched", "duration": dur})
seeds = list(range(seed0, seed0 + n))
orig = G.Guard._candidates
def alternatives_first(self, ego, acceleration, steering, rows, alternatives):
    a, s = orig(self, ego, acceleration, steering, rows, alternatives)
    if alternatives is None:
        return a, s
    k = len(G.BRAKING); m = a.shape[1] - k - self.verifier.failsafe_candidates(ego[rows[:1]])[0].shape[1]
    order = list(range(k, k + m)) + list(range(k)) + list(range(k + m, a.shape[1]))
    return a[:, order], s[:, order]
for label in ("shipped", "alternatives first"):
    G.Guard._candidates = orig if label == "shipped" else alternatives_first
    d = make_driver("verified:mpc", scen)
    t = time.perf_counter(); res = run_lockstep(scen, seeds, driver=d); wall = time.perf_counter() - t
    m = [r.metrics for r in res]
    print(f"{name} {label}: wall {wall:.0f} s speed {st.mean(x['mean_speed'] for x in m):.2f} meta {st.mean(x['meta_cost_mean'] for x in m):.3f} "
          f"coll {sum(x['collisions'] for x in m)} failsafe {sum(x['failsafe_steps'] for x in m)} |psi''| {st.mean(x['ang_acc_mean'] for x in m):.3f} lane changes {st.mean(x['lane_changes'] for x in m):.1f}")
