import dataclasses

import pytest

from mmpc import HighSpeedGoals, NearLaneGoals, Road
from mmpc.evaluate import scenario_fingerprint
from mmpc.footprint import ellipse_coverage
from mmpc.scenario import (
    SCENARIO_DIR, CruiseObjective, HighSpeedObjective, IDMTraffic, NGSIMTraffic, ScenarioConfig, ScriptedTraffic,
    load_scenario,
)


def test_shipped_cruise_yaml_is_the_default_scenario():
    assert load_scenario("cruise") == ScenarioConfig()


def test_shipped_high_speed_yaml_is_the_paper_layout():
    scenario = load_scenario("high_speed")
    assert isinstance(scenario.objective, HighSpeedObjective)
    assert scenario.objective.v_max == 24.0 and scenario.optimizer.v_max >= 24.0
    assert scenario.traffic.vehicles_density >= 1.5 and scenario.traffic.target_speeds == (7.0, 12.0)
    assert len(scenario.seeds) == 20 and scenario.duration == 40.0 and scenario.lanes == 6


def test_every_shipped_scenario_loads():
    names = sorted(p.stem for p in SCENARIO_DIR.glob("*.yaml"))
    assert {"cruise", "high_speed"} <= set(names)
    for name in names:
        assert load_scenario(name).name == name


@pytest.mark.parametrize(
    "values, bad_key",
    [
        ({"duraton": 10.0}, "duraton"),
        ({"objective": {"type": "cruise", "v_cruse": 15.0}}, "v_cruse"),
        ({"traffic": {"type": "idm", "vehicle_count": 10}}, "vehicle_count"),
        ({"traffic": {"type": "scripted", "vehicles": [{"lane": 1, "x": 20.0, "speed": 8.0, "lanes": 2}]}}, "lanes"),
        ({"ego": {"speeed": 10.0}}, "speeed"),
        ({"optimizer": {"iteratons": 10}}, "iteratons"),
        ({"mpc": {"num_obstacle": 3}}, "num_obstacle"),
    ],
)
def test_unknown_keys_are_errors(values, bad_key):
    with pytest.raises(ValueError, match=bad_key):
        ScenarioConfig.from_dict(values)


