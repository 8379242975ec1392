"""Training commands that must refuse before they write, or say what they did (tracker issue 55,
items 4, 5, 10, 11, 12, 13, 15, 16 and 20): ``mmpc imitate bc`` and ``dagger`` guard their
folders, a refused ``mmpc rl train`` start leaves nothing behind, ``mmpc rl evaluate`` checks its
``--out`` and world first and says how big its work is, the rounded-up training budget is recorded,
``mmpc rl report`` refuses a label given twice, a diverging BC run says so, and the training
episodes that crash are logged with what replays them."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from mmpc.cli.main import main
from mmpc.config import load_config
from mmpc.scenario import load_scenario
from tests.conftest import hold_lock, lock_is_free

pytestmark = pytest.mark.usefixtures("one_thread")

#: The lock files of the runs (mmpc.rl.train.RUN_LOCK, mmpc.imitation.bc.LOCK,
#: mmpc.imitation.dagger.LOCK), spelled out so that these tests fail on code without them.
RUN_LOCK = ".train.lock"
BC_LOCK = ".bc.lock"
DAGGER_LOCK = ".dagger.lock"


class _Stop(Exception):
    """Raised by a stand-in to end a command where the test has seen what it needs."""


def _files(folder: Path) -> dict[Path, bytes]:
    return {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}


@pytest.fixture(scope="module")
def demos(tmp_path_factory) -> Path:
    from mmpc.imitation.demos import generate_demonstrations

    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("demos")
    generate_demonstrations(load_scenario("cruise").replace(duration=1.0), [1000, 1001], out, lockstep=2)
    torch.set_num_threads(previous)
    return out


def _bc(demos: Path, out: Path, *settings: str) -> list[str]:
    argv = ["imitate", "bc", "--dataset", str(demos), "--out", str(out), "--epochs", "2", "--set", "batch_size=8"]
    for setting in settings:
        argv += ["--set", setting]
    return argv


def _rl_train(out: Path, *options: str) -> list[str]:
    return ["rl", "train", "--config", "smoke", "--timesteps", "8", "--no-eval", "--out", str(out), *options]


# ----------------------------------------------------------------------------------- item 4: bc and dagger folders


def test_bc_refuses_a_folder_holding_a_finished_run_and_holds_its_lock_while_training(demos, tmp_path, capsys,
                                                                                       monkeypatch):
    import mmpc.imitation.bc as bc

    out = tmp_path / "bc"
    held = []
    train_policy = bc.train_policy

    def spying_train_policy(*args, **kwargs):
        held.append(not lock_is_free(out / BC_LOCK))
        return train_policy(*args, **kwargs)

    monkeypatch.setattr(bc, "train_policy", spying_train_policy)
    assert main(_bc(demos, out)) == 0
    capsys.readouterr()
    assert held == [True]
    finished = _files(out)
    assert {p.name for p in finished} >= {"policy.pt", "train.json"}

    assert main(_bc(demos, out, "learning_rate=0.01")) == 2  # another run into the finished one's folder
    err = capsys.readouterr().err
    assert f"`out` {out} already holds a finished behaviour cloning run (20 samples of {demos})" in err, err
    assert "policy.pt" in err and "train.json" in err and "choose another --out" in err
    assert _files(out) == finished and held == [True]  # nothing replaced, no second training

    (tmp_path / "busy").mkdir()
    holder = hold_lock(tmp_path / "busy" / BC_LOCK)  # another run, training there
    try:
        assert main(_bc(demos, tmp_path / "busy")) == 2
    finally:
        holder.close()
    assert f"another `mmpc imitate bc` run is writing to {tmp_path / 'busy'}" in capsys.readouterr().err
    assert held == [True]


def _dagger(out: Path) -> list[str]:
    return ["imitate", "dagger", "--scenario", "cruise", "--duration", "0.5", "--iterations", "0", "--set",
            "initial_episodes=1", "--set", "check_episodes=0", "--set", "lockstep=1", "--out", str(out)]


def test_dagger_refuses_a_folder_another_run_holds_and_holds_its_own(tmp_path, capsys, monkeypatch):
    import mmpc.imitation.dagger as dagger

    out = tmp_path / "dagger"
    held = []

    def driving(*args, **kwargs):
        held.append(not lock_is_free(out / DAGGER_LOCK))
        raise _Stop

    monkeypatch.setattr(dagger, "_drive", driving)
    out.mkdir()
    holder = hold_lock(out / DAGGER_LOCK)  # the first run, in its round 0
    try:
        assert main(_dagger(out)) == 2
    finally:
        holder.close()
    assert f"mmpc imitate dagger: error: another `mmpc imitate dagger` run is writing to {out}" in capsys.readouterr().err
    assert held == [] and sorted(p.name for p in out.iterdir()) == [DAGGER_LOCK]  # no TensorBoard file beside the run's

    with pytest.raises(_Stop):
        main(_dagger(out))
    assert held == [True] and lock_is_free(out / DAGGER_LOCK)


# ----------------------------------------------------------------------------------- item 5: refused starts


def test_refused_rl_train_starts_leave_nothing_that_blocks_the_corrected_command(tmp_path, capsys):
    out = tmp_path / "run"
    refusals = [
        (["--algo", "sac", "--set", "env.replan=decision", "--set", "env.expert_action=true"], "expert_action"),
        (["--algo", "dqn", "--set", "algorithms.dqn.learning_rate=banana"],
         "`algorithms.dqn.learning_rate` must be a finite number > 0; got 'banana'"),
        (["--algo", "dqn", "--set", "algorithms.dqn.learning_rate=.nan"], "learning_rate"),
        (["--algo", "dqn", "--seed", "-1"], "`seed` must be an int in [0, 4294967295]; got -1"),
        (["--algo", "dqn", "--set", "scenario.mpc.warm_iterations=100"], "warm_iterations"),
    ]
    for options, message in refusals:
        assert main(_rl_train(out, *options)) == 2, options
        err = capsys.readouterr().err
        assert "mmpc rl train: error:" in err and message in err and "Traceback" not in err, (options, err)
        assert not out.exists() or list(out.iterdir()) == [], (options, sorted(p.name for p in out.iterdir()))
    assert main(_rl_train(out, "--algo", "dqn")) == 0  # the corrected command, in the same folder
    assert (out / "model.zip").is_file()
    assert yaml.safe_load((out / "config.yaml").read_text())["algo"] == "dqn"


# ----------------------------------------------------------------------------------- item 10, 20: rl evaluate


@pytest.fixture
def no_evaluation(monkeypatch):
    import mmpc.rl.train as rl_train

    def evaluated(*args, **kwargs):
        raise AssertionError("the episodes were driven")

    monkeypatch.setattr(rl_train, "evaluate_run", evaluated)


def test_rl_evaluate_checks_its_out_before_the_episodes(tmp_path, capsys, no_evaluation):
    (tmp_path / "file").write_text("")
    for out, problem in ((tmp_path, "it is a folder"), (tmp_path / "file" / "eval.json", "FileExistsError")):
        assert main(["rl", "evaluate", "--model", "high_speed_ppo", "--episodes", "1", "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert f"mmpc rl evaluate: error: --out {out} must be a file in a folder this process can create and write to" \
               in err and problem in err, err


def test_rl_evaluate_refuses_the_batched_world_it_does_not_drive(capsys, no_evaluation, monkeypatch):
    assert main(["rl", "evaluate", "--model", "high_speed_ppo", "--episodes", "1", "--set", "scenario.sim=batched"]) == 2
    err = capsys.readouterr().err
    assert "mmpc rl evaluate: error: `scenario.sim` must be 'highway-env'; got 'batched'" in err, err
    assert "`mmpc evaluate --sim batched --driver sb3:MODEL`" in err

    import mmpc.rl.train as rl_train

    worlds = []

    def evaluated(model, config, **kwargs):
        worlds.append(config.scenario.sim)
        raise _Stop

    monkeypatch.setattr(rl_train, "evaluate_run", evaluated)
    with pytest.raises(_Stop):
        main(["rl", "evaluate", "--model", "high_speed_ppo", "--episodes", "1", "--set", "scenario.sim=highway-env"])
    assert worlds == ["highway-env"]


def test_rl_evaluate_names_shipped_agents_and_says_how_big_its_work_is(capsys, monkeypatch):
    with pytest.raises(SystemExit):
        main(["rl", "evaluate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "MODEL.zip|NAME" in text and "high_speed_ppo" in text and "cruise_task_ppo" in text
    assert "minutes" in text and "hours" in text

    import mmpc.rl.train as rl_train

    def evaluated(*args, **kwargs):
        raise _Stop

    monkeypatch.setattr(rl_train, "evaluate_run", evaluated)
    with pytest.raises(_Stop):
        main(["rl", "evaluate", "--model", "high_speed_ppo", "--episodes", "3"])
    err = capsys.readouterr().err
    assert "evaluating high_speed_ppo: 3 episodes x 40 s in highway-env (120 s driven, 3 at a time" in err, err


# ----------------------------------------------------------------------------------- item 11: the budget trained


def test_rl_train_says_rollouts_round_the_budget_up_and_records_the_steps_trained(tmp_path, caplog):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out = tmp_path / "ppo"
    with caplog.at_level("WARNING", logger="mmpc.rl.train"):
        assert main(["rl", "train", "--algo", "ppo", "--config", "smoke", "--timesteps", "20", "--no-eval", "--out",
                     str(out)]) == 0
    # smoke: n_steps 8 x n_envs 2 = rollouts of 16 steps
    (warning,) = [r.getMessage() for r in caplog.records if r.name == "mmpc.rl.train"]
    assert "ppo trains whole rollouts of 16 steps (n_envs = 2): 20 timesteps round up to 32" in warning, warning
    run = yaml.safe_load((out / "config.yaml").read_text())
    assert run["timesteps"] == 20 and run["trained_timesteps"] == 32
    (folder,) = (out / "tb").iterdir()
    events = EventAccumulator(str(folder))
    events.Reload()
    assert max(event.step for event in events.Scalars("safety/episodes")) == 32


# ----------------------------------------------------------------------------------- item 12: rl report labels


def test_rl_report_refuses_a_label_given_twice(tmp_path, capsys):
    out = tmp_path / "report"
    assert main(["rl", "report", f"a={tmp_path / 'R1'}", f"a={tmp_path / 'R2'}", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"mmpc rl report: error: the label 'a' names two runs ({tmp_path / 'R1'}, {tmp_path / 'R2'})" in err, err
    assert not out.exists()


# ----------------------------------------------------------------------------------- item 13: a diverging BC run


def test_a_diverging_bc_run_says_so_writes_no_policy_and_the_corrected_run_follows(demos, tmp_path, capsys):
    out = tmp_path / "bc"
    assert main(_bc(demos, out, "learning_rate=1.0e+20")) == 2
    err = capsys.readouterr().err
    assert "mmpc imitate bc: error: the training diverged: loss inf (training)" in err, err
    assert "at epoch 1 of 2; try a smaller learning_rate (got 1e+20)" in err and "Traceback" not in err
    assert list(out.iterdir()) == []  # no policy, no TensorBoard events of the failed run
    assert main(_bc(demos, out)) == 0
    assert json.loads((out / "train.json").read_text())["samples"] == 20


def test_train_policy_refuses_a_nan_loss_at_its_epoch():
    from mmpc.imitation.bc import TrainConfig, TrainingDiverged, train_policy
    from mmpc.imitation.dataset import Transitions
    from mmpc.imitation.policy import PolicyConfig

    rng = np.random.default_rng(0)
    ego = np.zeros((12, 6), dtype=np.float32)
    ego[:, 0], ego[:, 1], ego[:, 3] = np.arange(12) * 2.0, 4.0, 20.0
    neighbours = np.full((12, 8, 4), np.nan, dtype=np.float32)  # no other cars
    data = Transitions(ego, neighbours, rng.normal(size=(12, 2)).astype(np.float32), np.arange(12) // 3)
    config = TrainConfig(epochs=3, batch_size=4, learning_rate=1e20, policy=PolicyConfig(hidden=(8,)))
    with pytest.raises(TrainingDiverged, match=r"diverged in round_2: loss .* at epoch 1 of 3; try a smaller learning_rate"):
        train_policy(data, load_scenario("cruise").road, config, tag="round_2/")


# ----------------------------------------------------------------------------------- item 15: crashed episodes


def test_training_crashes_are_logged_with_what_replays_them(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from mmpc.rl.config import RLConfig
    from mmpc.rl.train import make_highway_env, train

    # the plain baseline in dense traffic over 10 s episodes: an untrained DQN crashes within 64 steps
    config = load_config(RLConfig, "smoke", {"scenario.duration": 10.0, "scenario.traffic.vehicles_count": 40})
    out = tmp_path / "run"
    train(config, "dqn", 64, out, env_kind="highway", seed=0, evaluate_after=False)
    with open(out / "crashes.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    (folder,) = (out / "tb").iterdir()
    events = EventAccumulator(str(folder))
    events.Reload()
    assert len(rows) == events.Scalars("safety/crashes")[-1].value > 0  # every crash the scalar counts, once
    for row in rows:  # its seed and actions drive the episode again, into the crash at its step
        actions = json.loads(row["actions"])
        assert len(actions) == int(row["step"]) and 0 < int(row["timesteps"]) <= 64 and row["env"] in ("0", "1")
        assert float(row["time_s"]) == int(row["step"]) * config.env.decision_frames / config.scenario.frequency
        env = make_highway_env(config)
        env.reset(seed=int(row["episode_seed"]))
        ends = []
        for step, action in enumerate(actions, start=1):
            _, _, terminated, truncated, info = env.step(action)
            if terminated or truncated:
                ends.append((step, info["crashed"]))
        env.close()
        assert ends == [(int(row["step"]), True)], row


def test_the_crash_log_takes_each_episodes_seed_from_the_reset_that_began_it(tmp_path):
    from mmpc.rl.callbacks import CrashLog, SafetyTensorboardCallback

    class Venv:  # the vectorized environments as the callback reads them (SB3's VecEnv.reset_infos)
        reset_infos = [{"episode_seed": 7}, {"episode_seed": 8}]
        unwrapped = property(lambda self: self)

    class Model:
        env = Venv()

        def get_env(self):
            return self.env

    callback = SafetyTensorboardCallback(log_every=10**9, crash_log=CrashLog(tmp_path / "crashes.csv", 10.0))
    callback.model = Model()
    callback.num_timesteps = 0
    callback._on_training_start()
    steps = [  # (infos, dones, actions, the seeds the resets after this step drew)
        ([{"frames": 5}, {"frames": 5}], [False, False], [[0.5, 2.0], [1.0, -1.0]], None),
        ([{"frames": 3, "crashed": True}, {"frames": 5}], [True, False], [[0.1, 0.2], [3.0, 3.0]], [11, 8]),
        ([{"frames": 2, "crashed": True}, {"frames": 4, "crashed": True}], [True, True], [[0.0, 0.0], [9.0, 9.0]],
         [12, 13]),
    ]
    for infos, dones, actions, seeds in steps:
        if seeds is not None:
            Venv.reset_infos = [{"episode_seed": s} for s in seeds]
        callback.num_timesteps += 2
        callback.locals = {"infos": infos, "dones": np.array(dones), "actions": np.zeros((2, 2)),
                           "clipped_actions": np.array(actions)}
        callback._on_step()
    with open(tmp_path / "crashes.csv", newline="") as handle:
        rows = [dict(row) for row in csv.DictReader(handle)]
    assert rows == [
        {"timesteps": "4", "env": "0", "episode_seed": "7", "step": "2", "time_s": "0.8",
         "actions": "[[0.5, 2.0], [0.1, 0.2]]"},
        {"timesteps": "6", "env": "0", "episode_seed": "11", "step": "1", "time_s": "0.2", "actions": "[[0.0, 0.0]]"},
        {"timesteps": "6", "env": "1", "episode_seed": "8", "step": "3", "time_s": "1.4",
         "actions": "[[1.0, -1.0], [3.0, 3.0], [9.0, 9.0]]"},
    ]
    assert (callback.total_crashes, callback.total_episodes) == (3, 3)


# ----------------------------------------------------------------------------------- item 16: unwritable --out


def test_training_commands_refuse_an_out_they_cannot_write_before_any_work(demos, tmp_path, capsys, monkeypatch):
    import mmpc.imitation.bc as bc
    import mmpc.imitation.dagger as dagger
    import mmpc.rl.train as rl_train

    def no_work(*args, **kwargs):
        raise AssertionError("the command worked towards a folder it cannot write")

    monkeypatch.setattr(rl_train, "make_training_env", no_work)
    monkeypatch.setattr(bc, "train_policy", no_work)
    monkeypatch.setattr(dagger, "_drive", no_work)
    (tmp_path / "file").write_text("")
    out = tmp_path / "file" / "run"
    for verb, argv in (("rl train", _rl_train(out, "--algo", "dqn")), ("imitate bc", _bc(demos, out)),
                       ("imitate dagger", _dagger(out))):
        assert main(argv) == 2, verb
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert err.startswith(f"mmpc {verb}: error: `out` {out} must be a folder this process can create and write to; "
                              "got NotADirectoryError"), err
    assert main(["rl", "report", f"a={tmp_path}", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"mmpc rl report: error: --out {out} must be a folder this process can create and write to" in err, err
