import ast
import dataclasses
import importlib
import os
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from mmpc import MPCConfig, OptimizerConfig
from mmpc.config import ConfigError, from_dict, load_config, require_int, to_dict, with_overrides
from mmpc.drivers.frenet import FrenetConfig
from mmpc.drivers.nlp import NLPConfig
from mmpc.evaluate import CeilingConfig, EvaluationConfig
from mmpc.imitation.bc import TrainConfig as BCTrainConfig
from mmpc.imitation.dagger import DAGGER_POLICY, DaggerConfig
from mmpc.imitation.features import FeatureConfig, SceneGeometry
from mmpc.imitation.listwise import ProposerTrainConfig
from mmpc.imitation.policy import PolicyConfig
from mmpc.imitation.proposer import ProposerConfig
from mmpc.imitation.proposer_dagger import ProposerDaggerConfig
from mmpc.rl.config import RL_SCENARIO, RewardConfig, RLConfig, SafeEnvConfig
from mmpc.rl.config import TrainConfig as RLTrainConfig
from mmpc.sim import SimConfig
from mmpc.tracking import TrackingConfig
from mmpc.scenario import CruiseObjective, EgoConfig, HighSpeedObjective, ScenarioConfig, load_scenario
from mmpc.traffic_config import IDMTraffic, NGSIMTraffic, ScriptedTraffic, ScriptedVehicle

ROOT = Path(__file__).resolve().parents[1]

#: One valid instance of every config class (those without defaults get literal values).
CONFIGS = [
    OptimizerConfig(), MPCConfig(), ScenarioConfig(), EgoConfig(lane=2), CruiseObjective(), HighSpeedObjective(),
    IDMTraffic(), NGSIMTraffic(path="us101.csv", location="us-101"),
    ScriptedVehicle(lane=1, x=20.0, speed=8.0, cut_in_lane=2, cut_in_at=1.0, brake_at=2.0),
    ScriptedTraffic(vehicles=(ScriptedVehicle(0, 10.0, 5.0), ScriptedVehicle(2, -5.0, 7.0, constant_speed=True)),
                    window=(30.0, 150.0)),
    FrenetConfig(), NLPConfig(), RewardConfig(), SafeEnvConfig(), RLTrainConfig(), RLConfig(), BCTrainConfig(),
    PolicyConfig(), DaggerConfig(), SceneGeometry(4.0, (5.6, 3.1)), FeatureConfig(SceneGeometry(5.0, (8.0, 3.3))),
    EvaluationConfig(drivers=("mpc", "frenet"), seeds=(3, 1), ray="auto", episode_layout="{driver}/{seed}"),
    SimConfig(), TrackingConfig(speed_gain=2.0, max_lateral_error=0.3), SafeEnvConfig(replan="decision"),
    RewardConfig(source="meta_cost", meta_cost_scale=50.0),
    ProposerConfig(hidden=(64,)), ProposerTrainConfig(), ProposerDaggerConfig(),
    CeilingConfig(beam=16, verify=False, cell=(0.5, 0.5, 0.2), driver="mpc"),
]


def _frozen_dataclasses() -> set[str]:
    """Names of every frozen dataclass of the installed packages' sources whose name ends in
    Config, Objective, Traffic, Vehicle or Geometry (what a YAML file or a record can hold)."""
    names = set()
    for folder in ("mmpc", "rl", "imitation"):
        for path in (ROOT / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.ClassDef) and node.name.endswith(("Config", "Objective", "Traffic", "Vehicle", "Geometry")) \
                        and any("dataclass" in ast.unparse(d) and "frozen=True" in ast.unparse(d) for d in node.decorator_list):
                    names.add(node.name)
    return names


def test_defaults_are_the_authors_numbers():
    cfg = OptimizerConfig()
    assert (cfg.horizon, cfg.num_steps, cfg.order, cfg.iterations) == (8.0, 100, 10, 100)
    assert (cfg.ellipse_a, cfg.ellipse_b, cfg.a_max) == (5.6, 3.0, 4.0) == (*cfg.ellipse, 4.0)
    rho = cfg.rho_schedule()
    assert len(rho) == 100 and rho[0] == 1.0 and rho[1] == pytest.approx(1.06)


