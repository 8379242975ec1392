"""Inputs refused before any work (tracker issue 24): the demonstrations directory's lock, empty
config files, an unwritable ``mmpc drive --out``, a damaged evaluation folder on resume, a
resume with another ``--lockstep`` (allowed), and the safe RL environments' actions."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from mmpc.cli.main import main
from mmpc.config import load_config, to_dict
from mmpc.drivers import Decision, Driver, Observation, registry
from mmpc.problem import EGO_V, EGO_Y
from mmpc.scenario import load_scenario
from tests.conftest import hold_lock, lock_is_free

DEMOS_LOCK = ".demos.lock"


# ----------------------------------------------------------------------------------- mmpc demos


def _no_driving(*args, **kwargs):
    raise AssertionError("an episode was driven")


@pytest.mark.parametrize("existing", [False, True], ids=["new-folder", "earlier-run"])
def test_demos_refuses_a_folder_another_run_holds(tmp_path, monkeypatch, capsys, existing):
    import mmpc.imitation.demos as demos
    from mmpc.imitation.dataset import MANIFEST, Manifest, package_versions

    monkeypatch.setattr(demos, "drive_group", _no_driving)
    out = tmp_path / "demos"
    out.mkdir()
    scenario = load_scenario("cruise").replace(duration=0.5)
    if existing:  # a demonstrations directory of this very configuration, being resumed by another run
        (out / MANIFEST).write_text(Manifest(to_dict(scenario), 4, package_versions()).to_json())
    holder = hold_lock(out / DEMOS_LOCK)
    try:
        code = main(["imitate", "demos", "--scenario", "cruise", "--duration", "0.5", "--episodes", "2", "--out", str(out)])
    finally:
        holder.close()
    err = capsys.readouterr().err
    assert code == 2, err
    assert f"another `mmpc imitate demos` run is writing to {out}" in err and str(out / DEMOS_LOCK) in err


def test_demos_holds_its_lock_while_driving_and_releases_it_after_a_run_and_after_an_error(tmp_path, monkeypatch):
    import mmpc.imitation.demos as demos

    out = tmp_path / "demos"
    scenario = load_scenario("cruise").replace(duration=0.5)
    held_while_driving = []

    def fake_group(task):
        held_while_driving.append(not lock_is_free(out / DEMOS_LOCK))
        return list(task.missing)  # nothing staged: the dataset step is faked below

    monkeypatch.setattr(demos, "drive_group", fake_group)
    monkeypatch.setattr(demos, "built_seeds", lambda root, identifier: [0, 1])  # "already built"
    report = demos.generate_demonstrations(scenario, [0, 1], out, lockstep=2)
    assert report.generated == [0, 1] and not report.rebuilt
    assert held_while_driving == [True]
    assert (out / DEMOS_LOCK).exists() and lock_is_free(out / DEMOS_LOCK)

    def failing_group(task):
        raise RuntimeError("solver exploded")

    monkeypatch.setattr(demos, "drive_group", failing_group)
    with pytest.raises(RuntimeError, match="solver exploded"):
        demos.generate_demonstrations(scenario, [0, 1], out, lockstep=2)
    assert lock_is_free(out / DEMOS_LOCK)
    foreign = tmp_path / "foreign"  # a foreign folder is refused without a lock file left in it
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    with pytest.raises(RuntimeError, match="not an mmpc demonstrations directory"):
        demos.generate_demonstrations(scenario, [0, 1], foreign, lockstep=2)
    assert [p.name for p in foreign.iterdir()] == ["notes.txt"]


# ----------------------------------------------------------------------------------- config files


@pytest.mark.parametrize("text", ["", "# settings to come\n"], ids=["empty", "comments-only"])
def test_an_empty_config_file_is_an_error_naming_it(tmp_path, text):
    from mmpc.imitation.bc import TrainConfig
    from mmpc.rl.config import RLConfig

    path = tmp_path / "empty.yaml"
    path.write_text(text)
    with pytest.raises(ValueError, match=re.escape(f"ScenarioConfig file {path} is empty")):
        load_scenario(str(path))  # was the defaults of ScenarioConfig (cruise)
    with pytest.raises(ValueError, match=re.escape(f"RLConfig file {path} is empty")):
        load_config(RLConfig, path)
    with pytest.raises(ValueError, match=re.escape(f"TrainConfig file {path} is empty")):
        load_config(TrainConfig, path)


def test_a_config_file_that_is_not_a_mapping_is_an_error_naming_it(tmp_path):
    path = tmp_path / "list.yaml"
    path.write_text("- duration: 5\n")
    with pytest.raises(ValueError, match=re.escape(f"ScenarioConfig file {path} must hold a mapping") + ".*got a list"):
        load_scenario(str(path))
    path.write_text("0\n")  # was read as {} (the defaults)
    with pytest.raises(ValueError, match=re.escape(f"ScenarioConfig file {path} must hold a mapping") + ".*got a int"):
        load_scenario(str(path))


# ----------------------------------------------------------------------------------- mmpc drive --out


@pytest.mark.parametrize("seeds", [None, "0-1"], ids=["one-episode", "seeds"])
def test_drive_refuses_an_unwritable_out_before_driving(tmp_path, monkeypatch, capsys, seeds):
    import mmpc.highway.runner
    import mmpc.drivers
    import mmpc.evaluate

    for module, name in ((mmpc.drivers, "make_driver"), (mmpc.highway.runner, "run_episode"), (mmpc.evaluate, "evaluate")):
        monkeypatch.setattr(module, name, _no_driving)
    (tmp_path / "file.txt").write_text("a file, not a folder")
    out = tmp_path / "file.txt" / "out"  # fails even as root
    argv = ["drive", "--duration", "0.5", "--no-video", "--out", str(out)] + (["--seeds", seeds] if seeds else [])
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"--out {out} must be a folder this process can create and write to" in err and "NotADirectoryError" in err


# ----------------------------------------------------------------------------------- mmpc evaluate


class KeepLane(Driver):
    """Holds its start lane at 14 m/s; counts the episodes it starts (one driver per group)."""

    name = "keep-lane"
    episodes_started = 0

    def reset(self, num_envs):
        KeepLane.episodes_started += num_envs
        self.lane_y = None

    def decide(self, observation: Observation) -> Decision:
        ego = observation.ego
        if self.lane_y is None:
            self.lane_y = torch.round(ego[:, EGO_Y] / 4.0) * 4.0
        steering = (-0.02 * (ego[:, EGO_Y] - self.lane_y[observation.ids()])).clamp(-0.05, 0.05)
        return Decision.command_only(0.8 * (14.0 - ego[:, EGO_V]), steering, solve_ms=0.1)


@pytest.fixture
def keep_lane(monkeypatch, one_thread):
    monkeypatch.setitem(registry._registered, "keep-lane", lambda scenario, argument: KeepLane())
    KeepLane.episodes_started = 0


def _evaluation(tmp_path: Path, seeds=(0, 1), lockstep: int = 1):
    from mmpc.evaluate import EvaluationConfig, evaluate

    config = EvaluationConfig(drivers=("keep-lane",), seeds=tuple(seeds), lockstep=lockstep, report=False)
    return evaluate([load_scenario("cruise").replace(duration=0.5)], tmp_path, config)


def _evaluate_cli(out: Path) -> list[str]:
    return ["evaluate", "--driver", "keep-lane", "--scenarios", "cruise", "--seeds", "0-1", "--duration", "0.5",
            "--lockstep", "1", "--out", str(out)]


@pytest.mark.usefixtures("keep_lane")
def test_evaluate_resume_refuses_a_damaged_episodes_csv_naming_file_and_line(tmp_path, capsys):
    from mmpc.evaluate import read_episodes

    _evaluation(tmp_path)
    path = tmp_path / "episodes.csv"
    good = path.read_text()
    header, first, second = (line.split(",") for line in good.splitlines())
    count = len(header)

    def lines(*rows):
        return "".join(",".join(row) + "\n" for row in (header, *rows))

    def changed(row, column, value):
        return [value if name == column else field for name, field in zip(header, row)]

    damaged = {
        "one field too many": (lines(first, second + ["7"]), rf"line 3: {count + 1} fields, expected {count} \(the header's\)"),
        "a field missing": (lines(first[:-1], second), rf"line 2: {count - 1} fields, expected {count}"),
        "a word for a number": (lines(first, changed(second, "duration", "fast")),
                                r"line 3: `duration` is 'fast', expected a number"),
        "a float for an int": (lines(changed(first, "group", "0.5"), second), r"line 2: `group` is '0.5', expected an integer"),
        "no status": (lines(changed(first, "status", ""), second),
                      r"line 2: expected a driver, a scenario, a seed and status ok or error; .*status=''"),
    }
    for name, (text, message) in damaged.items():
        path.write_text(text)
        with pytest.raises(ValueError, match=re.escape(f"{path}, ") + message):
            read_episodes(path)
        with pytest.raises(ValueError, match=re.escape(f"{path}, ") + message):
            _evaluation(tmp_path)
        assert main(_evaluate_cli(tmp_path)) == 2, name
        assert f"mmpc evaluate: error: {path}, line" in capsys.readouterr().err
    path.write_bytes(good.encode() + b"mpc,\xff\n")  # garbage, as a crash can leave
    with pytest.raises(ValueError, match=re.escape(f"{path}, line 4: not UTF-8 text")):
        read_episodes(path)
    path.write_text(good)
    assert main(_evaluate_cli(tmp_path)) == 0 and KeepLane.episodes_started == 2  # nothing ran again


@pytest.mark.usefixtures("keep_lane")
@pytest.mark.parametrize("text, message", [("{\"cruise\": \"ab", r"is corrupt \(Unterminated string .*line 1 column 12"),
                                           ("[1, 2]", r"is corrupt: expected a JSON object")], ids=["cut-short", "a-list"])
def test_evaluate_resume_refuses_a_damaged_scenarios_json_naming_it(tmp_path, capsys, text, message):
    _evaluation(tmp_path)
    path = tmp_path / "scenarios.json"
    path.write_text(text)
    with pytest.raises(ValueError, match=re.escape(f"{path} ") + message):
        _evaluation(tmp_path)
    assert main(_evaluate_cli(tmp_path)) == 2
    assert f"mmpc evaluate: error: {path} is corrupt" in capsys.readouterr().err
    assert path.read_text() == text  # left for the user to look at


@pytest.mark.usefixtures("keep_lane")
def test_evaluate_resume_of_a_folder_of_an_earlier_mmpc_says_why_it_is_refused(tmp_path):
    _evaluation(tmp_path)
    path = tmp_path / "scenarios.json"
    assert json.loads(path.read_text())["format"] == 2
    path.write_text(json.dumps({"cruise": "0123456789abcdef"}))  # an earlier mmpc's hash (compile, wheelbase)
    with pytest.raises(ValueError, match=r"written by an earlier mmpc .*mpc.compile, mpc.wheelbase.*delete .*scenarios.json"):
        _evaluation(tmp_path)
    path.write_text(json.dumps({"format": 2, "scenarios": {"cruise": "0123456789abcdef"}}))
    with pytest.raises(ValueError, match="holds episodes of another scenario named 'cruise'"):
        _evaluation(tmp_path)


@pytest.mark.usefixtures("keep_lane")
def test_evaluate_resume_with_another_lockstep_runs_only_the_missing_episodes(tmp_path):
    """Allowed (see mmpc.evaluate): done is per key and every row keeps the group it ran in."""
    from mmpc.evaluate import METRIC_COLUMNS, read_episodes

    _evaluation(tmp_path / "resumed", seeds=range(4), lockstep=4)
    before = read_episodes(tmp_path / "resumed" / "episodes.csv")
    assert [(r["group"], r["group_size"]) for r in before] == [(0, 4)] * 4
    resumed = _evaluation(tmp_path / "resumed", seeds=range(6), lockstep=2)
    assert KeepLane.episodes_started == 6  # seeds 4 and 5 only
    rows = read_episodes(tmp_path / "resumed" / "episodes.csv")
    assert [r["seed"] for r in rows] == list(range(6))  # each key once
    assert repr(rows[:4]) == repr(before)  # the earlier rows as they were, with their groups (NaN-aware)
    assert [(r["seed"], r["group"], r["group_size"]) for r in rows[4:]] == [(4, 2, 2), (5, 2, 2)]
    assert json.loads((tmp_path / "resumed" / "summary.json").read_text())["lockstep"] == 2
    fresh = _evaluation(tmp_path / "fresh", seeds=range(6), lockstep=2)  # the uninterrupted run of the second call
    results = [c for c in METRIC_COLUMNS if not c.startswith("solve_ms")]
    for a, b in zip(resumed.rows, fresh.rows):
        assert repr({c: a[c] for c in results}) == repr({c: b[c] for c in results})


# ----------------------------------------------------------------------------------- RL actions


@pytest.fixture(scope="module")
def smoke():
    from mmpc.rl.config import RLConfig

    return load_config(RLConfig, "smoke")


def _safe_env(smoke, continuous: bool):
    from mmpc.rl.envs import SafeHighwayEnv

    return SafeHighwayEnv(smoke.scenario, smoke.env, smoke.reward, continuous=continuous)


@pytest.mark.usefixtures("one_thread")
def test_discrete_safe_env_takes_integers_and_refuses_floats_and_arrays(smoke):
    env = _safe_env(smoke, continuous=False)
    count = smoke.env.num_discrete_goals
    try:
        env.reset(seed=3)
        refused = [
            (2.7, r"`action` must be an int in \[0, %d\) .*; got 2.7 \(float\)" % count),  # was taken as 2
            (np.float32(2.0), r"got np.float32\(2.0\) \(float32\)"),
            (np.array([1, 7]), r"got an array of shape \(2,\) and dtype int64"),  # was taken as 1
            (np.array([1]), r"got an array of shape \(1,\)"),
            (np.array(2.0), r"got np.float64\(2.0\) \(float64\)"),
            (True, r"got True \(bool\)"),
            ("1", r"got '1' \(str\)"),
            (count, r"`action` must be an int in \[0, %d\); got %d" % (count, count)),
            (-1, r"got -1"),
        ]
        for action, message in refused:
            with pytest.raises(ValueError, match=message):
                env.step(action)
        assert env.episode.time == 0.0  # nothing was driven
        for action in (3, np.int64(3), np.int32(3), np.array(3), np.uint8(3)):  # SB3 passes np.int64; predict() a 0-d array
            assert env.check_action(action) == 3 and type(env.check_action(action)) is int
        _, _, _, _, info = env.step(np.array(count - 1))
        assert info["frames"] == smoke.env.decision_frames
    finally:
        env.close()


@pytest.mark.usefixtures("one_thread")
def test_continuous_safe_env_names_the_shape_and_refuses_nan(smoke):
    env = _safe_env(smoke, continuous=True)
    try:
        env.reset(seed=3)
        refused = {
            (0.1, 0.2, 0.3): r"`action` must have shape \(2,\); got \(3,\)",
            (0.5,): r"`action` must have shape \(2,\); got \(1,\)",
            ((0.1, 0.2),): r"`action` must have shape \(2,\); got \(1, 2\)",
            (np.nan, 0.0): r"`action` must be finite numbers \(in \[-1, 1\]\); got \[nan, 0.0\]",
            (0.0, np.inf): r"must be finite",
            ("a", "b"): r"`action` must be an array of 2 numbers; got dtype <U1",
        }
        for action, message in refused.items():
            with pytest.raises(ValueError, match=message):
                env.step(np.array(action) if action != ("a", "b") else list(action))
        assert env.episode.time == 0.0  # nothing was driven
        env.step([0.0, 2.0])  # a list of numbers is fine; values outside [-1, 1] are clipped
    finally:
        env.close()


@pytest.mark.usefixtures("one_thread")
def test_batched_advance_names_the_environment_with_a_bad_action(smoke):
    from mmpc.rl.vec_env import SafeVecEnv

    venv = SafeVecEnv(2, smoke.scenario, smoke.env, smoke.reward)
    try:
        venv.reset()
        with pytest.raises(ValueError, match=r"environment 1: `action` must be an int .*got 1.5 \(float\)"):
            venv.step([np.int64(0), 1.5])
        assert [episode.time for episode in venv.batch.world.episodes] == [0.0, 0.0]  # nothing was driven
    finally:
        venv.close()
