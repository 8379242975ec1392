"""Config values of the wrong type are refused by their field types (issue 44, items 7 and 9):
the loader names the dotted key (``optimizer.horizon``), a config built directly names its
field; both through :func:`mmpc.config.fits_type`, not per-field code."""

from __future__ import annotations

from typing import Any, Mapping, Optional

import pytest

from mmpc import OptimizerConfig
from mmpc.cli.arguments import override
from mmpc.cli.main import main
from mmpc.config import ConfigError, fits_type, load_config, require_field_types
from mmpc.rl.config import RLConfig
from mmpc.scenario import EgoConfig, ScenarioConfig, load_scenario
from mmpc.traffic_config import IDMTraffic, ScriptedVehicle
from mmpc.sim import SimConfig
from tests.test_config import CONFIGS


@pytest.mark.parametrize("hint, value, fits", [
    (float, 24, True), (float, 2.5, True), (float, True, False), (float, "4", False), (float, {"a": 1}, False),
    (int, 3, True), (int, 3.0, False), (int, False, False),
    (bool, True, True), (bool, "maybe", False), (bool, 1, False),
    (str, "cruise", True), (str, 3, False),
    (Optional[float], None, True), (Optional[float], "x", False), (Optional[int], 2, True),
    (tuple[float, float], (1, 2.0), True), (tuple[float, float], (1.0,), False), (tuple[float, float], (1.0, "a"), False),
    (tuple[float, float], [1.0, 2.0], False),  # from_dict turns lists into tuples before it checks
    (tuple[int, ...], (), True), (tuple[int, ...], (1, 2), True), (tuple[int, ...], (1, True), False),
    (Mapping[str, Mapping[str, Any]], {"ppo": {"lr": 1e-3}}, True), (Mapping[str, Mapping[str, Any]], {"ppo": 3}, False),
    (OptimizerConfig, OptimizerConfig(), True), (OptimizerConfig, {"horizon": 8.0}, False),
    (Any, object(), True),
])
def test_fits_type_reads_config_field_types(hint, value, fits):
    assert fits_type(hint, value) is fits


@pytest.mark.parametrize("config", CONFIGS, ids=lambda c: type(c).__name__)
def test_every_config_class_holds_values_of_its_field_types(config):
    require_field_types(config)


@pytest.mark.parametrize("key, value, expected", [
    ("horizon", "abc", "a number"), ("ellipse_a", "abc", "a number"), ("ellipse_b", "abc", "a number"),
    ("v_max", "abc", "a number"), ("a_max", "abc", "a number"), ("rho_init", "abc", "a number"),
    ("lane_weight", "abc", "a number"), ("obstacle_backoff", "abc", "a number"),
    ("weight_xy", {"a": 1}, "a number"), ("v_max", True, "a number"), ("iterations", 2.5, "an int"),
    ("start_acceleration", "maybe", "true or false"), ("heading_target_deg", "x", "a number or null"),
])
def test_a_value_of_the_wrong_type_is_refused_by_its_key(key, value, expected):
    with pytest.raises(ConfigError, match=rf"`{key}` must be {expected}; got {value!r}$"):
        load_config(OptimizerConfig, None, {key: value})


@pytest.mark.parametrize("overrides, key", [
    ({"optimizer.horizon": "abc"}, "optimizer.horizon"),
    ({"optimizer.start_acceleration": "maybe"}, "optimizer.start_acceleration"),
    ({"mpc.stop_gap": "abc"}, "mpc.stop_gap"),  # MPCConfig: checked by the loader alone
    ({"mpc.num_obstacles": 2.5}, "mpc.num_obstacles"),
    ({"traffic.lane_changes": "maybe"}, "traffic.lane_changes"),
    ({"traffic.window": ["a", 200.0]}, "traffic.window"),
    ({"ego.speed": "fast"}, "ego.speed"),
    ({"seeds": [1, "x"]}, "seeds"),
])
def test_scenario_overrides_of_the_wrong_type_name_their_dotted_key(overrides, key):
    with pytest.raises(ConfigError, match=rf"`{key}` must be"):
        load_scenario("cruise", overrides)


def test_nested_sections_of_other_configs_are_checked_by_the_loader():
    with pytest.raises(ConfigError, match=r"`train.n_envs` must be an int; got 'eight'"):
        load_config(RLConfig, "smoke", {"train.n_envs": "eight"})
    with pytest.raises(ConfigError, match=r"`scenario.optimizer.v_max` must be a number; got True"):
        load_config(RLConfig, "smoke", {"scenario.optimizer.v_max": True})


def test_values_of_the_right_type_still_load():
    config = load_config(OptimizerConfig, None, {"v_max": 24, "start_acceleration": False, "heading_target_deg": None})
    assert (config.v_max, config.start_acceleration, config.heading_target_deg) == (24, False, None)
    assert load_config(OptimizerConfig, None, dict([override("start_acceleration=no")])).start_acceleration is False
    scenario = load_scenario("cruise", {"traffic.window": [30, 150.5], "seeds": [3, 4], "vehicle_size": [4.5, 2]})
    assert scenario.traffic.window == (30, 150.5) and scenario.seeds == (3, 4) and scenario.vehicle_size == (4.5, 2)


@pytest.mark.parametrize("build, message", [
    (lambda: OptimizerConfig(a_max="4"), "OptimizerConfig: `a_max` must be a number; got '4'"),
    (lambda: OptimizerConfig(start_acceleration="maybe"), "OptimizerConfig: `start_acceleration` must be true or false"),
    (lambda: OptimizerConfig(weight_xy={"a": 1}), "OptimizerConfig: `weight_xy` must be a number"),
    (lambda: SimConfig(acceleration_range=(-5.0, "5")), r"SimConfig: `acceleration_range` must be a list \(tuple\)"),
    (lambda: ScenarioConfig(name=3), "ScenarioConfig: `name` must be a string; got 3"),
    (lambda: ScenarioConfig(seeds=[0, 1]), r"ScenarioConfig: `seeds` must be a list \(tuple\), each item an int"),
    (lambda: EgoConfig(speed="14"), "EgoConfig: `speed` must be a number"),
    (lambda: IDMTraffic(lane_changes="yes"), "IDMTraffic: `lane_changes` must be true or false"),
    (lambda: ScriptedVehicle(lane=1, x="10", speed=5.0), "ScriptedVehicle: `x` must be a number"),
])
def test_a_config_built_directly_names_the_field_of_the_wrong_type(build, message):
    with pytest.raises(ConfigError, match=message):
        build()


def test_the_command_line_refuses_a_value_of_the_wrong_type(tmp_path, capsys):
    assert main(["solve", "--set", "start_acceleration=maybe", "--out", str(tmp_path)]) == 2
    assert "`start_acceleration` must be true or false; got 'maybe'" in capsys.readouterr().err
    assert main(["solve", "--set", "v_max=true", "--out", str(tmp_path)]) == 2
    assert "`v_max` must be a number; got True" in capsys.readouterr().err
    assert main(["config", "show", "optimizer", "--set", "horizon=abc"]) == 2
    assert "`horizon` must be a number; got 'abc'" in capsys.readouterr().err
    assert main(["config", "show", "scenario", "cruise", "--set", "optimizer.horizon=abc"]) == 2
    assert "`optimizer.horizon` must be a number; got 'abc'" in capsys.readouterr().err
    assert main(["config", "show", "mpc", "--set", "num_obstacles=abc"]) == 2
    assert "`num_obstacles` must be an int; got 'abc'" in capsys.readouterr().err
    assert not (tmp_path / "solve.json").exists()
