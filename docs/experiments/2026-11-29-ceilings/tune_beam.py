"""Beam-width tuning of the ceiling search. Usage: tune_beam.py SCENARIO VERIFY(0|1) BEAM DURATION SEEDS"""
import sys, time
from mmpc.scenario import load_scenario
from mmpc.evaluate.ceiling import search_ceiling, CeilingConfig
name, verify, beam, dur, seeds = sys.argv[1], sys.argv[2] == "1", int(sys.argv[3]), float(sys.argv[4]), [int(s) for s in sys.argv[5].split(",")]
sc = load_scenario(name, {"duration": dur})
t = time.perf_counter()
last = [0]
def prog(k, n, s):
    if k % 10 == 0 or k == n: print(f"step {k}/{n} {s:.1f}s", flush=True)
res = search_ceiling(sc, seeds, CeilingConfig(beam=beam, verify=verify), progress=prog)
for r in res: print(r)
print("total", time.perf_counter() - t)