def test_yaml_file_with_unknown_key_is_an_error(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("name: bad\ntraffic: {type: idm, vehicles_densty: 2.0}\n")
    with pytest.raises(ValueError, match="vehicles_densty"):
        load_scenario(path)


def test_variants_need_a_known_type():
    with pytest.raises(ValueError, match="type"):
        ScenarioConfig.from_dict({"objective": {"v_cruise": 15.0}})
    with pytest.raises(ValueError, match="fast_lane"):
        ScenarioConfig.from_dict({"objective": {"type": "fast_lane"}})


def test_missing_scenario_lists_the_shipped_ones():
    with pytest.raises(FileNotFoundError, match="high_speed"):
        load_scenario("no_such_scenario")


@pytest.mark.parametrize(
    "values, message",
    [
        ({"objective": {"type": "high_speed", "v_max": 35.0}}, "optimizer.v_max"),
        ({"lanes": 3, "ego": {"lane": 3}}, "ego.lane"),
        ({"lanes": 3, "traffic": {"type": "scripted", "vehicles": [{"lane": 3, "x": 10.0, "speed": 5.0}]}}, "lane 3"),
        ({"mpc": {"num_obstacles": 12}}, "max_obstacles"),
        ({"duration": 0.0}, "duration"),
        ({"seeds": []}, "seeds"),
        ({"vehicle_size": [4.0, 1.4]}, "wheelbase"),
        ({"vehicle_size": [4.0, -1.4], "mpc": {"wheelbase": 4.0}}, "vehicle_width"),
        ({"vehicle_size": [4.0], "mpc": {"wheelbase": 4.0}}, "vehicle_size"),
        ({"vehicle_size": [4.0, 1.4], "mpc": {"wheelbase": 4.0}, "traffic": {"type": "ngsim", "path": "x.csv"}}, "NGSIM"),
        ({"mpc": {"wheelbase": 4.0}}, "wheelbase"),
    ],
)
def test_inconsistent_scenarios_are_rejected(values, message):
    with pytest.raises(ValueError, match=message):
        ScenarioConfig.from_dict(values)


def test_to_dict_omits_unset_settings_and_round_trips():
    """A top-level setting left at None (vehicle_size, added after datasets and evaluations were
    written) is not part of the record, so earlier records keep their identity; a set one is."""
    plain = load_scenario("cruise")
    small = plain.replace(vehicle_size=(4.0, 1.4), mpc=dataclasses.replace(plain.mpc, wheelbase=4.0))
    assert "vehicle_size" not in plain.to_dict() and small.to_dict()["vehicle_size"] == [4.0, 1.4]
    for scenario in (plain, small):
        assert ScenarioConfig.from_dict(scenario.to_dict()) == scenario
    assert scenario_fingerprint(small) != scenario_fingerprint(plain)
    assert scenario_fingerprint(ScenarioConfig.from_dict(plain.to_dict())) == scenario_fingerprint(plain)


def test_traffic_values_are_validated():
    with pytest.raises(ValueError, match="target_speeds"):
        IDMTraffic(target_speeds=(12.0, 7.0))
    with pytest.raises(ValueError, match="window"):
        IDMTraffic(window=(-1.0, 100.0))
    with pytest.raises(ValueError, match="window"):
        ScriptedTraffic(window=(30.0,))
    with pytest.raises(ValueError, match="path"):
        NGSIMTraffic(path="")


def test_objectives_build_the_paper_goals_plus_near_lane_goals():
    road = Road(num_lanes=6)
    cruise = CruiseObjective().goal_sampler(road, 8.0)
    assert isinstance(cruise, NearLaneGoals) and cruise.base.num_goals == road.num_lanes
    high = HighSpeedObjective().goal_sampler(road, 8.0)
    assert isinstance(high, NearLaneGoals) and isinstance(high.base, HighSpeedGoals)
    assert isinstance(CruiseObjective(near_lane_speeds=()).goal_sampler(road, 8.0), type(cruise.base))


def test_ellipse_coverage_is_exact_on_aligned_boxes_and_grows_with_heading():
    # aligned 5 m x 2 m boxes touch at |dx| <= 5, |dy| <= 2: the corner (5, 2) decides
    assert ellipse_coverage((8.0, 3.0), 0.0) == pytest.approx(25 / 64 + 4 / 9)
    assert ellipse_coverage((5.6, 3.1), 0.0) > 1  # the authors' ellipse misses highway-env's corners
    assert ellipse_coverage((8.0, 3.3), 13.0, 3.0) == pytest.approx(0.991, abs=1e-3)  # cruise: both turned, still inside
    assert ellipse_coverage((8.0, 3.0), 13.0, 3.0) == pytest.approx(1.128, abs=1e-3)  # why cruise's b is not 3.0
    turned = [ellipse_coverage((8.0, 3.3), heading) for heading in (0.0, 4.0, 8.0, 13.0, 16.0)]
    assert turned == sorted(turned) and ellipse_coverage((8.0, 3.3), -13.0) == pytest.approx(turned[3])
    with pytest.raises(ValueError, match="semi_axes"):
        ellipse_coverage((8.0, 0.0), 0.0)


@pytest.mark.parametrize("name", sorted(p.stem for p in SCENARIO_DIR.glob("*.yaml")))
def test_shipped_ellipses_cover_the_scenario_vehicles_across_the_heading_band(name):
    """The ego anywhere in its heading band, the other car along its lane: no corner of the two
    vehicle boxes' Minkowski sum lies outside the obstacle ellipse."""
    scenario = load_scenario(name)
    optimizer = scenario.optimizer
    axes, band = (optimizer.ellipse_a, optimizer.ellipse_b), optimizer.max_heading_deg
    assert max(ellipse_coverage(axes, heading, vehicle=scenario.vehicle) for heading in (-band, band)) <= 1.0
