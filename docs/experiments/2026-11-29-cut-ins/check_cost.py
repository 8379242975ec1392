"""The check's time per call under the two lane-change rules, E = 1, 16, 256 environments of high-speed traffic, K = 12 random commands, eager, one thread."""
import time, torch
from mmpc.scenario import load_scenario
from mmpc.sim import SimEpisodes
from mmpc.verify import Verifier, TrafficAssumptions
torch.set_num_threads(1)
sc = load_scenario("high_speed", {"sim": "batched", "duration": 10.0})
for E in (1, 16, 256):
    ep = SimEpisodes(sc, seeds=list(range(71400, 71400 + E)))
    for _ in range(30): ep.step(torch.zeros(E, 2))
    ego, veh, mask = ep.road_state()
    acc = torch.rand(E, 12) * 10 - 5; steer = (torch.rand(E, 12) - 0.5) * 0.2
    res = {}
    for rule in ("highway-env", "follower", "highway-env", "follower"):
        v = Verifier.for_scenario(sc, assumptions=TrafficAssumptions.for_scenario(sc, cut_in=rule), compile=False)
        v.check(ego, veh, mask, acc, steer)
        t = time.perf_counter(); n = 5
        for _ in range(n): d = v.check(ego, veh, mask, acc, steer)
        res[rule] = ((time.perf_counter() - t) / n * 1e3, float(d.verified.float().mean()))
    print(E, {k: (round(a, 1), round(b, 3)) for k, (a, b) in res.items()})
