"""Why verified:mpc pays in cruise: how often the check changes the MPC's command, and to what.
Usage: overrides.py SCENARIO SEED0 N DURATION (batched world)."""
import sys, collections, statistics as st, torch
from mmpc.scenario import load_scenario
from mmpc.highway.runner import run_lockstep
from mmpc.drivers import make_driver
from mmpc.drivers import verified as V
torch.set_num_threads(1)
name, seed0, n, dur = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
kinds = collections.Counter(); braking = []
original = V.guarded_command
def counted(guard, observation, acceleration, steering, *args, **kwargs):
    out = original(guard, observation, acceleration, steering, *args, **kwargs)
    for i in range(acceleration.shape[0]):
        if not bool(out.changed[i]):
            kinds["asked"] += 1
        elif bool(out.failsafe[i]):
            kinds["stored fail-safe"] += 1
        elif float(out.steering[i]) == float(steering[i]):
            kinds["asked steering, braking"] += 1; braking.append(float(acceleration[i] - out.acceleration[i]))
        else:
            kinds["another candidate or a fail-safe's first command"] += 1
    return out
V.guarded_command = counted
for spec in ("verified:mpc", "verified:frenet"):
    kinds.clear(); braking.clear()
    scenario = load_scenario(name, {"sim": "batched", "duration": dur})
    results = run_lockstep(scenario, list(range(seed0, seed0 + n)), driver=make_driver(spec, scenario))
    total = sum(kinds.values())
    meta = st.mean(r.metrics["meta_cost_mean"] for r in results); speed = st.mean(r.metrics["mean_speed"] for r in results)
    print(f"{name} {spec}: meta {meta:.3f} speed {speed:.2f}; " + ", ".join(f"{k} {v / total:.1%}" for k, v in kinds.items())
          + (f"; braking added, mean {st.mean(braking):.2f} m/s^2" if braking else ""), flush=True)