@pytest.mark.parametrize(
    "field, value",
    [("horizon", -1.0), ("num_steps", 1), ("order", 2), ("iterations", 0), ("v_max", 0.05),
     ("a_max", 0.0), ("max_heading_deg", 95.0), ("rho_growth", 0.9), ("num_steps", 10.5),
     ("ellipse_a", float("nan")), ("max_obstacles", -1), ("heading_target_deg", 14.0),
     ("heading_target_deg", 0.0), ("heading_target_deg", float("nan"))],
)
def test_invalid_values_name_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        OptimizerConfig(**{field: value})


def test_from_dict_rejects_unknown_keys_naming_the_section_and_the_allowed_keys():
    assert from_dict(OptimizerConfig, {"iterations": 50}).iterations == 50
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['iteratons'\] in OptimizerConfig; allowed keys: .*'iterations'"):
        from_dict(OptimizerConfig, {"iteratons": 50})
    with pytest.raises(ValueError, match=r"\['stop_gapp'\] in my.yaml: mpc; allowed keys: .*'stop_gap'"):
        from_dict(ScenarioConfig, {"mpc": {"stop_gapp": 1.0}}, where="my.yaml")
    with pytest.raises(ValueError, match=r"my.yaml: traffic scripted: vehicles\[1\]; allowed"):
        from_dict(ScenarioConfig, {"traffic": {"type": "scripted", "vehicles": [{"lane": 1, "x": 5.0, "speed": 3.0},
                                                                                {"lane": 1, "x": 50.0, "sped": 3.0}]}},
                  where="my.yaml")
    with pytest.raises(ValueError, match="my.yaml: ego must be a mapping"):
        from_dict(ScenarioConfig, {"ego": [14.0]}, where="my.yaml")


def test_from_dict_reads_field_types():
    scenario = from_dict(ScenarioConfig, {
        "seeds": [3, 4], "vehicle_size": [4.0, 1.4], "ego": None,  # an empty section: the defaults
        "objective": {"type": "high_speed", "right_lane_distances": [150.0, 170.0]},
        "traffic": {"type": "scripted", "window": [36.0, 200.0], "vehicles": [{"lane": 0, "x": 10.0, "speed": 5.0}]},
        "optimizer": {"ellipse_a": 5.6, "ellipse_b": 3.1, "heading_target_deg": None},
    })
    assert scenario.seeds == (3, 4) and scenario.vehicle_size == (4.0, 1.4) and scenario.ego == EgoConfig()
    assert scenario.objective == HighSpeedObjective(right_lane_distances=(150.0, 170.0))
    assert scenario.traffic == ScriptedTraffic(vehicles=(ScriptedVehicle(0, 10.0, 5.0),), window=(36.0, 200.0))
    assert scenario.optimizer.heading_target_deg is None
    with pytest.raises(ValueError, match="objective must be a mapping with a `type` key"):
        from_dict(ScenarioConfig, {"objective": {"v_cruise": 15.0}})
    with pytest.raises(ValueError, match="`type` is 'idm'; expected 'scripted'"):
        from_dict(ScriptedTraffic, {"type": "idm"})


def test_every_config_class_is_in_the_round_trip_list():
    assert _frozen_dataclasses() <= {type(config).__name__ for config in CONFIGS} | {"TrainConfig"}
    assert {BCTrainConfig, RLTrainConfig} <= {type(config) for config in CONFIGS}


@pytest.mark.parametrize("config", CONFIGS, ids=lambda c: type(c).__name__)
def test_to_dict_round_trips_through_yaml(config):
    written = yaml.safe_dump(to_dict(config))
    assert from_dict(type(config), yaml.safe_load(written)) == config
    assert from_dict(type(config), to_dict(config, complete=True)) == config


