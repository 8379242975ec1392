import os, sys, time, functools, collections
os.environ.setdefault("MMPC_COMPILE", "1")
import torch, gymnasium as gym
torch.set_num_threads(1)
import mmpc.rl
from mmpc.scenario import load_scenario
acc = collections.defaultdict(float); cnt = collections.Counter()
def wrap(obj, name, label):
    f = getattr(obj, name)
    @functools.wraps(f)
    def g(*a, **k):
        t = time.perf_counter()
        try: return f(*a, **k)
        finally: acc[label] += time.perf_counter() - t; cnt[label] += 1
    setattr(obj, name, g)
from mmpc.verify import verifier, occupancy as occ, failsafe
from mmpc import mpc as mpcmod
import mmpc.verify.verifier as V
wrap(V.Verifier, "check", "check"); wrap(failsafe.FailSafeRollout, "__call__", "check.rollout"); wrap(V.Verifier, "_meets", "check.meets")
V.occupancy = (lambda f: (lambda *a, **k: (lambda t: (lambda r: (acc.__setitem__("check.occupancy", acc["check.occupancy"] + time.perf_counter() - t), r)[1])(f(*a, **k)))(time.perf_counter())))(V.occupancy)
wrap(mpcmod.MPC, "score", "score"); wrap(mpcmod.MPC, "build_problem", "build_problem")
import mmpc.solver.optimizer as O
wrap(O.BatchOptimizer, "forward", "solve")
from mmpc.highway import batched_world, highway_env_world
wrap(batched_world.BatchedWorld, "apply", "world.apply"); wrap(highway_env_world.HighwayEnvWorld, "apply", "world.apply")
import mmpc.rl.safety as S, mmpc.rl.engine as EN
wrap(S.SafetyLayer, "frame", "layer.frame"); wrap(EN.SafeEnvs, "_observations", "observations"); wrap(EN.SafeEnvs, "advance", "advance")
world = sys.argv[1]; verify = sys.argv[3] == "on"
scenario = load_scenario("rl_highway_fast", {"sim": "batched"} if world == "batched" else None)
env = gym.make("mmpc/SafeHighway-v0", scenario=scenario, config={"verify": verify})
env.reset(seed=63100); seed = 63101
for i in range(int(sys.argv[2])):
    o, r, te, tr, info = env.step(env.action_space.sample())
    if te or tr: env.reset(seed=seed); seed += 1
acc.clear(); cnt.clear()
n = 0; t0 = time.perf_counter()
while n < 60:
    o, r, te, tr, info = env.step(env.action_space.sample()); n += 1
    if te or tr: env.reset(seed=seed); seed += 1
dt = time.perf_counter() - t0
print(f"{world} verify={verify}: {n/dt:.2f} agent steps/s; ms per agent step:")
for k in sorted(acc): print(f"  {k:<18} {acc[k]/n*1e3:7.2f}  calls/step {cnt[k]/n:.1f}")
