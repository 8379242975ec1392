"""Refusals and leftovers of the evaluation tools (tracker issue 55): compare_drivers.py pairs
only runs of one scenario and seeds, a resumed evaluation refuses a driver whose files changed,
bench_solver.py refuses unknown variants and repeats before any work, and an evaluation leaves
files of the usual mode, no lock file and no error bar below a bound."""

import json
import os
import stat
from pathlib import Path

import matplotlib
import pytest
import torch

import bench_solver
import mmpc.files as files
from compare_drivers import main as compare
from mmpc.cli.main import main
from mmpc.drivers import Decision, Driver, Observation, registry
from mmpc.evaluate import COLUMNS, EvaluationConfig, EvaluationFolderError, evaluate, read_episodes
from mmpc.evaluate.report import COMPARED, plot_comparison, summarize
from mmpc.drivers import driver_files
from mmpc.files import atomic_write_text, exclusive
from mmpc.scenario import load_scenario
from tests.conftest import evaluation_folder, lock_is_free

# ------------------------------------------------------------------- compare_drivers.py (item 2)


def test_compare_refuses_runs_of_other_scenario_settings_unless_told(tmp_path, capsys):
    cruise = load_scenario("cruise")
    long = evaluation_folder(tmp_path / "long", cruise.replace(duration=3.0), [300.0, 290.0, 310.0])
    short = evaluation_folder(tmp_path / "short", cruise.replace(duration=1.0), [100.0, 98.0, 103.0])
    assert compare([str(long), str(short)]) == 2
    captured = capsys.readouterr()
    assert "duration: 3.0 vs 1.0" in captured.err and "--allow-different-scenarios" in captured.err
    assert "|" not in captured.out  # no table
    assert compare([str(long), str(short), "--allow-different-scenarios", "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "mpc on cruise: scenario differs from the reference's: duration: 3.0 vs 1.0" in printed
    written = json.loads((tmp_path / "compare_drivers.json").read_text())
    assert written["scenario_differences"] == {"mpc on cruise": ["duration: 3.0 vs 1.0"]}
    # the same settings under another name pair; a folder without scenarios.json cannot be checked
    renamed = evaluation_folder(tmp_path / "renamed", cruise.replace(duration=3.0, name="cruise_again"), [301.0, 291.0, 311.0])
    assert compare([str(long), str(renamed), "--metrics", "task_return"]) == 0
    assert "| mpc on cruise_again | 3 | 0 (0) | +1 ± 0 (+0.3%) |" in capsys.readouterr().out
    (renamed / "scenarios.json").unlink()
    assert compare([str(long), str(renamed)]) == 2
    assert "does not record scenario 'cruise_again'" in capsys.readouterr().err


def test_compare_refuses_no_common_seed_and_unknown_or_no_metrics(tmp_path, capsys):
    cruise = load_scenario("cruise")
    first = evaluation_folder(tmp_path / "first", cruise, [300.0, 290.0, 310.0])
    later = evaluation_folder(tmp_path / "later", cruise, [300.0, 290.0, 310.0], seeds=[10, 11, 12])
    assert compare([str(first), str(later)]) == 2
    err = capsys.readouterr().err
    assert "finished no seed in common (3 finished seeds 10-12 against 3 finished seeds 0-2)" in err
    same = evaluation_folder(tmp_path / "same", cruise, [301.0, 291.0, 311.0])
    for metrics, unknown in (("task_retrun", "'task_retrun'"), ("task_return,collision_part", "'collision_part'")):
        assert compare([str(first), str(same), "--metrics", metrics]) == 2
        err = capsys.readouterr().err
        assert err.startswith("compare_drivers: error: --metrics: the metrics must be one or more of the number columns")
        assert f"of which {unknown} not" in err and err.count("\n") == 1
    assert compare([str(first), str(same), "--metrics", ""]) == 2
    assert "--metrics: the metrics must be one or more of the number columns of episodes.csv" in capsys.readouterr().err
    assert compare([str(first), str(same), "--metrics", ","]) == 2


# ------------------------------------------------------------ driver files on resume (item 3)


class Coast(Driver):
    """No acceleration, no steering."""

    name = "coast"
    decisions = 0  # decide calls: an evaluation that ran no episode made none (building is its first check)

    def decide(self, observation: Observation) -> Decision:
        Coast.decisions += 1
        zeros = torch.zeros(observation.num_envs, dtype=observation.ego.dtype)
        return Decision.command_only(zeros, zeros, solve_ms=0.1)


def _coast(scenario, argument):
    return Coast()


@pytest.fixture
def coast(monkeypatch):
    monkeypatch.setitem(registry._registered, "coast", _coast)
    Coast.decisions = 0


@pytest.mark.usefixtures("one_thread", "coast")
def test_resume_refuses_a_driver_whose_file_changed(tmp_path, capsys):
    checkpoint = tmp_path / "policy.pt"
    checkpoint.write_bytes(b"first weights")
    spec = f"coast:{checkpoint}"
    out = tmp_path / "evaluation"
    scenario = load_scenario("cruise").replace(duration=0.3)
    evaluate([scenario], out, EvaluationConfig(drivers=(spec,), seeds=(0,), report=False))
    driven = Coast.decisions
    assert driven > 0
    checkpoint.write_bytes(b"other weights")  # retrained into the same path
    with pytest.raises(EvaluationFolderError, match=f"episodes of driver '{spec}' run with other contents of its "
                                                    f"file\\(s\\) {checkpoint}"):
        evaluate([scenario], out, EvaluationConfig(drivers=(spec,), seeds=(0, 1), report=False))
    cli = ["evaluate", "--driver", spec, "--scenarios", "cruise", "--duration", "0.3", "--seeds", "0-1", "--lockstep", "1",
           "--out", str(out)]
    assert main(cli) == 2
    assert f"mmpc evaluate: error: {out} holds episodes of driver '{spec}'" in capsys.readouterr().err
    assert Coast.decisions == driven and len(read_episodes(out / "episodes.csv")) == 1  # nothing ran with the new file
    checkpoint.write_bytes(b"first weights")  # the file the episodes were run with: resumed
    evaluate([scenario], out, EvaluationConfig(drivers=(spec,), seeds=(0, 1), report=False))
    assert Coast.decisions == 2 * driven and [r["seed"] for r in read_episodes(out / "episodes.csv")] == [0, 1]


def test_shipped_driver_names_are_fingerprinted_by_their_files(tmp_path):
    from mmpc.imitation.proposer_driver import SHIPPED_PROPOSERS
    from mmpc.rl.runs import SHIPPED_MODELS

    assert driver_files("proposer:cruise") == (SHIPPED_PROPOSERS / "cruise.pt",)
    assert driver_files("sb3:high_speed_ppo") == tuple(sorted((SHIPPED_MODELS / "high_speed_ppo").iterdir()))
    assert driver_files("mpc") == () and driver_files("proposer:no_such_model") == ()
    # a folder whose proposer:cruise episodes were run with another shipped file is refused before any episode
    (tmp_path / "scenarios.json").write_text(json.dumps({"format": 2, "scenarios": {}, "drivers": {"proposer:cruise": "0" * 16}}))
    with pytest.raises(EvaluationFolderError, match="driver 'proposer:cruise' .*cruise.pt"):
        evaluate([load_scenario("cruise")], tmp_path, EvaluationConfig(drivers=("proposer:cruise",), seeds=(0,)))
    assert not (tmp_path / "episodes.csv").exists()


# -------------------------------------------------------------------- bench_solver.py (item 14)


@pytest.mark.parametrize("arguments, named", [
    (["--variants", "eager,compile"], "'compile'"),
    (["--variants", "eager-turnd"], "'eager-turnd'"),
    (["--variants", "compiled-warm10-warm5"], "'compiled-warm10-warm5'"),
    (["--repeats", "0"], "`repeats` must be an int >= 1; got 0"),
    (["--devices", "gpu"], "`devices` must be 'cpu' and/or 'cuda'"),
])
def test_bench_solver_refuses_unknown_variants_and_repeats_before_any_work(tmp_path, monkeypatch, capsys, arguments, named):
    def no_work(*args, **kwargs):
        raise AssertionError("the benchmark ran")

    monkeypatch.setattr(bench_solver, "run", no_work)
    with pytest.raises(SystemExit) as exited:
        bench_solver.main(["--devices", "cpu", *arguments, "--out", str(tmp_path)])
    assert exited.value.code == 2
    err = capsys.readouterr().err
    assert named in err
    if "--variants" in arguments:
        assert "expected 'eager' or 'compiled', then optionally each at most once '-turned', '-warmK'" in err
    assert not any(tmp_path.iterdir())


def test_bench_spec_takes_known_variants_and_refuses_others():
    spec = bench_solver.SolverBenchmark(variants=("eager", "compiled-turned-warm10-exit10.30"))
    assert spec.variants[1] == "compiled-turned-warm10-exit10.30"
    for variants in (("compile",), ("eager", "eager"), ()):
        with pytest.raises(ValueError, match="variant"):
            bench_solver.SolverBenchmark(variants=variants)


# ------------------------------------------------- outputs: modes, lock file, error bars (item 21)


@pytest.fixture
def umask_022():
    previous = os.umask(0o022)
    yield
    os.umask(previous)


@pytest.mark.usefixtures("one_thread", "coast", "umask_022")
def test_evaluation_files_get_the_usual_mode_and_no_lock_file_stays(tmp_path):
    scenario = load_scenario("cruise").replace(duration=0.3)
    config = EvaluationConfig(drivers=("coast",), seeds=(0, 1))
    evaluate([scenario], tmp_path, config)
    for name in ("episodes.csv", "summary.json", "scenarios.json", "summary.md", "compare.png"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o644, name
    assert not (tmp_path / ".evaluate.lock").exists()
    with pytest.raises(EvaluationFolderError, match="another scenario named 'cruise'"):  # raised holding the lock
        evaluate([scenario.replace(duration=0.2)], tmp_path, config)
    assert not (tmp_path / ".evaluate.lock").exists()


def test_atomic_write_gives_the_mode_open_would(tmp_path):
    previous = os.umask(0o027)
    try:
        atomic_write_text(tmp_path / "new.json", "{}")
        with open(tmp_path / "plain.json", "w") as handle:
            handle.write("{}")
        assert stat.S_IMODE((tmp_path / "new.json").stat().st_mode) == 0o640
        assert stat.S_IMODE((tmp_path / "plain.json").stat().st_mode) == 0o640
        os.chmod(tmp_path / "new.json", 0o604)  # an existing file keeps its mode, as with open(path, "w")
        atomic_write_text(tmp_path / "new.json", "[]")
        assert stat.S_IMODE((tmp_path / "new.json").stat().st_mode) == 0o604
        assert (tmp_path / "new.json").read_text() == "[]"
    finally:
        os.umask(previous)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["new.json", "plain.json"]  # no temporary file left


def test_a_removed_lock_file_still_keeps_a_second_writer_out(tmp_path, monkeypatch):
    path = tmp_path / ".test.lock"
    with exclusive(tmp_path, ".test.lock", "a first run", remove=True):
        with pytest.raises(RuntimeError, match="a first run is writing to"):
            with exclusive(tmp_path, ".test.lock", "a first run", remove=True):
                pass
        assert path.exists()  # a refused writer leaves the holder's file alone
    assert not path.exists()
    # a writer that opened the lock file just before the holder removed it locks a file no longer there:
    # it must take the lock of the file there now, or a third writer would get in beside it
    stale = tmp_path / "stale"
    stale.write_text("")
    opened = []

    def open_stale_first(name, mode="r", *args, **kwargs):
        opened.append(name)
        if len(opened) == 1:
            handle = open(stale, mode, *args, **kwargs)
            stale.unlink()  # removed by the holder that was finishing
            return handle
        return open(name, mode, *args, **kwargs)

    monkeypatch.setattr(files, "open", open_stale_first, raising=False)
    with exclusive(tmp_path, ".test.lock", "a second run", remove=True):
        assert opened == [path, path]
        assert not lock_is_free(path)
    assert not path.exists()


def test_compare_plot_draws_no_error_bar_below_zero_for_a_non_negative_metric(tmp_path, monkeypatch):
    rows = [{column: 0.0 for column in COLUMNS} | {"driver": "mpc", "scenario": "cruise", "seed": seed, "status": "ok",
                                                   "collisions": 0, "offroad": 0, "collision_part": None,
                                                   "meta_cost_mean": cost, "mean_speed": speed}
            for seed, cost, speed in ((0, 0.1, 14.0), (1, 2.0, 15.0))]
    summary = summarize(rows)
    assert summary[0]["meta_cost_mean_ci"][0] < 0  # two episodes: the t interval reaches below zero
    bars = []
    original = matplotlib.axes.Axes.bar

    def recording_bar(self, xs, heights, *args, yerr=None, **kwargs):
        bars.append((list(heights), [list(side) for side in yerr]))
        return original(self, xs, heights, *args, yerr=yerr, **kwargs)

    monkeypatch.setattr(matplotlib.axes.Axes, "bar", recording_bar)
    plot_comparison(summary, tmp_path / "compare.png")
    panels = dict(zip((key for key, _ in COMPARED), bars))
    [cost], ([below], [above]) = panels["meta_cost_mean"]
    assert cost - below == 0.0 and cost + above == pytest.approx(summary[0]["meta_cost_mean_ci"][1])
    [speed], ([below], _) = panels["mean_speed"]  # a speed has no such bound: its interval as it is
    assert speed - below == pytest.approx(summary[0]["mean_speed_ci"][0])


def test_a_driver_says_which_files_it_reads(tmp_path):
    """Each driver factory names its own files (mmpc.drivers.driver_files): a run's model with the
    config beside it, an RL config of the safe stand-ins, a checkpoint given by path."""
    from mmpc.rl.runs import SHIPPED_MODELS

    assert driver_files("safe-expert:cruise_task")[0].name == "cruise_task.yaml"
    assert driver_files("safe-expert") == () and driver_files("safe-random:no_such_config") == ()
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    for name in ("config.yaml", "checkpoints/model_100.zip"):
        (run / name).write_bytes((SHIPPED_MODELS / "high_speed_ppo" / Path(name).name.replace("model_100", "model")).read_bytes())
    assert driver_files(f"sb3:{run / 'checkpoints' / 'model_100.zip'}") == (run / "checkpoints" / "model_100.zip",
                                                                            run / "config.yaml")
    policy = tmp_path / "policy.pt"
    policy.write_bytes(b"weights")
    assert driver_files(f"bc:{policy}") == (policy,) and driver_files(f"bc:{tmp_path / 'none.pt'}") == ()
