"""Regression scenes: high-speed episodes of the batched simulator in which an earlier expert
crashed (side impacts with a slower car changing lanes while the ego swerved past it astride a
lane line), driven by the shipped expert up to just after the old crash."""

import dataclasses

import pytest

from mmpc.highway import run_lockstep
from mmpc.scenario import load_scenario

#: seed -> when the expert at 1923571 crashed [s] (docs/experiments/2026-11-26-no-crash.md); in
#: 50401 the expert of 14f0f67 too (7.9 s): the car the ego overtook on its lane moved into the
#: lane the ego was entering, as MOBIL had let it (only a contingency foresees it).
OLD_CRASHES = {40042: 2.7, 40005: 8.9, 50401: 8.0}


@pytest.mark.parametrize("seed", [40042] + [pytest.param(seed, marks=pytest.mark.slow) for seed in (40005, 50401)])
def test_the_shipped_expert_passes_where_the_old_one_crashed(seed):
    scenario = dataclasses.replace(load_scenario("high_speed"), sim="batched", duration=OLD_CRASHES[seed] + 1.5)
    [result] = run_lockstep(scenario, [seed])
    assert result.metrics["collisions"] == 0, result.metrics
