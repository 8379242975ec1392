"""Where an evaluation step goes: mmpc's episode runner (run_lockstep) on the batched world with the
MPC driver at E environments, one torch thread.

    MMPC_COMPILE=1 python eval_step_split.py E SCENARIO WARM_ITERATIONS exit|noexit DURATION

One run of E seeds compiles the call layouts, a second run of other seeds is timed; the time of
the world's observe and apply, the MPC's build_problem, score (the solve) and choose, and the
runner's step records, compile time taken out. Prints one JSON line.
"""
import sys, time, json, collections, dataclasses
import torch
torch.set_num_threads(1)
from mmpc.scenario import load_scenario
from mmpc.highway import runner
from mmpc.highway.worlds import BatchedWorld
from mmpc.drivers.mpc_driver import MPCDriver
from mmpc.mpc import MPC
E = int(sys.argv[1]); name = sys.argv[2]; warm = int(sys.argv[3]); exits = sys.argv[4] == "exit"; duration = float(sys.argv[5])
s = load_scenario(name, {"sim": "batched", "mpc.warm_iterations": warm, "optimizer.exit_checks": [10, 30, 60] if exits else []})
timers = collections.defaultdict(float)
def wrap(owner, attr, key):
    f = getattr(owner, attr)
    def g(*a, **k):
        t = time.perf_counter(); r = f(*a, **k); timers[key] += time.perf_counter() - t; return r
    setattr(owner, attr, g)
for owner, attr, key in [(BatchedWorld, "observe", "observe"), (BatchedWorld, "apply", "apply"), (MPCDriver, "decide", "decide"),
                         (runner, "_step_records", "records"), (MPC, "build_problem", "build_problem"), (MPC, "choose", "choose")]:
    wrap(owner, attr, key)
score = MPC.score
def timed_score(self, problem, *a):
    t = time.perf_counter(); r = score(self, problem, *a)
    timers["score"] += time.perf_counter() - t; timers["compile"] += r.compile_ms / 1e3; return r
MPC.score = timed_score
driver = runner.make_driver("mpc", s)
runner.run_lockstep(s.replace(duration=duration), list(range(100000, 100000 + E)), driver=driver)  # compiles the layouts
timers.clear()
t = time.perf_counter()
results = runner.run_lockstep(s.replace(duration=duration), list(range(200000, 200000 + E)), driver=driver)
wall = time.perf_counter() - t - timers["compile"]
steps = sum(len(r.records) for r in results)
out = {"E": E, "scenario": name, "warm": warm, "exit": exits, "env_steps": steps, "wall_s": wall,
       "ms_per_env_step": 1e3 * wall / steps, **{k: round(v - (timers["compile"] if k in ("score", "decide") else 0), 3) for k, v in timers.items()}}
out["solve_share"] = (timers["score"] - timers["compile"]) / wall
print(json.dumps(out))
