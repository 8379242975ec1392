import time, torch, mmpc
from mmpc.scenario import load_scenario
from mmpc.verify import Verifier
from mmpc.verify.failsafe import Body, drive, failsafe_command
torch.set_num_threads(1)
scen = load_scenario("high_speed")
v = Verifier.for_scenario(scen)
def frame(x, y, h, s, lane, dec):
    body = Body(x, y, h, s)
    a, st = failsafe_command(body, lane, dec, v.length, v.road, v.sim)
    return tuple(drive(body, a, st, v.length, v.sim))
cf = torch.compile(frame, dynamic=True)
def run(f, K):
    x = torch.zeros(1, K, 3); y = torch.full((1, K, 3), 8.3); h = torch.zeros(1, K, 3); s = torch.full((1, K, 3), 22.0)
    lane = torch.tensor([2, 1, 3]).expand(1, K, 3); dec = torch.full((1, K, 3), 5.0)
    for _ in range(47):
        x, y, h, s = f(x, y, h, s, lane, dec)
    return x
t = time.perf_counter(); run(cf, 1); run(cf, 15); print("compile", time.perf_counter() - t)
for f, name in ((frame, "eager"), (cf, "compiled")):
    for K in (1, 15):
        t = time.perf_counter()
        for _ in range(20): run(f, K)
        print(name, K, (time.perf_counter() - t) / 20 * 1e3, "ms per 47 frames")
print((run(frame, 15) - run(cf, 15)).abs().max())
