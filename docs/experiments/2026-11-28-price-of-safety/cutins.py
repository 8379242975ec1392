"""How often a car decides to enter the ego's lane directly ahead of it (within 60 m, no car of the ego's lane between), ego holding its speed."""
import sys, torch
from mmpc.scenario import load_scenario
from mmpc.sim import SimEpisodes
torch.set_num_threads(1)
import json
OVER = json.loads(sys.argv[2]) if len(sys.argv) > 2 else {}
for name in sys.argv[1].split(","):
    for flag in (False, True):
        sc = load_scenario(name, {"sim": "batched", "duration": 20.0, "traffic.ego_as_follower": flag, **OVER})
        ep = SimEpisodes(sc, seeds=list(range(1000, 1032)))
        count = 0
        for step in range(200):
            before = ep.state.target_lane.clone()
            ep.step(torch.zeros(32, 2))
            st = ep.state
            ego_lane = st.lane[:, :1]
            dx = st.x[:, 1:] - st.x[:, :1]
            new = (st.target_lane[:, 1:] != before[:, 1:]) & (st.target_lane[:, 1:] == ego_lane) & (st.lane[:, 1:] != ego_lane) & (dx > 0) & (dx < 60) & st.alive[:, 1:]
            in_lane = (st.lane[:, 1:] == ego_lane) & st.alive[:, 1:] & (dx > 0)
            between = (in_lane[:, None, :] & (dx[:, None, :] < dx[:, :, None])).any(dim=2)
            count += int((new & ~between).sum())
        print(f"{name} ego_as_follower={flag}: {count} decisions to enter the ego's lane 0-60 m ahead in 32 x 20 s")
