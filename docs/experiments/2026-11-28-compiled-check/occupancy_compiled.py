import time, torch
torch.set_num_threads(1)
import mmpc
from mmpc.verify.occupancy import occupancy
from mmpc.verify.assumptions import TrafficAssumptions
road = mmpc.Road(num_lanes=3); a = TrafficAssumptions()
def f(ego, vehicles, mask, times):
    return occupancy(ego, vehicles, mask, road, times, a, ego_braking=5.0)
cf = torch.compile(f, dynamic=True, fullgraph=True)
def inputs(E, M, T, dt=torch.float64):
    g = torch.Generator().manual_seed(0)
    ego = torch.cat([mmpc.ego_state(0.0, 4.0, 0.0, 20.0)] * E).to(dt)
    veh = torch.rand(E, M, 4, generator=g, dtype=dt) * torch.tensor([100, 8, 25, 0.5], dtype=dt) - torch.tensor([50, 0, 0, 0.25], dtype=dt)
    mask = torch.rand(E, M, generator=g) > 0.2
    times = torch.arange(T + 1, dtype=dt) * 0.1
    return ego, veh, mask, times
t = time.perf_counter(); out = cf(*inputs(1, 10, 40)); print("compile", time.perf_counter() - t, flush=True)
def tm(g, n=100):
    g(); t = time.perf_counter()
    for _ in range(n): g()
    return (time.perf_counter() - t) / n * 1e3
for E, M, T in ((1, 10, 40), (1, 12, 55), (16, 10, 40), (256, 10, 40)):
    x = inputs(E, M, T)
    ref, got = f(*x), cf(*x)
    same = all(torch.equal(r, g) if r.dtype in (torch.bool, torch.long) else torch.allclose(r, g, atol=1e-9) for r, g in zip(ref, got))
    print(E, M, T, "eager", round(tm(lambda: f(*x)), 3), "compiled", round(tm(lambda: cf(*x)), 3), "same", same, flush=True)
