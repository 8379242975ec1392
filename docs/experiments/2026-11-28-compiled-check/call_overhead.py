import time, torch
torch.set_num_threads(1)
from mmpc.verify import failsafe
from mmpc.verify.failsafe import Body, FailSafeRollout, _compiled_chunk
from mmpc.sim.config import SimConfig
import mmpc
sim = SimConfig(simulation_frequency=10.0, policy_frequency=10.0); road = mmpc.Road(num_lanes=3)
r = FailSafeRollout(5.0, road, sim, compile=True)
N = 3
body = Body(*(torch.rand(N, dtype=torch.float64) + c for c in (0.0, 4.0, 0.0, 20.0)))
lane = torch.ones(N, dtype=torch.long); dec = torch.full((N,), 5.0, dtype=torch.float64)
r(body, lane, dec, 52)
f = _compiled_chunk(5.0, road, sim)
def tm(g, n=200):
    g(); t = time.perf_counter()
    for _ in range(n): g()
    return (time.perf_counter() - t) / n * 1e6
print("chunk call us", tm(lambda: f(*body, lane, dec)))
print("rollout 52 us", tm(lambda: r(body, lane, dec, 52)))
import torch._dynamo
with torch.compiler.set_stance(skip_guard_eval_unsafe=True):
    print("skip guards chunk call us", tm(lambda: f(*body, lane, dec)))
import torch._inductor.config as ic
from torch._dynamo.utils import counters
print(counters["inductor"])
