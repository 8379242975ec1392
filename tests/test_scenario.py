import dataclasses

import pytest

from mmpc import HighSpeedGoals, NearLaneGoals, Road
from mmpc.config import from_dict, to_dict
from mmpc.evaluate import scenario_fingerprint
from mmpc.mpc import MPCConfig
from mmpc.obstacles.shape import ellipse_coverage, smallest_covering_axis
from mmpc.scenario import SCENARIO_DIR, CruiseObjective, HighSpeedObjective, ScenarioConfig, build_mpc, load_scenario
from mmpc.traffic_config import IDMTraffic, NGSIMTraffic, ScriptedTraffic


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
        from_dict(ScenarioConfig, values)


def test_yaml_file_with_unknown_key_is_an_error(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("name: bad\ntraffic: {type: idm, vehicles_densty: 2.0}\n")
    with pytest.raises(ValueError, match="vehicles_densty"):
        load_scenario(path)


def test_variants_need_a_known_type():
    with pytest.raises(ValueError, match="type"):
        from_dict(ScenarioConfig, {"objective": {"v_cruise": 15.0}})
    with pytest.raises(ValueError, match="fast_lane"):
        from_dict(ScenarioConfig, {"objective": {"type": "fast_lane"}})


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
        ({"vehicle_size": [4.0, -1.4]}, "vehicle_width"),
        ({"vehicle_size": [4.0]}, "vehicle_size"),
        ({"vehicle_size": [4.0, 1.4], "traffic": {"type": "ngsim", "path": "x.csv"}}, "NGSIM"),
        ({"optimizer": {"ellipse_a": 8.0, "ellipse_b": 3.0}}, "does not cover two 5.0 m x 2.0 m vehicles"),
    ],
)
def test_inconsistent_scenarios_are_rejected(values, message):
    with pytest.raises(ValueError, match=message):
        from_dict(ScenarioConfig, values)


def test_to_dict_omits_unset_settings_and_round_trips():
    """A top-level setting left at None (vehicle_size, added after datasets and evaluations were
    written) is not part of the record, so earlier records keep their identity; a set one is."""
    plain = load_scenario("cruise")
    small = plain.replace(vehicle_size=(4.0, 1.4))
    assert "vehicle_size" not in to_dict(plain) and to_dict(small)["vehicle_size"] == [4.0, 1.4]
    for scenario in (plain, small):
        assert from_dict(ScenarioConfig, to_dict(scenario)) == scenario
    assert scenario_fingerprint(small) != scenario_fingerprint(plain)
    assert scenario_fingerprint(from_dict(ScenarioConfig, to_dict(plain))) == scenario_fingerprint(plain)


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


def test_the_ellipse_is_checked_at_load_and_the_message_names_the_smallest_covering_one():
    """cruise's b = 3.3 m is what covers two 5 m x 2 m cars over its 13-degree band: b = 3.0 m is
    refused, naming b >= 3.14 m for a = 8 m (and a for b = 3 m); with an 8-degree band 3.0 m is enough."""
    with pytest.raises(ValueError, match=r"ellipse_coverage 1\.062 > 1.*`optimizer.ellipse_b` >= 3\.14 m with a = 8\.0 m "
                                         r"or `optimizer.ellipse_a` >= 8\.83 m with b = 3\.0 m"):
        load_scenario("cruise", {"optimizer.ellipse_b": 3.0})
    with pytest.raises(ValueError, match="no b covers them with a = 4.5 m"):
        load_scenario("cruise", {"optimizer.ellipse_a": 4.5})
    assert load_scenario("cruise", {"optimizer.ellipse_b": 3.14, "optimizer.max_heading_deg": 13.0}).optimizer.ellipse_b == 3.14
    assert load_scenario("cruise", {"optimizer.ellipse_b": 3.0, "optimizer.max_heading_deg": 8.0,
                                    "optimizer.heading_target_deg": 7.2}).optimizer.ellipse == (8.0, 3.0)
    # the authors' smaller cars are covered by their smaller ellipse, highway-env's are not
    assert load_scenario("cruise_paper").optimizer.ellipse == (5.6, 3.1)
    with pytest.raises(ValueError, match="does not cover two 5.0 m x 2.0 m vehicles"):
        load_scenario("cruise_paper", {"vehicle_size": None})
    b = smallest_covering_axis(8.0, "a", (-13.0, 13.0))
    assert max(ellipse_coverage((8.0, b), h) for h in (-13.0, 13.0)) == pytest.approx(1.0)
    a = smallest_covering_axis(3.3, "b", (-13.0, 13.0))
    assert max(ellipse_coverage((a, 3.3), h) for h in (-13.0, 13.0)) == pytest.approx(1.0)


