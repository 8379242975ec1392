"""Traffic that reads the ego as an IDM follower at its present speed (``traffic.ego_as_follower``):
cars may cut in directly ahead of the ego where MOBIL's safety criterion allows, in both worlds, and
the check stops counting on the old reading."""

import torch

from mmpc.highway.episode import HighwayEpisode
from mmpc.scenario import load_scenario
from mmpc.sim import SimConfig, vehicle_state
from mmpc.sim.mobil import mobil_safe
from mmpc.verify import TrafficAssumptions, Verifier


def scene(gap_ahead: float):
    """The ego on lane 1 at 20 m/s, a car on lane 2 at 20 m/s ``gap_ahead`` metres ahead (centres)."""
    return vehicle_state(torch.tensor([[0.0, gap_ahead]]), torch.tensor([[4.0, 8.0]]), 0.0, torch.tensor([[20.0, 20.0]]),
                         config=SimConfig())


def test_mobil_lets_a_car_cut_in_ahead_of_the_ego_only_when_it_reads_the_ego_as_an_idm_follower():
    into_egos_lane = torch.tensor([[1]])
    car = torch.tensor([[1]])
    artefact, follower = SimConfig(), SimConfig(ego_as_follower=True)
    # far enough ahead that an IDM follower at 20 m/s brakes less than 2 m/s^2: safe by the criterion
    assert not bool(mobil_safe(scene(80.0), into_egos_lane, artefact, car))  # the ego read with no target speed
    assert bool(mobil_safe(scene(80.0), into_egos_lane, follower, car))
    # close ahead the follower would brake harder: refused either way
    assert not bool(mobil_safe(scene(20.0), into_egos_lane, follower, car))


def test_both_worlds_and_the_check_read_the_scenario_option():
    scenario = load_scenario("high_speed", {"traffic.ego_as_follower": True, "duration": 1.0})
    from mmpc.sim.traffic import sim_config

    assert sim_config(scenario).ego_as_follower and not sim_config(load_scenario("high_speed")).ego_as_follower
    # the check's default rule covers both readings (cars cut in where the ego as a follower allows)
    assert Verifier.for_scenario(scenario).assumptions == Verifier.for_scenario(load_scenario("high_speed")).assumptions
    assert Verifier.for_scenario(scenario).assumptions.cut_in == "follower"
    assert TrafficAssumptions.for_scenario(scenario, cut_in="highway-env").cut_in == "highway-env"
    episode = HighwayEpisode(scenario, seed=0)
    try:
        speed = float(episode.ego.speed)
        episode.apply(0.0, 0.0)
        assert episode.ego.target_speed == speed  # highway-env's MOBIL reads it as the follower's target speed
    finally:
        episode.close()
