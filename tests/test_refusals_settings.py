"""Refusals found by a hostile probe (issue 55): settings checked against each other and for NaN
or inf by the one config loader, the run's device and --threads checked before any work, every
refusal one line on stderr (an --out that cannot be written included) while a bug keeps its
traceback, SDL's XDG_RUNTIME_DIR noise gone from a drive, the NGSIM scenario refused before it
makes a folder, the driver specs in --help, and a README whose commands parse."""

from __future__ import annotations

import math
import re

import pytest
import yaml

from mmpc.cli.main import main
from mmpc.config import ConfigError, load_config
from mmpc.imitation.bc import TrainConfig as BCTrainConfig
from mmpc.scenario import EgoConfig, IDMTraffic, load_scenario


def _error_lines(err: str) -> list[str]:
    """The lines of stderr that are not progress bars (tqdm redraws with carriage returns)."""
    lines = [line.rsplit("\r", 1)[-1].strip() for line in err.splitlines()]
    return [line for line in lines if line and not re.search(r"\d+/\d+ \[", line)]


def _one_refusal(err: str, start: str) -> str:
    """The single error line of ``err``, which must start with ``start``; no traceback."""
    assert "Traceback" not in err, err
    lines = _error_lines(err)
    assert len(lines) == 1 and lines[0].startswith(start), lines
    return lines[0]


# ---------------------------------------------------------------- item 6: settings checked together


def test_warm_iterations_above_the_schedule_is_refused_naming_both_keys():
    with pytest.raises(ConfigError, match=r"`mpc.warm_iterations` \(101\) must be <= `optimizer.iterations` \(100\)"):
        load_scenario("cruise", {"mpc.warm_iterations": 101})
    with pytest.raises(ConfigError, match=r"`mpc.warm_iterations` \(40\) must be <= `optimizer.iterations` \(30\)"):
        load_scenario("high_speed", {"optimizer.iterations": 30, "mpc.warm_iterations": 40})
    assert load_scenario("cruise", {"mpc.warm_iterations": 100}).mpc.warm_iterations == 100  # the whole schedule


def test_drive_refuses_warm_iterations_above_the_schedule_before_any_work(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["drive", "--set", "mpc.warm_iterations=500", "--out", str(out)]) == 2
    line = _one_refusal(capsys.readouterr().err, "mmpc drive: error:")
    assert "mpc.warm_iterations" in line and "optimizer.iterations" in line
    assert not out.exists()


# ---------------------------------------------------------------- item 7: NaN and inf refused by the loader


@pytest.mark.parametrize("scenario, overrides, key, shown", [
    ("cruise", {"ego.speed": math.inf}, "ego.speed", "inf"),
    ("cruise", {"traffic.target_speeds": [math.inf, math.inf]}, "traffic.target_speeds[0]", "inf"),
    ("high_speed", {"objective.other_distance": math.inf}, "objective.other_distance", "inf"),
    ("high_speed", {"objective.right_lane_distances": [150.0, math.inf]}, "objective.right_lane_distances[1]", "inf"),
    ("cruise", {"mpc.contingency_min_gain": math.nan}, "mpc.contingency_min_gain", "nan"),
    ("cruise", {"vehicle_size": [5.0, -math.inf]}, "vehicle_size[1]", "-inf"),
    ("cruise", {"optimizer.heading_target_deg": math.nan}, "optimizer.heading_target_deg", "nan"),  # Optional[float]
])
def test_a_non_finite_float_is_refused_naming_its_key(scenario, overrides, key, shown):
    with pytest.raises(ConfigError, match=re.escape(f"`{key}` must be finite; got {shown}")):
        load_scenario(scenario, overrides)


def test_the_training_configs_refuse_non_finite_floats_through_the_same_loader():
    with pytest.raises(ConfigError, match=re.escape("`weight_decay` must be finite; got inf")):
        load_config(BCTrainConfig, None, {"weight_decay": math.inf})


def test_a_yaml_file_with_inf_and_nan_is_refused(tmp_path):
    path = tmp_path / "scenario.yaml"
    path.write_text(yaml.safe_dump({"from": "cruise", "ego": {"speed": 14.0}}) + "traffic: {type: idm, target_speeds: [7.0, .nan]}\n")
    with pytest.raises(ConfigError, match=re.escape("`traffic.target_speeds[1]` must be finite; got nan")):
        load_scenario(path)


def test_a_config_built_directly_refuses_non_finite_floats_too():
    with pytest.raises(ConfigError, match=re.escape("EgoConfig: `speed` must be finite; got inf")):
        EgoConfig(speed=math.inf)
    with pytest.raises(ConfigError, match=re.escape("IDMTraffic: `window[1]` must be finite; got inf")):
        IDMTraffic(window=(60.0, math.inf))
    assert IDMTraffic(target_speeds=None, window=None).window is None  # Optional left empty


@pytest.mark.parametrize("argv, verb, key", [
    (["config", "show", "scenario", "cruise", "--set", "ego.speed=.inf"], "config show", "ego.speed"),
    (["drive", "--set", "mpc.contingency_min_gain=.nan"], "drive", "mpc.contingency_min_gain"),
    (["imitate", "bc", "--dataset", "no-such-dataset", "--set", "weight_decay=.inf"], "imitate bc", "weight_decay"),
])
def test_set_refuses_a_non_finite_value_in_one_line(argv, verb, key, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(argv if verb == "config show" else [*argv, "--out", str(out)]) == 2
    line = _one_refusal(capsys.readouterr().err, f"mmpc {verb}: error:")
    assert re.search(rf"`{re.escape(key)}` must be finite; got (inf|nan)$", line), line
    assert not out.exists()
