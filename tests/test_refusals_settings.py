"""Refusals found by a hostile probe (issue 55): settings checked against each other and for NaN
or inf by the one config loader, the run's device and --threads checked before any work, every
refusal one line on stderr (an --out that cannot be written included) while a bug keeps its
traceback, SDL's XDG_RUNTIME_DIR noise gone from a drive, the NGSIM scenario refused before it
makes a folder, the driver specs in --help, and a README whose commands parse."""

from __future__ import annotations

import math
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml

from mmpc.cli import solve as solve_module
from mmpc.cli.arguments import THREADS_PER_CPU, max_threads
from mmpc.cli.main import build_parser, main, refused
from mmpc.config import ConfigError, load_config
from mmpc.device import DEVICE_ENV
from mmpc.drivers import registry
from mmpc.imitation.bc import TrainConfig as BCTrainConfig
from mmpc.scenario import EgoConfig, load_scenario
from mmpc.traffic_config import IDMTraffic

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


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
    ("cruise", {"mpc.tie_margin": math.nan}, "mpc.tie_margin", "nan"),
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
    (["drive", "--set", "mpc.tie_margin=.nan"], "drive", "mpc.tie_margin"),
    (["imitate", "bc", "--dataset", "no-such-dataset", "--set", "weight_decay=.inf"], "imitate bc", "weight_decay"),
])
def test_set_refuses_a_non_finite_value_in_one_line(argv, verb, key, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(argv if verb == "config show" else [*argv, "--out", str(out)]) == 2
    line = _one_refusal(capsys.readouterr().err, f"mmpc {verb}: error:")
    assert re.search(rf"`{re.escape(key)}` must be finite; got (inf|nan)$", line), line
    assert not out.exists()


# ---------------------------------------------------------------- item 8: the device from the environment


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal of cuda on a machine without it")
def test_mmpc_device_cuda_without_a_gpu_is_refused_before_any_work(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv(DEVICE_ENV, "cuda")
    out = tmp_path / "out"
    argv = ["evaluate", "--scenarios", "cruise", "--seeds", "0", "--duration", "0.2", "--compile", "off", "--out", str(out)]
    assert main(argv) == 2
    line = _one_refusal(capsys.readouterr().err, f"mmpc: error: {DEVICE_ENV}:")
    assert "cannot use" in line
    assert not out.exists()  # no episodes.csv of error rows, no "run again to retry"


def test_mmpc_device_garbage_is_one_line(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv(DEVICE_ENV, "garbage")
    out = tmp_path / "out"
    assert main(["drive", "--duration", "0.2", "--out", str(out)]) == 2
    line = _one_refusal(capsys.readouterr().err, f"mmpc: error: {DEVICE_ENV}:")
    assert "'garbage'" in line
    assert not out.exists()


def test_a_verb_that_computes_nowhere_ignores_the_device_variable(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv(DEVICE_ENV, "garbage")
    assert main(["config", "show", "optimizer"]) == 0


# ---------------------------------------------------------------- item 9: --threads bounded


@pytest.mark.parametrize("threads", ["0", "-3", str(max_threads() + 1), "1000", "100000"])
def test_threads_outside_the_bound_are_refused_naming_it(threads, capsys):
    # scenarios that do not exist: the old code went on to set the threads and failed later
    assert main(["evaluate", "--threads", threads, "--scenarios", "no-such-scenario"]) == 2
    line = _one_refusal(capsys.readouterr().err, "mmpc: error: --threads")
    assert f"[1, {max_threads()}]" in line and f"{THREADS_PER_CPU} per CPU" in line and line.endswith(f"got {threads}")


def test_threads_up_to_the_bound_pass(capsys):
    for verb in (["drive"], ["evaluate"], ["imitate", "demos"]):
        assert refused(build_parser().parse_args([*verb, "--threads", str(max_threads())])) is None
        assert refused(build_parser().parse_args([*verb, "--threads", str(max_threads() + 1)])) is not None
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    assert max_threads() == THREADS_PER_CPU * cpus


# ---------------------------------------------------------------- item 16: one line, not a traceback


@pytest.fixture(scope="module")
def demos(tmp_path_factory) -> Path:
    """A demonstrations folder of one short episode (for imitate bc)."""
    out = tmp_path_factory.mktemp("demos")
    assert main(["imitate", "demos", "--episodes", "1", "--duration", "0.3", "--compile", "off", "--out", str(out)]) == 0
    return out


UNWRITABLE_OUT = {
    "solve": ["solve"],
    "evaluate": ["evaluate", "--scenarios", "cruise", "--seeds", "0", "--duration", "0.2", "--compile", "off"],
    "rl train": ["rl", "train", "--algo", "dqn", "--config", "smoke", "--timesteps", "10", "--no-eval"],
    "rl report": ["rl", "report", "a=no-such-run"],
    "imitate demos": ["imitate", "demos", "--episodes", "1", "--duration", "0.2", "--compile", "off"],
    "imitate bc": ["imitate", "bc", "--set", "epochs=1"],
    "imitate dagger": ["imitate", "dagger", "--iterations", "0", "--duration", "0.2", "--compile", "off"],
    "imitate proposer": ["imitate", "proposer", "--rounds", "0", "--duration", "0.2", "--compile", "off"],
    "imitate export": ["imitate", "export", "--policy", "no-such-policy.pt"],
}


@pytest.mark.parametrize("verb", sorted(UNWRITABLE_OUT))
def test_an_out_folder_that_cannot_be_made_is_one_line(verb, tmp_path, capsys, request):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder\n")  # a path under a regular file: refused even to root
    argv = list(UNWRITABLE_OUT[verb])
    if verb == "imitate bc":
        argv += ["--dataset", str(request.getfixturevalue("demos"))]
    out = blocker / "out" / ("policy.zip" if verb == "imitate export" else "")
    assert main([*argv, "--out", str(out)]) == 2
    line = _one_refusal(capsys.readouterr().err, f"mmpc {verb}: error:")
    assert "NotADirectoryError" in line and str(blocker) in line
    assert blocker.read_text() == "not a folder\n"


def test_repeated_scenarios_are_one_line_before_any_folder(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["evaluate", "--scenarios", "cruise,cruise", "--seeds", "0", "--out", str(out)]) == 2
    assert "--scenarios names cruise more than once" in _one_refusal(capsys.readouterr().err, "mmpc: error:")
    assert main(["drive", "--scenario", "high_speed,cruise,high_speed", "--seeds", "0", "--out", str(out)]) == 2
    assert "--scenario names high_speed more than once" in _one_refusal(capsys.readouterr().err, "mmpc: error:")
    # distinct files, one name: refused by the loaded names
    assert main(["drive", "--scenario", "cruise,high_speed", "--seeds", "0", "--set", "name=same", "--out", str(out)]) == 2
    assert "distinct names" in _one_refusal(capsys.readouterr().err, "mmpc drive: error:")
    assert not out.exists()


def test_a_bug_keeps_its_traceback(monkeypatch, tmp_path):
    def broken(args):
        raise ValueError("a bug, not a refusal")

    monkeypatch.setattr(solve_module, "run", broken)
    with pytest.raises(ValueError, match="a bug, not a refusal"):
        main(["solve", "--out", str(tmp_path)])


# ---------------------------------------------------------------- item 17: no SDL noise from a drive


def test_drive_with_a_video_prints_no_sdl_error(tmp_path):
    env = {key: value for key, value in os.environ.items() if key not in ("XDG_RUNTIME_DIR", "SDL_VIDEODRIVER")}
    done = subprocess.run([sys.executable, "-m", "mmpc.cli", "drive", "--duration", "0.2", "--compile", "off",
                           "--threads", "1", "--out", str(tmp_path)], env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert "XDG_RUNTIME_DIR" not in done.stderr and "error:" not in done.stderr.lower(), done.stderr
    assert (tmp_path / "episode.mp4").stat().st_size > 0


# ---------------------------------------------------------------- item 18: config spellings


def test_drive_takes_config_as_the_scenario():
    parser = build_parser()
    assert parser.parse_args(["drive", "--config", "high_speed"]).scenario == "high_speed"
    assert parser.parse_args(["drive", "--scenario", "high_speed"]).scenario == "high_speed"


def _readme_commands() -> list[str]:
    """Every ``mmpc ...`` line of the README's bash blocks (continuations joined, comments cut)."""
    commands = []
    for block in re.findall(r"```bash\n(.*?)```", README.read_text(encoding="utf-8"), flags=re.S):
        for line in block.replace("\\\n", " ").splitlines():
            for part in line.split("#", 1)[0].split("&&"):
                if part.strip().startswith("mmpc "):
                    commands.append(part.strip())
    return commands


def test_every_mmpc_command_of_the_readme_parses():
    commands = _readme_commands()
    assert len(commands) >= 8
    for command in commands:
        try:
            build_parser().parse_args(shlex.split(command)[1:])
        except SystemExit as error:
            raise AssertionError(f"README command does not parse: {command}") from error


# ---------------------------------------------------------------- item 19: NGSIM data not shipped


@pytest.mark.skipif(Path(load_scenario("cruise_ngsim").traffic.path).is_file(), reason="the NGSIM recording is here")
def test_the_ngsim_scenario_without_its_data_is_refused_before_making_a_folder(tmp_path, capsys):
    out = tmp_path / "ngsim"
    assert main(["drive", "--scenario", "cruise_ngsim", "--out", str(out)]) == 2
    line = _one_refusal(capsys.readouterr().err, "mmpc drive: error: scenario 'cruise_ngsim':")
    assert "'NGSIM replay'" in line and load_scenario("cruise_ngsim").traffic.path in line
    assert not out.exists()
    assert main(["config", "show", "scenario"]) == 0
    shown = capsys.readouterr().out
    assert "cruise_ngsim (needs data)" in shown and "cruise (needs data)" not in shown


def test_the_readme_says_where_the_ngsim_data_comes_from_and_goes():
    text = README.read_text(encoding="utf-8")
    section = text[text.index("NGSIM replay"):]
    section = section[:section.index("\n\n")]
    assert "data.transportation.gov" in section and "Next Generation Simulation (NGSIM) Vehicle Trajectories" in section
    assert "US-101" in section and load_scenario("cruise_ngsim").traffic.path in section


# ---------------------------------------------------------------- item 20: every driver spec in --help


@pytest.mark.parametrize("verb", ["drive", "evaluate"])
def test_the_help_of_a_driving_verb_lists_every_driver_spec(verb, monkeypatch, capsys):
    monkeypatch.setitem(registry._registered, "probe-driver", lambda scenario, argument: None)
    monkeypatch.setenv("COLUMNS", "2000")  # argparse wraps the help at hyphens otherwise
    with pytest.raises(SystemExit):
        build_parser().parse_args([verb, "--help"])
    text = capsys.readouterr().out
    for name in registry.driver_names():
        assert name in text, name
    assert "probe-driver" in text  # generated from the registry, not written out
    for form in ("proposer:RUN/proposer.pt", "safe-expert[:RL_CONFIG]", "safe-random[:RL_CONFIG]", "sb3:RUN/model.zip",
                 "bc:RUN/policy.pt", "batch-nlp[:B]"):
        assert form in text, form


# ---------------------------------------------------------------- items 22, 23: README


def test_readme_keeps_its_two_commands_says_how_to_get_cpu_torch_and_stays_short():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= 300
    assert lines[3].startswith("pip install torch==2.13.0 -e . && mmpc drive ")
    assert lines[4].startswith('pip install torch==2.13.0 -e ".[test]" && python -m pytest ')
    assert any("pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu" in line for line in lines[5:12])
    text = "\n".join(lines)
    assert "about 23 s on an idle 2-core machine" in text and "about 6 minutes on an idle 2-core machine" in text


def test_retired_prediction_options_are_dropped_when_off_and_refused_when_on(caplog):
    """Files written before 2026-11-28 spell out the retired MPC options (the shipped agents' configs did)."""
    from mmpc.config import from_dict, to_dict
    from mmpc.scenario import ScenarioConfig

    scenario = load_scenario("high_speed")
    written = to_dict(scenario, complete=True)
    written["mpc"].update(contingencies=0, contingency_window=4.0, contingency_trigger="incentive", passing_margin=0.0,
                          max_passing_margin=1.0, closing_margin=0.0, max_closing_margin=4.0, evasive_horizon=0.0)
    with caplog.at_level("WARNING", logger="mmpc.mpc"):
        assert from_dict(ScenarioConfig, written) == scenario
    assert "retired MPC option key(s)" in caplog.text and "evasive_horizon" in caplog.text
    written["mpc"]["passing_margin"] = 0.5
    with pytest.raises(ValueError, match=r"\{'passing_margin': 0.5\} switch on prediction options"):
        from_dict(ScenarioConfig, written)
