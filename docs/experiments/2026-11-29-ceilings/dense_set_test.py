"""The check at small E: eager vs compiled (dense set test), and sparse vs dense compiled side by side."""
import time, torch
from mmpc.scenario import load_scenario
from mmpc.sim import SimEpisodes
from mmpc.verify import Verifier
from mmpc.verify import verifier as vmod
torch.set_num_threads(1)
sc = load_scenario("high_speed", {"duration": 10})
ep = SimEpisodes(sc, list(range(71300, 71316)))
for _ in range(30): ep.step(torch.zeros(16, 2))
ego, veh, mask = ep.road_state()
eager, comp = Verifier.for_scenario(sc, compile=False), Verifier.for_scenario(sc, compile=True)
gen = torch.Generator().manual_seed(0)
for E, K in [(1, 1), (1, 8), (4, 5), (16, 1)]:
    acc = (torch.rand(E, K, generator=gen) * 8 - 5); st = (torch.rand(E, K, generator=gen) - 0.5) * 0.1
    a = eager.check(ego[:E], veh[:E], mask[:E], acc, st); b = comp.check(ego[:E], veh[:E], mask[:E], acc, st)
    assert torch.equal(a.verified, b.verified) and torch.equal(a.lane, b.lane), (E, K)
    for name, v in (("eager", eager), ("compiled", comp)):
        t = time.perf_counter()
        for _ in range(20): v.check(ego[:E], veh[:E], mask[:E], acc, st)
        print(E, K, name, f"{(time.perf_counter() - t) / 20 * 1e3:.2f} ms", a.verified.float().mean().item())
print("--- sparse compiled (DENSE_TESTS=0) vs dense, same run")
for rep in range(2):
    for limit in (0, 1 << 18):
        vmod.DENSE_TESTS = limit
        for E, K in [(1, 1), (1, 8), (16, 1)]:
            acc = torch.zeros(E, K) - 1; st = torch.zeros(E, K)
            comp.check(ego[:E], veh[:E], mask[:E], acc, st)
            t = time.perf_counter()
            for _ in range(40): comp.check(ego[:E], veh[:E], mask[:E], acc, st)
            print(rep, "dense" if limit else "sparse", E, K, f"{(time.perf_counter() - t) / 40 * 1e3:.2f} ms")
