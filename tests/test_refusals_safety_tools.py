"""The safety tools tried as a hostile user would: what cannot run is refused in one line before
any folder or row, and nothing a finished run wrote is replaced."""

import json
import shutil

import pytest

from mmpc.cli.main import main
from mmpc.evaluate.store import read_episodes
from red_team import main as red_team


@pytest.mark.parametrize("argument", [["--seeds", "-5"], ["--seeds", "0", "--train-seed", "-1"]])
def test_the_red_team_refuses_negative_seeds_before_training(tmp_path, capsys, argument):
    with pytest.raises(SystemExit) as refused:
        red_team(["--driver", "mpc", "--steps", "256", *argument, "--out", str(tmp_path / "out")])
    assert refused.value.code == 2 and "must be >= 0" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_the_red_team_reads_set_into_its_scenario_and_refuses_an_unknown_key(tmp_path, capsys):
    with pytest.raises(SystemExit) as refused:
        red_team(["--driver", "mpc", "--seeds", "0", "--set", "traffic.no_such_key=1", "--out", str(tmp_path / "out")])
    assert refused.value.code == 2 and "no_such_key" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_the_red_team_refuses_a_folder_a_run_finished(tmp_path, capsys):
    out = tmp_path / "red"
    out.mkdir()
    (out / "model.zip").write_bytes(b"a trained red team")
    (out / "red_team.json").write_text('{"collisions": 0}\n')
    for extra in ([], ["--model", str(out / "model.zip")], ["--train-seed", "3"]):
        assert red_team(["--driver", "mpc", "--steps", "256", "--seeds", "0", "--episodes", "2", "--out", str(out), *extra]) == 2
        err = capsys.readouterr().err
        assert "already holds" in err and "neither resumes nor replaces" in err and err.count("\n") == 1
    assert (out / "model.zip").read_bytes() == b"a trained red team"
    assert (out / "red_team.json").read_text() == '{"collisions": 0}\n'
    assert sorted(p.name for p in out.iterdir()) == ["model.zip", "red_team.json"]


def test_the_red_team_refuses_a_missing_model_and_a_driver_it_cannot_build(tmp_path, capsys):
    for argument in (["--model", str(tmp_path / "none.zip"), "--driver", "mpc"], ["--driver", "verified:garbage"]):
        with pytest.raises(SystemExit) as refused:
            red_team([*argument, "--seeds", "0", "--out", str(tmp_path / "out")])
        assert refused.value.code == 2
    assert not (tmp_path / "out").exists()
    assert "unknown driver 'garbage'" in capsys.readouterr().err


@pytest.mark.parametrize("spec", ["verified:garbage", "verified:", "verified", "bc:NOPE/policy.pt", "proposer:NOPE"])
def test_a_driver_that_cannot_be_built_is_refused_before_any_folder(tmp_path, capsys, spec):
    evaluation = ["evaluate", "--driver", spec, "--scenarios", "cruise", "--seeds", "0-1", "--duration", "0.2", "--out",
                  str(tmp_path / "evaluation")]
    assert main(evaluation) == 2
    assert f"driver {spec!r} cannot drive scenario 'cruise'" in capsys.readouterr().err
    assert main(["drive", "--driver", spec, "--duration", "0.2", "--no-video", "--out", str(tmp_path / "drive")]) == 2
    err = capsys.readouterr().err
    assert f"driver {spec!r} cannot drive scenario 'cruise'" in err and err.count("\n") == 1
    assert not (tmp_path / "evaluation").exists() and not (tmp_path / "drive").exists()


def test_the_driver_help_shows_what_verified_takes(capsys):
    for verb in ("drive", "evaluate"):
        with pytest.raises(SystemExit):
            main([verb, "--help"])
        assert "verified:DRIVER" in " ".join(capsys.readouterr().out.split())


def test_an_evaluation_recorded_with_retired_keys_resumes_and_a_changed_one_says_what_changed(tmp_path, capsys):
    out = tmp_path / "evaluation"
    run = ["evaluate", "--scenarios", "cruise", "--duration", "0.2", "--out", str(out)]
    assert main([*run, "--seeds", "0"]) == 0
    record = json.loads((out / "scenarios.json").read_text())
    # as an mmpc before the prediction options were retired wrote it: their keys (off), another hash
    record["settings"]["cruise"]["mpc"].update(contingencies=0, passing_margin=0.0, contingency_window=1.5)
    record["scenarios"]["cruise"] = "0123456789abcdef"
    (out / "scenarios.json").write_text(json.dumps(record))
    assert main([*run, "--seeds", "0-1"]) == 0
    assert [row["seed"] for row in read_episodes(out / "episodes.csv")] == [0, 1]
    record = json.loads((out / "scenarios.json").read_text())
    record["settings"]["cruise"]["duration"] = 5.0
    record["scenarios"]["cruise"] = "0123456789abcdef"
    (out / "scenarios.json").write_text(json.dumps(record))
    capsys.readouterr()
    assert main([*run, "--seeds", "0-2"]) == 2
    assert "settings changed: duration: 5.0 then, 0.2 now" in capsys.readouterr().err


@pytest.mark.parametrize("verb", ["demos", "proposer", "dagger"])
def test_imitation_without_the_ngsim_recording_is_refused_before_any_folder(tmp_path, capsys, verb):
    assert main(["imitate", verb, "--scenario", "cruise_ngsim", "--out", str(tmp_path / "out")]) == 2
    assert "the NGSIM recording is not shipped" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_an_rl_run_whose_config_switches_a_retired_option_on_is_refused_before_any_folder(tmp_path, capsys):
    from mmpc.rl.runs import SHIPPED_MODELS

    run = tmp_path / "old_run"
    shutil.copytree(SHIPPED_MODELS / "cruise_task_ppo", run)
    config = (run / "config.yaml").read_text()
    (run / "config.yaml").write_text(config.replace("      num_obstacles: 6\n", "      num_obstacles: 6\n      contingencies: 1\n", 1))
    spec = f"sb3:{run / 'model.zip'}"
    assert main(["evaluate", "--driver", spec, "--scenarios", "cruise", "--seeds", "0", "--duration", "0.2", "--out",
                 str(tmp_path / "evaluation")]) == 2
    err = capsys.readouterr().err
    assert f"driver {spec!r} cannot drive scenario 'cruise'" in err and "no longer has" in err and err.count("\n") == 1
    assert not (tmp_path / "evaluation").exists()
