"""Regression scenes: high-speed episodes of the batched simulator in which an earlier expert
crashed (side impacts with a slower car changing lanes while the ego swerved past it astride a
lane line), driven by the shipped expert up to just after the old crash."""

import dataclasses

import pytest

from mmpc.drivers import make_driver
from mmpc.highway import run_lockstep
from mmpc.scenario import load_scenario

#: seed -> when the expert at 1923571 crashed [s] (docs/experiments/2026-11-26-no-crash.md).
OLD_CRASHES = {40042: 2.7, 40005: 8.9}


@pytest.mark.parametrize("seed", [40042, pytest.param(40005, marks=pytest.mark.slow)])
def test_the_shipped_expert_passes_where_the_old_one_crashed(seed):
    scenario = dataclasses.replace(load_scenario("high_speed"), sim="batched", duration=OLD_CRASHES[seed] + 1.5)
    [result] = run_lockstep(scenario, [seed])
    assert result.metrics["collisions"] == 0, result.metrics


def test_the_verified_expert_keeps_clear_of_the_overtaken_car_moving_into_the_ego_s_new_lane():
    """Seed 50401: the shipped expert crashes at 7.9 s (checked), the car it overtakes on its
    lane moving, as MOBIL lets it, into the lane the ego enters; behind the check
    (:mod:`mmpc.verify`, which replaced the MPC's lane-change contingencies) it does not."""
    scenario = dataclasses.replace(load_scenario("high_speed"), sim="batched", duration=9.5)
    [crash] = run_lockstep(scenario, [50401])
    [result] = run_lockstep(scenario, [50401], driver=make_driver("verified:mpc", scenario))
    assert crash.metrics["collisions"] == 1 and result.metrics["collisions"] == 0, result.metrics
