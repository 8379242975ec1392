"""Follow-ups of tracker issue 55 ("nothing misread: every bad setting refused up front"):
``mmpc evaluate`` lists every driver spec in its --help and takes ``--config`` for its scenarios
as ``drive`` does, refuses scenarios that load under one name or lack their data before it makes
its output folder, an unknown config name is one line from any verb, and compare_drivers.py
refuses two runs of one label."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from compare_drivers import main as compare
from mmpc.cli.main import build_parser, main
from mmpc.config import ConfigError
from mmpc.evaluate import EvaluationConfig, evaluate
from mmpc.scenario import ScenarioConfig, load_scenario
from tests.conftest import evaluation_folder

ROOT = Path(__file__).resolve().parents[1]


def _one_refusal(err: str, start: str) -> str:
    """The single error line of ``err`` (progress bars left out), which must start with ``start``;
    no traceback."""
    assert "Traceback" not in err, err
    lines = [line.rsplit("\r", 1)[-1].strip() for line in err.splitlines()]
    lines = [line for line in lines if line and not re.search(r"\d+/\d+ \[", line)]
    assert len(lines) == 1 and lines[0].startswith(start), lines
    return lines[0]


# ---------------------------------------------------------------- evaluate --help and --config


def test_evaluate_takes_config_as_its_scenarios(tmp_path, capsys):
    parser = build_parser()
    assert parser.parse_args(["evaluate", "--config", "high_speed,cruise"]).scenarios == "high_speed,cruise"
    assert parser.parse_args(["evaluate", "--scenarios", "cruise"]).scenarios == "cruise"
    assert parser.parse_args(["evaluate"]).scenarios == "cruise,high_speed"  # the default stays
    out = tmp_path / "out"
    assert main(["evaluate", "--config", "cruise,cruise", "--out", str(out)]) == 2  # checked as --scenarios is
    assert "--scenarios names cruise more than once" in _one_refusal(capsys.readouterr().err, "mmpc: error:")
    assert not out.exists()


# ---------------------------------------------------------------- evaluate: scenarios refused before the folder


def _scenario_file(path: Path, text: str) -> str:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return str(path)


@pytest.mark.parametrize("case", ["two files", "a file and a shipped name", "--set name"])
def test_evaluate_refuses_scenarios_of_one_loaded_name_before_making_a_folder(case, tmp_path, capsys):
    if case == "two files":
        given = [_scenario_file(tmp_path / "a" / "s.yaml", "from: cruise\n"),
                 _scenario_file(tmp_path / "b" / "s.yaml", "from: cruise\nduration: 3.0\n")]
        argv, name = ["--scenarios", ",".join(given)], "cruise"
    elif case == "a file and a shipped name":
        given = ["cruise", _scenario_file(tmp_path / "mine.yaml", "from: high_speed\nname: cruise\n")]
        argv, name = ["--scenarios", ",".join(given)], "cruise"
    else:
        argv, name = ["--scenarios", "cruise,high_speed", "--set", "name=x"], "x"
    out = tmp_path / "out"
    assert main(["evaluate", *argv, "--seeds", "0", "--duration", "0.2", "--compile", "off", "--out", str(out)]) == 2
    line = _one_refusal(capsys.readouterr().err, "mmpc evaluate: error:")
    assert "distinct names" in line and f"{name!r} more than once" in line, line
    assert argv[1] in line  # what came
    assert not out.exists()


def test_evaluate_refuses_scenarios_of_one_name_with_the_config_error(tmp_path):
    cruise = load_scenario("cruise")
    with pytest.raises(ConfigError, match=r"distinct names.*'cruise' more than once"):
        evaluate([cruise, cruise.replace(duration=1.0)], tmp_path / "out", EvaluationConfig(seeds=(0,)))
    with pytest.raises(ConfigError, match="at least one"):
        evaluate([], tmp_path / "out", EvaluationConfig(seeds=(0,)))
    assert not (tmp_path / "out").exists()


def _without_data(tmp_path: Path) -> ScenarioConfig:
    return load_scenario("cruise_ngsim", {"traffic.path": str(tmp_path / "no_recording.csv")})


def test_evaluate_refuses_a_scenario_without_its_data_before_making_a_folder(tmp_path, capsys):
    out = tmp_path / "out"
    missing = tmp_path / "no_recording.csv"
    assert main(["evaluate", "--scenarios", "cruise_ngsim", "--set", f"traffic.path={missing}", "--seeds", "0",
                 "--compile", "off", "--out", str(out)]) == 2
    line = _one_refusal(capsys.readouterr().err,
                        "mmpc evaluate: error: --scenarios cruise_ngsim: scenario 'cruise_ngsim':")
    assert str(missing) in line and "'NGSIM replay'" in line
    assert not out.exists()
    with pytest.raises(ConfigError, match="scenario 'cruise_ngsim': `traffic.path`"):  # the library refuses it too
        evaluate([_without_data(tmp_path)], out, EvaluationConfig(seeds=(0,)))
    assert not out.exists()


# ---------------------------------------------------------------- an unknown config name: one line


@pytest.mark.parametrize("argv, verb, name, shipped", [
    (["drive", "--scenario", "no_such_scenario"], "drive", "no_such_scenario", "shipped scenarios: [.*'high_speed'"),
    (["drive", "--config", "no_such_scenario"], "drive", "no_such_scenario", "shipped scenarios: [.*'high_speed'"),
    (["evaluate", "--scenarios", "cruise,no_such_scenario"], "evaluate", "no_such_scenario",
     "shipped scenarios: [.*'cruise'"),
    (["rl", "train", "--algo", "dqn", "--config", "no_such", "--timesteps", "8"], "rl train", "no_such",
     "shipped rl: [.*'smoke'"),
    (["solve", "--config", "no_such_optimizer"], "solve", "no_such_optimizer", "ships no named configs; give a YAML path"),
])
def test_an_unknown_config_name_is_one_line_naming_it_and_the_shipped_ones(argv, verb, name, shipped, tmp_path, capsys):
    out = tmp_path / "out"
    assert main([*argv, "--out", str(out)]) == 2
    line = _one_refusal(capsys.readouterr().err, f"mmpc {verb}: error: FileNotFoundError:")
    assert repr(name) in line and re.search(shipped.replace("[", r"\["), line), line
    assert not out.exists()


# ---------------------------------------------------------------- compare_drivers.py: one label, one run


def test_compare_refuses_two_runs_of_one_label(tmp_path, capsys):
    reference = evaluation_folder(tmp_path / "reference", load_scenario("cruise"), [300.0, 290.0, 310.0])
    first = evaluation_folder(tmp_path / "first", load_scenario("cruise"), [301.0, 291.0, 311.0])
    second = evaluation_folder(tmp_path / "second", load_scenario("cruise"), [250.0, 240.0, 260.0])
    for others, label in (([f"agent={first}", f"agent={second}"], "agent"),
                          ([str(first), str(second)], "mpc on cruise")):  # the default labels
        assert compare([str(reference), *others, "--out", str(tmp_path / "out")]) == 2
        captured = capsys.readouterr()
        line = _one_refusal(captured.err, "compare_drivers: error:")
        assert f"{label!r}" in line and str(first) in line and str(second) in line and "LABEL=" in line, line
        assert "|" not in captured.out and not (tmp_path / "out").exists()
    # distinct labels compare; the reference's label may be another run's (the same driver in another folder)
    assert compare([str(reference), str(first), f"worse={second}", "--metrics", "task_return"]) == 0
    printed = capsys.readouterr().out
    assert "| mpc on cruise | 3 |" in printed and "| worse | 3 |" in printed


def test_scripts_readme_names_the_compare_option_for_unlike_runs():
    row = next(line for line in (ROOT / "scripts" / "README.md").read_text().splitlines()
               if line.startswith("| `compare_drivers.py`"))
    assert "--allow-different-scenarios" in row
