"""The MPC plans around cars ahead with the check's following distance (a prototype, not shipped). Usage: python following_distance.py 71168 8 12 verified:mpc [reaction s] [JSON overrides]; constant < 0: off"""
import sys, torch, statistics as st, time
from mmpc.scenario import load_scenario
from mmpc.highway.runner import run_lockstep
from mmpc.drivers import make_driver
from mmpc.mpc import MPC
from mmpc.verify import guard as G
torch.set_num_threads(1)
seed0, n, const, spec = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]), sys.argv[4]
react = float(sys.argv[5]) if len(sys.argv) > 5 else 0.0
import json
scen = load_scenario("high_speed", {"sim": "batched", "duration": 20.0, **json.loads(sys.argv[6] if len(sys.argv) > 6 else "{}")})
orig = MPC.build_problem
def build(self, ego, vehicles, vehicle_mask=None):
    p = orig(self, ego, vehicles, vehicle_mask)
    if const < 0: return p
    vm = vehicle_mask if vehicle_mask is not None else torch.ones(vehicles.shape[:2], dtype=torch.bool)
    vehicles = torch.where(vm[..., None], vehicles, torch.zeros_like(vehicles)).to(ego.dtype)
    states, mask = self.nearest_obstacles(ego.to(p.ego.dtype), vehicles.to(p.ego.dtype), vm)
    M = states.shape[1]
    ve = (ego[:, 3] * torch.cos(ego[:, 2]))[:, None]
    vl = states[..., 2].clamp_min(0)
    ahead = states[..., 0] > ego[:, None, 0]
    need = ve * react + ve**2 / 10 - vl**2 / 12 + const
    axes = p.obstacle_axes.clone()
    delta = torch.where(ahead, (need - axes[:, :M, 0]).clamp(0, 80), torch.zeros_like(need))
    obstacles = p.obstacles.clone()
    obstacles[:, :M, :, 0] -= delta[..., None] / 2
    axes[:, :M, 0] += delta / 2
    return p._replace(obstacles=obstacles, obstacle_axes=axes)
MPC.build_problem = build
t = time.perf_counter()
res = run_lockstep(scen, list(range(seed0, seed0 + n)), driver=make_driver(spec, scen))
ms = [r.metrics for r in res]
print(spec, const, react, 'wall', round(time.perf_counter() - t), 'speed', round(st.mean(m['mean_speed'] for m in ms), 2),
      'verified', round(st.mean((m.get('verified_share') or 1) for m in ms), 3), 'coll', sum(m['collisions'] for m in ms), 'failsafe', sum(m.get('failsafe_steps', 0) for m in ms), flush=True)