# ----------------------------------------------------------------------------------- retired settings

#: A scenario as mmpc wrote it (ScenarioConfig.to_dict) before compiling became a run option and the
#: wheelbase was derived: dataset manifests, DAgger runs, RL run folders and old YAML files hold these keys.
OLD_CRUISE_PAPER = {
    "name": "cruise_paper", "objective": {"type": "cruise", "v_cruise": 15.0, "near_lane_speeds": [3.0, 6.0, 9.0, 12.0],
                                          "near_lanes": 2},
    "lanes": 6, "duration": 67.0, "frequency": 10.0, "seeds": [0, 1], "env_id": "highway-v0",
    "ego": {"speed": 14.0, "lane": 0},
    "traffic": {"type": "scripted", "vehicles": [{"lane": 2, "x": 10.0, "speed": 10.0, "lane_change": False,
                                                  "constant_speed": False, "cut_in_lane": None, "cut_in_at": 0.0,
                                                  "brake_at": None, "brake_deceleration": 6.0}],
                "window": [36.0, 200.0]},
    "vehicle_size": [4.0, 1.4],
    "optimizer": {"ellipse_a": 5.6, "ellipse_b": 3.1, "max_heading_deg": 13.0, "heading_target_deg": 11.7, "v_max": 30.0},
    "mpc": {"num_obstacles": 6, "ignore_behind": 20.0, "obstacle_lookahead": 3.0, "prediction": "lanes",
            "wheelbase": 4.0, "command_window": 0.3, "tie_tolerance": 0.01, "tie_margin": 1.0, "brake_deceleration": 4.0,
            "max_deceleration": 5.0, "stop_lanes": 1, "stop_gap": 2.0, "max_steering": 0.7853981633974483,
            "road_margin": 1.0, "compile": "auto"},
}


def test_an_old_scenario_with_compile_and_wheelbase_loads_with_warnings(caplog, tmp_path):
    import yaml

    path = tmp_path / "old.yaml"
    path.write_text(yaml.safe_dump(OLD_CRUISE_PAPER))
    with caplog.at_level("WARNING", logger="mmpc.scenario"):
        scenario = load_scenario(path)
    assert "`mpc.compile: auto` is ignored: compiling is a run option" in caplog.text
    assert "`mpc.wheelbase` is ignored: the MPC takes the vehicle length (4.0 m)" in caplog.text
    assert scenario.mpc == MPCConfig() and scenario.vehicle == (4.0, 1.4)
    assert scenario == from_dict(ScenarioConfig, {**OLD_CRUISE_PAPER, "mpc": {}})
    assert build_mpc(scenario).wheelbase == 4.0 and build_mpc(load_scenario("cruise")).wheelbase == 5.0
    cruise = to_dict(load_scenario("cruise"))
    old_cruise = {**cruise, "mpc": {**cruise["mpc"], "wheelbase": 5.0, "compile": False}}
    assert from_dict(ScenarioConfig, old_cruise) == load_scenario("cruise")


def test_an_old_wheelbase_other_than_the_vehicle_length_is_refused():
    with pytest.raises(ValueError, match=r"`mpc.wheelbase` is 5.0 m but the vehicles are 4.0 m long.*remove `mpc.wheelbase`"):
        from_dict(ScenarioConfig, {**OLD_CRUISE_PAPER, "mpc": {"wheelbase": 5.0}})
    with pytest.raises(ValueError, match=r"`mpc.wheelbase` is 4.0 m but the vehicles are 5.0 m long.*vehicle_size: \[4.0, WIDTH\]"):
        load_scenario("cruise", {"mpc.wheelbase": 4.0})
    assert "wheelbase" not in {f.name for f in dataclasses.fields(MPCConfig)}


def test_compile_is_a_run_option_not_part_of_the_scenario(monkeypatch):
    from mmpc.solver.execution import COMPILE_ENV

    assert "compile" not in {f.name for f in dataclasses.fields(MPCConfig)}
    plain = load_scenario("cruise")
    assert scenario_fingerprint(load_scenario("cruise", {"mpc.compile": False})) == scenario_fingerprint(plain)
    assert scenario_fingerprint(load_scenario("cruise", {"mpc.stop_gap": 3.0})) != scenario_fingerprint(plain)
    monkeypatch.setenv(COMPILE_ENV, "0")
    assert not build_mpc(plain).optimizer.compiled  # "auto" reads MMPC_COMPILE
    assert build_mpc(plain, compile=True).optimizer.compiled  # an explicit choice wins
    monkeypatch.setenv(COMPILE_ENV, "1")
    assert build_mpc(plain).optimizer.compiled and not build_mpc(plain, compile=False).optimizer.compiled
