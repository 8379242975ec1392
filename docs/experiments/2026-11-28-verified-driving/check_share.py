"""The check's share of a verified decision: cProfile of `verified:mpc` over 16 tuning episodes x 10 s of high speed
(batched, E = 16, one thread; a warm-up episode first). Usage: python check_share.py"""
import cProfile
import pstats

import torch

from mmpc.drivers import make_driver
from mmpc.highway.runner import run_lockstep
from mmpc.scenario import load_scenario

torch.set_num_threads(1)
scenario = load_scenario("high_speed", {"sim": "batched", "duration": 10.0})
driver = make_driver("verified:mpc", scenario)
run_lockstep(scenario, [71168], driver=driver)
profile = cProfile.Profile()
profile.enable()
run_lockstep(scenario, list(range(71168, 71184)), driver=driver)
profile.disable()
stats = pstats.Stats(profile).sort_stats("cumulative")
stats.print_stats(r"verified.py.*decide|guard.py.*choose|mpc_driver.py.*decide|verifier.py.*check|rollout|occupancy\)")