def _changed(value, data):
    """A nearby value of the same kind (a number scaled, an int moved, a bool flipped, a tuple
    reordered or shortened, a nested config with one field changed)."""
    if isinstance(value, bool):
        return not value
    if isinstance(value, int):
        return value + data.draw(st.integers(-2, 3))
    if isinstance(value, float):
        return value * data.draw(st.floats(0.5, 2.0))
    if isinstance(value, tuple) and value:
        return data.draw(st.sampled_from([tuple(reversed(value)), value[:-1], value + value[-1:]]))
    if dataclasses.is_dataclass(value):
        return _with_one_change(value, data)
    return value


def _with_one_change(config, data):
    field = data.draw(st.sampled_from([f.name for f in dataclasses.fields(config)]))
    try:
        return dataclasses.replace(config, **{field: _changed(getattr(config, field), data)})
    except (ValueError, TypeError):
        assume(False)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.filter_too_much, HealthCheck.too_slow])
@given(st.sampled_from(CONFIGS), st.data())
def test_every_valid_variant_of_every_config_round_trips(config, data):
    """from_dict(type(c), to_dict(c)) == c for configs one (possibly nested) field away from the
    listed ones, through YAML text."""
    changed = _with_one_change(config, data)
    assert from_dict(type(changed), yaml.safe_load(yaml.safe_dump(to_dict(changed)))) == changed


def test_to_dict_writes_variants_with_their_type_and_leaves_out_unset_optionals():
    values = to_dict(ScenarioConfig())
    assert values["objective"]["type"] == "cruise" and values["traffic"]["type"] == "idm"
    assert "vehicle_size" not in values and "lane" not in values["ego"]
    assert to_dict(ScenarioConfig(), complete=True)["vehicle_size"] is None
    assert isinstance(values["seeds"], list) and isinstance(values["traffic"]["window"], list)


# ----------------------------------------------------------------------------------- load_config


def test_load_config_takes_a_shipped_name_a_path_or_the_defaults(tmp_path):
    assert load_config(ScenarioConfig, "high_speed") == load_scenario("high_speed")
    assert load_config(RLConfig) == RLConfig() and RLConfig().scenario == load_scenario(RL_SCENARIO)
    path = tmp_path / "optimizer.yaml"
    path.write_text("iterations: 10\nellipse_b: 3.3\n")
    assert load_config(OptimizerConfig, path) == OptimizerConfig(iterations=10, ellipse_b=3.3)
    with pytest.raises(FileNotFoundError, match="ships no named configs; give a YAML path"):
        load_config(OptimizerConfig, "default")
    with pytest.raises(FileNotFoundError, match=r"shipped rl: \[.*'smoke'"):
        load_config(RLConfig, "safe_highway")


