"""A scripted brake-check red car against a driver (the red team's environment). Usage: python brake_check.py mpc 128 30 (driver, episodes from 71168, brake when the ego is this close behind [m])"""
import sys, dataclasses, numpy as np, torch, time
from mmpc.drivers import make_driver
from mmpc.rl.red_team import score_red_team
from mmpc.scenario import load_scenario
torch.set_num_threads(1)
spec, n, gap = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
class BrakeCheck:
    def predict(self, obs, deterministic=True):
        dx, dy = obs[:, 3] * 50, obs[:, 4] * 8
        return np.where((dx > 0) & (dx < gap) & (np.abs(dy) < 2.0), 1, 0), None
scen = dataclasses.replace(load_scenario("high_speed", {"sim": "batched"}), duration=10.0)
t = time.perf_counter()
print(spec, gap, score_red_team(BrakeCheck(), make_driver(spec, scen), scen, list(range(71168, 71168 + n)), 64), round(time.perf_counter() - t))
