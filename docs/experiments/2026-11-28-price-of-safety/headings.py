"""Max body heading and lateral speeds of uncrashed cars in the batched simulator per frequency."""
import sys, torch
from mmpc.scenario import load_scenario
from mmpc.sim import SimEpisodes
torch.set_num_threads(1)
for name in sys.argv[1].split(','):
    for f in [1, 2, 3, 4, 5, 10, 15]:
        sc = load_scenario(name, {"sim": "batched", "duration": 20.0, "frequency": float(f)})
        ep = SimEpisodes(sc, seeds=list(range(64)))
        hmax = vlat = vmot = 0.0
        for step in range(int(20 * f)):
            st = ep.state
            ok = st.alive[:, 1:] & ~st.crashed[:, 1:]
            h = st.heading[:, 1:].abs()
            hmax = max(hmax, float(h[ok].max()))
            vlat = max(vlat, float((st.speed[:, 1:] * torch.sin(st.heading[:, 1:])).abs()[ok].max()))
            ep.step(torch.zeros(64, 2))
        print(f"{name} {f:>3} Hz: max |heading| {hmax:.3f} rad, max |v sin h| {vlat:.2f} m/s")
