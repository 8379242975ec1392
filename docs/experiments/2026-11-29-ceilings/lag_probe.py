"""Decision-to-visible lag of MOBIL lane changes (|vy| > 0.5 m/s or 0.5 m off the lane centre), ego coasting, ego-as-follower traffic."""
import torch
from mmpc.scenario import load_scenario
from mmpc.sim import SimEpisodes
torch.set_num_threads(1)
worst = {}
for name in ("high_speed_threats", "cruise_threats", "high_speed"):
    sc = load_scenario(name, {"duration": 20.0, "traffic.ego_as_follower": True})
    ep = SimEpisodes(sc, list(range(1000, 1032)), dtype=torch.float64)
    E, V = ep.state.x.shape
    decided = torch.full((E, V), -1.0, dtype=torch.float64)
    lags = []
    for k in range(int(20 * sc.frequency)):
        before = ep.state.target_lane.clone()
        ep.step(torch.zeros(E, 2, dtype=torch.float64))
        st = ep.state
        t = (k + 1) / sc.frequency
        new = (st.target_lane != before) & st.alive
        decided = torch.where(new, torch.tensor(t - 1.0 / sc.frequency, dtype=torch.float64), decided)
        vy = st.speed * torch.sin(st.heading)
        offset = st.y - st.lane.double() * 4.0
        visible = (vy.abs() > 0.5) | (offset.abs() >= 0.5)
        shown = visible & (decided >= 0)
        for e, v in shown.nonzero().tolist():
            if v == 0: continue
            lags.append((t - float(decided[e, v]), float(st.speed[e, v])))
        decided = torch.where(shown, -1.0, decided)
    lags.sort()
    print(name, len(lags), "max lag", lags[-1] if lags else None, "lags > 0.2:", [l for l in lags if l[0] > 0.2][:10])
