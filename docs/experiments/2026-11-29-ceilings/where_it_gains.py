"""Where the verified ceiling gains on verified:mpc: replay the ceiling's commands and drive the driver on
one seed, print lane and speed every 2 s. Usage: where_it_gains.py ROWS.jsonl SEED"""
import json, sys
import torch
from mmpc.drivers import make_driver
from mmpc.highway.runner import run_lockstep
from mmpc.scenario import load_scenario
from mmpc.sim import SimEpisodes

rows, seed = sys.argv[1], int(sys.argv[2])
row = next(r for r in map(json.loads, open(rows)) if r["seed"] == seed and r["kind"] == "verified")
scenario = load_scenario(row["scenario"], {"duration": row["duration"], "sim": "batched"})
episodes, ceiling = SimEpisodes(scenario, [seed]), []
for acceleration, steering in row["commands"]:
    ego = episodes.road_state()[0][0]
    ceiling.append((float(ego[1]) / 4.0, float(ego[3])))
    episodes.step(torch.tensor([[acceleration, steering]]))
(driven,) = run_lockstep(scenario, [seed], driver=make_driver("verified:mpc", scenario))
every = int(2 * scenario.frequency)
print("t [s] | ceiling lane, speed | verified:mpc lane, speed")
for k in range(0, len(ceiling), every):
    record = driven.records[k]
    print(f"{k / scenario.frequency:5.1f} | {ceiling[k][0]:4.2f} {ceiling[k][1]:5.2f} | {record.y / 4.0:4.2f} {record.v:5.2f}")
