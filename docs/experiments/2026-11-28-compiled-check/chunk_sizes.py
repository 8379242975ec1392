import time, torch, sys
torch.set_num_threads(1)
from mmpc.verify import failsafe
failsafe.ROLLOUT_CHUNK = int(sys.argv[1])  # usage: chunk_sizes.py FRAMES (run with TORCHINDUCTOR_CACHE_DIR=a new folder for cold compiles)
from mmpc.verify.failsafe import Body, FailSafeRollout, _compiled_chunk, rollout
from mmpc.sim.config import SimConfig
import mmpc
sim = SimConfig(simulation_frequency=10.0, policy_frequency=10.0); road = mmpc.Road(num_lanes=3)
r = FailSafeRollout(5.0, road, sim, compile=True)
def tm(g, n=100):
    g(); t = time.perf_counter()
    for _ in range(n): g()
    return (time.perf_counter() - t) / n * 1e3
for N in (3, 60, 768):
    body = Body(*(torch.rand(N, dtype=torch.float64) + c for c in (0.0, 4.0, 0.0, 20.0)))
    lane = torch.ones(N, dtype=torch.long); dec = torch.full((N,), 5.0, dtype=torch.float64)
    t0 = time.perf_counter(); r(body, lane, dec, 52); first = time.perf_counter() - t0
    print(f"C={failsafe.ROLLOUT_CHUNK} N={N} first {first:.1f}s rollout52 {tm(lambda: r(body, lane, dec, 52)):.2f} ms eager {tm(lambda: rollout(body, lane, dec, 52, 5.0, road, sim), 10):.2f} ms", flush=True)