def test_load_config_rejects_unknown_keys_in_files(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("iterations: 10\nrho_grwoth: 1.1\n")
    with pytest.raises(ValueError, match=f"rho_grwoth.*in OptimizerConfig {path}"):
        load_config(OptimizerConfig, path)


def test_overrides_change_one_value_of_what_would_be_loaded(tmp_path):
    assert load_config(ScenarioConfig, "cruise", {"mpc.stop_gap": 3.0}).mpc.stop_gap == 3.0
    # a section the file leaves out starts from the field's default, not from the section class's
    path = tmp_path / "dagger.yaml"
    path.write_text("iterations: 2\n")
    dagger = load_config(DaggerConfig, path, {"train.epochs": 4})
    assert dagger.iterations == 2 and dagger.train == BCTrainConfig(epochs=4, policy=DAGGER_POLICY)
    rl = load_config(RLConfig, None, {"scenario.duration": 5.0, "algorithms.dqn.gamma": 0.9})
    assert rl.scenario == load_scenario(RL_SCENARIO).replace(duration=5.0)
    assert rl.algorithms["dqn"] == {**RLConfig().algorithms["dqn"], "gamma": 0.9}
    # a section named by a string: the named config, changed
    path.write_text("scenario: high_speed\n")
    assert load_config(RLConfig, path, {"scenario.lanes": 5}).scenario == load_scenario("high_speed").replace(lanes=5)
    with pytest.raises(ValueError, match="unknown key.*'stop_gapp'"):
        load_config(ScenarioConfig, "cruise", {"mpc.stop_gapp": 3.0})
    with pytest.raises(ValueError, match="override 'name.first': 'name' is not a section"):
        load_config(ScenarioConfig, "cruise", {"name.first": "x"})
    assert with_overrides(OptimizerConfig(), {"iterations": 7}) == OptimizerConfig(iterations=7)


def test_a_section_can_start_from_another_config(tmp_path):
    base = tmp_path / "base.yaml"
    base.write_text("name: base\nlanes: 4\nobjective: {type: cruise, v_cruise: 12.0}\n"
                    "optimizer: {ellipse_a: 8.0, ellipse_b: 3.0, max_heading_deg: 8.0}\n")
    child = tmp_path / "child.yaml"
    child.write_text(f"from: {base}\nname: child\noptimizer: {{iterations: 30}}\n")
    scenario = load_config(ScenarioConfig, child)
    assert (scenario.name, scenario.lanes, scenario.objective.v_cruise) == ("child", 4, 12.0)
    assert (scenario.optimizer.iterations, scenario.optimizer.max_heading_deg) == (30, 8.0)  # merged key by key
    child.write_text(f"from: {base}\nobjective: {{type: high_speed}}\n")  # another variant replaces the section
    assert load_config(ScenarioConfig, child).objective == HighSpeedObjective()
    base.write_text(f"from: {child}\n")
    with pytest.raises(ValueError, match="reads itself"):
        load_config(ScenarioConfig, child)


def test_shipped_configs_round_trip():
    for name in ("cruise", "cruise_paper", "cruise_ngsim", "high_speed", RL_SCENARIO):
        scenario = load_scenario(name)
        assert from_dict(ScenarioConfig, to_dict(scenario)) == scenario
    smoke = load_config(RLConfig, "smoke")
    assert from_dict(RLConfig, to_dict(smoke)) == smoke and smoke.scenario.name == "rl_smoke"


def test_no_shipped_file_restates_the_defaults():
    """The defaults live in the dataclasses only (``mmpc config show`` prints them)."""
    from mmpc.configs import shipped_config_dir

    assert not (ROOT / "configs" / "optimizer").exists() and not (ROOT / "configs" / "imitation").exists()
    defaults = to_dict(RLConfig())
    shipped = sorted(shipped_config_dir("rl").glob("*.yaml"))
    assert [p.stem for p in shipped] == ["cruise_task", "high_speed", "high_speed_task", "smoke"]
    for path in shipped:  # every value a recipe sets (the scenario aside) differs from the default
        for section, values in yaml.safe_load(path.read_text()).items():
            if section in ("scenario", "algorithms"):
                continue
            loaded = to_dict(from_dict(type(getattr(RLConfig(), section)), values))  # the section's keys checked together
            restated = [key for key in values if loaded[key] == defaults[section][key]]
            assert not restated, f"{path.name}: {section}.{restated} restate the defaults"


# ----------------------------------------------------------------------------------- command line


@pytest.mark.parametrize("kind, name, overrides", [
    ("scenario", "cruise_paper", ["mpc.stop_gap=3.0"]), ("optimizer", None, ["iterations=7"]), ("rl", "smoke", []),
    ("bc", None, ["policy.hidden=[32]"]), ("dagger", None, ["train.epochs=5"]), ("mpc", None, []),
])
def test_config_show_prints_what_load_config_loads(capsys, kind, name, overrides):
    from mmpc.cli.config import config_class
    from mmpc.cli.main import main

    argv = ["config", "show", kind] + ([name] if name else []) + [a for o in overrides for a in ("--set", o)]
    assert main(argv) == 0
    shown = yaml.safe_load(capsys.readouterr().out)
    cls = config_class(kind)
    expected = load_config(cls, name, {k: yaml.safe_load(v) for k, v in (o.split("=") for o in overrides)})
    assert from_dict(cls, shown) == expected


def test_every_verb_with_a_config_takes_set_and_the_mpc_verbs_compile():
    from mmpc.cli.main import build_parser

    parser = build_parser()
    verbs = {
        ("solve",): False, ("drive",): True, ("evaluate",): True,
        ("rl", "train", "--algo", "dqn", "--timesteps", "1", "--out", "x"): True, ("rl", "evaluate", "--model", "m.zip"): True, ("imitate", "demos"): True, ("imitate", "bc", "--dataset", "d"): False,
        ("imitate", "dagger"): True, ("config", "show", "rl"): False,
    }
    for verb, builds_mpc in verbs.items():
        args = parser.parse_args([*verb, "--set", "a.b=[1, 2]", "--set", "c=x"] + (["--compile", "off"] if builds_mpc else []))
        assert args.set == [("a.b", [1, 2]), ("c", "x")], verb
        assert getattr(args, "compile", None) == ("off" if builds_mpc else None), verb
    assert parser.parse_args(["solve", "--config", "my.yaml"]).config == "my.yaml"


def test_solve_takes_an_optimizer_config_and_overrides(tmp_path, capsys):
    from mmpc.cli.main import main

    path = tmp_path / "fast.yaml"
    path.write_text("iterations: 4\n")
    assert main(["solve", "--config", str(path), "--set", "num_steps=30", "--goals", "2", "--out", str(tmp_path)]) == 0
    assert "4 iterations" in capsys.readouterr().out


def test_compile_flag_sets_the_one_environment_variable(monkeypatch):
    from mmpc.cli.arguments import apply_compile
    from mmpc.solver.execution import COMPILE_ENV

    monkeypatch.setenv(COMPILE_ENV, "0")
    apply_compile("auto")
    assert os.environ[COMPILE_ENV] == "0"
    apply_compile("on")
    assert os.environ[COMPILE_ENV] == "1"
    apply_compile("off")
    assert os.environ[COMPILE_ENV] == "0"


def test_config_modules_define_no_per_class_serialisation():
    for module in ("mmpc.solver.config", "mmpc.mpc", "mmpc.scenario", "mmpc.drivers.frenet", "mmpc.drivers.nlp", "mmpc.rl.config",
                   "mmpc.imitation.bc", "mmpc.imitation.dagger", "mmpc.imitation.features", "mmpc.imitation.policy"):
        loaded = importlib.import_module(module)
        for value in vars(loaded).values():
            if isinstance(value, type) and dataclasses.is_dataclass(value) and value.__module__ == module:
                assert not {"from_dict", "to_dict", "from_yaml"} & set(vars(value)), value


def test_require_int_names_the_value_and_the_range():
    require_int("", low=1, lockstep=1, episodes=7)
    require_int("train", low=0, high=8, neighbours=8)
    require_int("", seed=-3)  # no bound
    cases = [
        (dict(where="", low=1, lockstep=0), "`lockstep` must be an int >= 1; got 0"),
        (dict(where="train", low=0, eval_seed=-1), "train: `eval_seed` must be an int >= 0; got -1"),
        (dict(where="", low=0, high=8, neighbours=9), r"`neighbours` must be an int in \[0, 8\]; got 9"),
        (dict(where="", high=4, keep=5), "`keep` must be an int <= 4; got 5"),
        (dict(where="", seed=2.0), "`seed` must be an int; got 2.0"),
        (dict(where="", low=0, lanes=True), "`lanes` must be an int >= 0; got True"),  # a bool is not a count
        (dict(where="", low=1, episodes=3, lockstep="8"), "`lockstep` must be an int >= 1; got '8'"),
    ]
    for kwargs, message in cases:
        with pytest.raises(ConfigError, match=f"^{message}$"):
            require_int(kwargs.pop("where"), **kwargs)
