"""For cars the lane rule can hold (on their target lane, |vy| <= 0.5 m/s, within 0.5 m of the centre): how far beyond the lane centre does the footprint plus the world's one-frame sweep reach? (the band allows lane_overreach 1.6 m)"""
import sys, torch
from mmpc.scenario import load_scenario
from mmpc.sim import SimEpisodes
torch.set_num_threads(1)
for hz in (5.0, 10.0, 15.0):
    sc = load_scenario("high_speed_threats", {"sim": "batched", "duration": 20.0, "frequency": hz})
    ep = SimEpisodes(sc, seeds=list(range(64)))
    worst = 0.0
    for _ in range(int(20 * hz)):
        st = ep.state
        vy = st.speed[:, 1:] * st.heading[:, 1:].sin()
        off0 = (st.y[:, 1:] - st.lane[:, 1:].to(st.y.dtype) * 4.0).abs()
        keep = st.alive[:, 1:] & ~st.crashed[:, 1:] & (st.lane[:, 1:] == st.target_lane[:, 1:]) & (vy.abs() <= 0.5) & (off0 < 0.5)
        h, v = st.heading[:, 1:], st.speed[:, 1:]
        reach = 2.5 * h.sin().abs() + 1.0 * h.cos().abs()
        off = (st.y[:, 1:] - st.lane[:, 1:].to(st.y.dtype) * 4.0).abs()
        sweep = (v * h.sin()).abs() / hz
        excess = (off + reach + sweep) - torch.clamp(off + reach, min=1.6)  # beyond the band (overreach or the edge now)
        worst = max(worst, float(excess[keep].max()))
        ep.step(torch.zeros(64, 2))
    print(f"{hz} Hz: worst reach of footprint + one-frame sweep beyond the band (max of 1.6 m and the edge now): {worst:.3f} m")
