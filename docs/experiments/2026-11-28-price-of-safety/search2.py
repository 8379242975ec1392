"""Random scenes: commands the check verifies, then the world steps them and the check's fail-safe. Usage: python search2.py HZ SCENES [SEED]"""
# The check before this pass: git show 6498250:mmpc/verify/verifier.py > old_verifier.py (beside this script)
import math, torch, mmpc, importlib.util, sys
from mmpc.sim import SimConfig, HighwaySimulator, vehicle_state
from mmpc.verify.failsafe import ego_body, failsafe_command, Body
import mmpc.verify.verifier as new_mod
spec = importlib.util.spec_from_file_location("old_verifier", "old_verifier.py"); old_mod = importlib.util.module_from_spec(spec); spec.loader.exec_module(old_mod)
freq = float(sys.argv[1]); n = int(sys.argv[2])
sim = SimConfig(simulation_frequency=freq, policy_frequency=freq)
road = mmpc.Road(num_lanes=4)
g = torch.Generator().manual_seed(int(sys.argv[3]) if len(sys.argv) > 3 else 0)
M = 3
ex = torch.zeros(n); ey = 4.0 + (torch.rand(n, generator=g) - 0.5) * 5; eh = (torch.rand(n, generator=g) - 0.5) * 0.8; ev = 5 + torch.rand(n, generator=g) * 20
cx = torch.rand(n, M, generator=g) * 40 - 4.0; cy = torch.randint(0, 3, (n, M), generator=g).float() * 4; cv = torch.rand(n, M, generator=g) * 20
acc = torch.rand(n, 1, generator=g) * 10 - 5; st = (torch.rand(n, 1, generator=g) - 0.5) * 1.5
sx, sy = torch.cat([ex[:, None], cx], 1), torch.cat([ey[:, None], cy], 1)
# keep scenes whose cars do not overlap each other or the ego now
state0 = vehicle_state(sx, sy, heading=torch.cat([eh[:, None], torch.zeros(n, M)], 1), speed=torch.cat([ev[:, None], cv], 1), config=sim, lane_change_enabled=False)
from mmpc.sim.collision import pair_collisions
pairs = pair_collisions(state0, sim.dt)
ok = ~(pairs.intersecting | pairs.will_intersect).flatten(1).any(1)
ego = torch.stack([ex, ey, eh, ev, torch.zeros(n), torch.zeros(n)], 1)
veh = torch.stack([cx, cy, cv, torch.zeros(n, M)], 2)
mask = torch.ones(n, M, dtype=torch.bool)
res = {}
for name, mod in (("old", old_mod), ("new", new_mod)):
    v = mod.Verifier(road, sim)
    verdict = v.check(ego, veh, mask, acc, st)
    good = verdict.verified[:, 0] & ok
    state = v and vehicle_state(sx, sy, heading=torch.cat([eh[:, None], torch.zeros(n, M)], 1), speed=torch.cat([ev[:, None], cv], 1), config=sim, lane_change_enabled=False)
    state = HighwaySimulator(sim).step(state, torch.cat([acc, st], 1))
    crashed = state.crashed[:, 0] | state.impact_pending[:, 0]
    lane, dec = verdict.lane[:, 0].clamp_min(0), torch.nan_to_num(verdict.deceleration[:, 0], nan=5.0)
    for t in range(int(12 * freq)):
        b = Body(state.x[:, 0], state.y[:, 0], state.heading[:, 0], state.speed[:, 0])
        a_, s_ = failsafe_command(b, lane, dec, 5.0, road, sim)
        state = HighwaySimulator(sim).step(state, torch.stack([a_, s_], 1))
        crashed |= state.crashed[:, 0]
    bad = good & crashed
    print(f"{freq} Hz {name}: verified {int(good.sum())} of {int(ok.sum())}, then crashed {int(bad.sum())}", bad.nonzero()[:5, 0].tolist())
    # classify the crashes of this verifier: collider behind the ego (its fault by the rule) or not
    from mmpc.collisions import is_ego_fault
    idxs = bad.nonzero()[:, 0]
    if name == "old":
        for i in idxs[:8].tolist():
            print("  scene", [round(float(q), 2) for q in ego[i]], "cars", [[round(float(q), 1) for q in c] for c in veh[i]], "cmd", round(float(acc[i, 0]), 2), round(float(st[i, 0]), 2))
