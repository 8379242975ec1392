"""The verified search's node collision on high_speed seed 78435 rebuilt from three cars at step 184: every command verifies, the ego is struck."""
import torch
from mmpc.scenario import load_scenario
from mmpc.sim import HighwaySimulator, vehicle_state
from mmpc.sim.traffic import sim_config
from mmpc.verify import Verifier
sc = load_scenario("high_speed", {"sim": "batched"})
sim = sim_config(sc)
for dtype in (torch.float32, torch.float64):
    t = lambda v: torch.tensor([v], dtype=dtype)
    state = vehicle_state(t([427.922, 422.375, 425.627]), t([10.096, 12.0, 4.0]), heading=t([0.420, 0.0, 0.0]),
                          speed=t([9.095, 8.087, 10.337]), config=sim, target_speed=t([14.0, 9.47, 10.61]),
                          idm_delta=t([4.0, 3.54, 3.97]), lane_change_enabled=torch.tensor([[False, True, True]]),
                          lane_change_timer=torch.tensor([[19.01, 0.1, 0.0]], dtype=torch.float64))
    verifier = Verifier.for_scenario(sc, compile=False)
    simulator = HighwaySimulator(sim)
    applied = [-5.0, -0.0731]
    commands = [(-5.0, -0.1749), (-5.0, 0.7854), (-5.0, 0.6813), (-5.0, 0.3880), (-5.0, 0.2123)]
    import math
    for a, s in commands:
        x, y, h, v = (f[0] for f in (state.x, state.y, state.heading, state.speed))
        beta = math.atan(0.5 * math.tan(applied[1]))
        ego = torch.tensor([[float(x[0]), float(y[0]), float(h[0]) + beta, float(v[0]), applied[0], float(v[0]) * math.sin(beta) / 2.5]], dtype=dtype)
        cars = torch.stack([x[1:], y[1:], v[1:] * torch.cos(h[1:]), v[1:] * torch.sin(h[1:])], dim=1)[None]
        verdict = verifier.check(ego, cars, torch.ones(1, 2, dtype=torch.bool), t([a]), t([s]))
        state = simulator.step(state, t([a, s]))
        applied = [a, s]
        print(dtype, "verified", bool(verdict.verified[0, 0]), "crashed", state.crashed[0].tolist())
