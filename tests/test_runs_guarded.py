"""Runs that must not overwrite, mix with or outlive each other (tracker issue 44, items 1-4 and 12):
``mmpc rl train`` into a folder holding a run or held by one, a second ``mmpc imitate proposer``
run in a running folder, pool workers of a killed ``mmpc evaluate``, an interrupted ``mmpc
evaluate``, and ``mmpc rl evaluate`` on another road than the agent's."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mmpc.cli.main import main
from tests.conftest import hold_lock, lock_is_free

#: The lock files of a training run and of a proposer run (mmpc.rl.train.RUN_LOCK,
#: mmpc.imitation.proposer_dagger.LOCK), spelled out so that these tests fail on code without them.
RUN_LOCK = ".train.lock"
PROPOSER_LOCK = ".proposer.lock"


def _rl_train(out: Path, algo: str, seed: int = 0) -> list[str]:
    return ["rl", "train", "--algo", algo, "--config", "smoke", "--timesteps", "20", "--no-eval", "--seed", str(seed),
            "--out", str(out)]


class _Stop(Exception):
    """Raised by a stand-in to end a command where the test has seen what it needs."""


# ----------------------------------------------------------------------------------- mmpc rl train


def test_rl_train_refuses_a_folder_holding_a_finished_run(tmp_path, capsys, monkeypatch, one_thread):
    import mmpc.rl.train as rl_train
    from mmpc.rl.runs import load_run

    out = tmp_path / "R"
    held = []
    make_env = rl_train.make_training_env

    def spying_make_env(*args, **kwargs):  # the run holds its folder's lock while it trains
        held.append(not lock_is_free(out / RUN_LOCK))
        return make_env(*args, **kwargs)

    monkeypatch.setattr(rl_train, "make_training_env", spying_make_env)
    assert main(_rl_train(out, "dqn")) == 0
    capsys.readouterr()
    files = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    checkpoints = sorted(p.name for p in (out / "checkpoints").glob("dqn_*_steps.zip"))
    assert checkpoints == ["dqn_16_steps.zip", "dqn_24_steps.zip"]  # every checkpoint_every steps, and at the end
    checkpoint = out / "checkpoints" / checkpoints[-1]

    for argv in (_rl_train(out, "ppo"), _rl_train(out, "dqn", seed=1)):  # another algorithm, another seed
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert f"`out` {out} already holds a finished run (dqn on safe, seed 0)" in err, err
        assert "config.yaml" in err and "model.zip" in err and "choose another --out" in err
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == files  # nothing replaced, nothing added
    assert load_run(checkpoint).algo == "dqn"
    assert held == [True] and lock_is_free(out / RUN_LOCK)  # held while training; the refused runs built nothing


def test_rl_train_refuses_a_folder_another_run_is_writing(tmp_path, capsys, monkeypatch):
    import mmpc.rl.train as rl_train

    def no_training(*args, **kwargs):
        raise AssertionError("a second run started training")

    monkeypatch.setattr(rl_train, "make_training_env", no_training)
    out = tmp_path / "R"
    out.mkdir()
    holder = hold_lock(out / RUN_LOCK)  # a PPO run started a moment ago and still writes there
    try:
        assert main(_rl_train(out, "dqn")) == 2
    finally:
        holder.close()
    err = capsys.readouterr().err
    assert f"another `mmpc rl train` run is writing to {out}" in err and str(out / RUN_LOCK) in err, err
    assert sorted(p.name for p in out.iterdir()) == [RUN_LOCK]  # no config.yaml beside the other run's files


def test_rl_train_leaves_a_foreign_folder_as_it_was(tmp_path, capsys, monkeypatch):
    import mmpc.rl.train as rl_train

    def no_training(*args, **kwargs):
        raise AssertionError("a run trained among another's files")

    monkeypatch.setattr(rl_train, "make_training_env", no_training)
    (tmp_path / "notes.txt").write_text("mine")
    assert main(_rl_train(tmp_path, "dqn")) == 2
    assert f"`out` {tmp_path} already holds files: notes.txt" in capsys.readouterr().err
    assert not (tmp_path / RUN_LOCK).exists() and sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


# ----------------------------------------------------------------------------------- mmpc imitate proposer


def _proposer(out: Path) -> list[str]:
    return ["imitate", "proposer", "--scenario", "cruise", "--duration", "0.5", "--set", "episodes=1", "--set",
            "rounds=0", "--set", "check_episodes=0", "--out", str(out)]


def test_proposer_refuses_a_folder_another_run_holds(tmp_path, capsys, monkeypatch):
    import mmpc.imitation.proposer_dagger as proposer_dagger

    def no_labelling(*args, **kwargs):
        raise AssertionError("a second run labelled round 0 again")

    monkeypatch.setattr(proposer_dagger, "label_episodes", no_labelling)
    out = tmp_path / "proposer"
    out.mkdir()
    holder = hold_lock(out / PROPOSER_LOCK)  # the first run, in its round 0
    try:
        assert main(_proposer(out)) == 2
    finally:
        holder.close()
    err = capsys.readouterr().err
    assert f"mmpc imitate proposer: error: another `mmpc imitate proposer` run is writing to {out}" in err, err
    assert "imitate demos" not in err
    assert sorted(p.name for p in out.iterdir()) == [PROPOSER_LOCK]  # no second TensorBoard file


def test_proposer_holds_its_folder_while_it_runs(tmp_path, monkeypatch):
    import mmpc.imitation.proposer_dagger as proposer_dagger

    out = tmp_path / "proposer"
    held = []

    def labelling(*args, **kwargs):
        held.append(not lock_is_free(out / PROPOSER_LOCK))
        raise _Stop

    monkeypatch.setattr(proposer_dagger, "label_episodes", labelling)
    with pytest.raises(_Stop):
        main(_proposer(out))
    assert held == [True] and lock_is_free(out / PROPOSER_LOCK)


# ----------------------------------------------------------------------------------- mmpc evaluate


def test_an_interrupted_evaluation_says_how_to_resume_and_exits_130(tmp_path, capsys, monkeypatch):
    import mmpc.evaluate

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(mmpc.evaluate, "evaluate", interrupted)
    out = tmp_path / "evaluation"
    try:
        code = main(["evaluate", "--scenarios", "cruise", "--seeds", "0-1", "--out", str(out)])
    except KeyboardInterrupt:
        pytest.fail("Ctrl-C ended `mmpc evaluate` in a traceback")
    assert code == 130
    assert (f"mmpc evaluate: interrupted; the finished episodes are kept in {out}/episodes.csv; re-run the same "
            "command to resume") in capsys.readouterr().err


def test_a_second_evaluation_into_a_running_folder_is_an_error_not_a_traceback(tmp_path, capsys):
    holder = hold_lock(tmp_path / ".evaluate.lock")  # the first evaluation, still running
    try:
        assert main(["evaluate", "--scenarios", "cruise", "--seeds", "0-1", "--out", str(tmp_path)]) == 2
    finally:
        holder.close()
    assert f"mmpc evaluate: error: another evaluation is writing to {tmp_path}" in capsys.readouterr().err


def _children(pid: int) -> dict[int, str]:
    """Live child processes of ``pid``: pid -> command line."""
    found = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rpartition(")")[2].split()
            command = (stat.parent / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        if int(fields[1]) == pid and fields[0] != "Z":
            found[int(stat.parent.name)] = command
    return found


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()[0] != "Z"
    except OSError:
        return False


def _resident_mb(pid: int) -> float:
    try:
        return int(Path(f"/proc/{pid}/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except OSError:
        return 0.0


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="workers follow a killed parent on Linux")
def test_pool_workers_end_with_a_killed_evaluation(tmp_path):
    command = [sys.executable, "-m", "mmpc.cli", "evaluate", "--workers", "2", "--scenarios", "cruise", "--seeds", "0-3",
               "--lockstep", "1", "--out", str(tmp_path / "evaluation")]
    process = subprocess.Popen(command, env={**os.environ, "OMP_NUM_THREADS": "1"}, stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE)
    workers: dict[int, str] = {}
    try:
        deadline = time.time() + 120
        while time.time() < deadline:  # both workers spawned and past their imports (~340 MB each)
            assert process.poll() is None, process.communicate()[1].decode()
            workers = {pid: c for pid, c in _children(process.pid).items() if "spawn_main" in c}
            if len(workers) == 2 and all(_resident_mb(pid) > 150 for pid in workers):
                break
            time.sleep(0.2)
        assert len(workers) == 2, _children(process.pid)
        time.sleep(2.0)  # into their first tasks
        trackers = [pid for pid, c in _children(process.pid).items() if "resource_tracker" in c]
        process.kill()
        process.wait()
        deadline = time.time() + 10
        while time.time() < deadline and any(map(_alive, [*workers, *trackers])):
            time.sleep(0.1)
        assert not [pid for pid in [*workers, *trackers] if _alive(pid)], "orphaned worker or resource tracker"
    finally:
        for pid in workers:  # the orphans of a failed run (ours, by id)
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
        if process.poll() is None:
            process.kill()
            process.wait()


# ----------------------------------------------------------------------------------- mmpc rl evaluate


@pytest.mark.parametrize("key,value,trained", [("scenario.lanes", "2", "6"), ("env.kinematics_vehicles", "7", "5")])
def test_rl_evaluate_refuses_another_road_or_observation_than_the_trained_one(capsys, monkeypatch, key, value, trained):
    import mmpc.rl.train as rl_train

    def no_evaluation(*args, **kwargs):
        raise AssertionError("the agent was evaluated")

    monkeypatch.setattr(rl_train, "evaluate_run", no_evaluation)
    assert main(["rl", "evaluate", "--model", "high_speed_ppo", "--episodes", "1", "--set", f"{key}={value}"]) == 2
    err = capsys.readouterr().err
    assert f"`{key}` must stay {trained}, the value the agent was trained with; got {value}" in err, err


def test_rl_evaluate_still_takes_other_traffic(monkeypatch):
    import mmpc.rl.train as rl_train

    def evaluated(model, config, **kwargs):
        assert config.scenario.traffic.vehicles_count == 30
        raise _Stop

    monkeypatch.setattr(rl_train, "evaluate_run", evaluated)
    with pytest.raises(_Stop):
        main(["rl", "evaluate", "--model", "high_speed_ppo", "--episodes", "1", "--set",
              "scenario.traffic.vehicles_count=30"])
