"""The run device on a CPU machine: MMPC_DEVICE read in one place, ``--device`` refused when it
names nothing usable, and ``--device cpu`` changing nothing (the CLI's episodes, the RL
environments on the batched simulator). The CUDA runs are in test_cuda_pipelines.py."""

from __future__ import annotations

import csv
import dataclasses

import numpy as np
import pytest
import torch

from mmpc.device import DEVICE_ENV, run_device
from mmpc.rl.config import RewardConfig, SafeEnvConfig
from mmpc.scenario import load_scenario

#: Columns of episodes.csv that measure the machine, not the episode.
TIMING_COLUMNS = {"worker", "wall_s", "solve_ms_mean", "solve_ms_max", "solve_ms_per_episode_mean"}


def test_run_device_reads_the_environment(monkeypatch):
    monkeypatch.delenv(DEVICE_ENV, raising=False)
    assert run_device() == torch.device("cpu")
    monkeypatch.setenv(DEVICE_ENV, "  ")
    assert run_device() == torch.device("cpu")
    monkeypatch.setenv(DEVICE_ENV, "cpu")
    assert run_device() == torch.device("cpu")
    monkeypatch.setenv(DEVICE_ENV, "auto")
    assert run_device() == (torch.device("cuda", torch.cuda.current_device()) if torch.cuda.is_available()
                            else torch.device("cpu"))
    monkeypatch.setenv(DEVICE_ENV, "nonsense")
    with pytest.raises(ValueError, match=DEVICE_ENV):
        run_device()


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal of cuda on a machine without it")
def test_cuda_without_a_gpu_is_refused_naming_the_variable(monkeypatch):
    monkeypatch.setenv(DEVICE_ENV, "cuda")
    with pytest.raises(ValueError, match=DEVICE_ENV):
        run_device()


def test_cli_refuses_a_device_that_names_nothing(tmp_path, monkeypatch, capsys):
    from mmpc.cli.main import main

    monkeypatch.delenv(DEVICE_ENV, raising=False)  # main sets it; monkeypatch takes it away again
    argv = ["evaluate", "--scenarios", "high_speed", "--sim", "batched", "--seeds", "0", "--duration", "0.2",
            "--compile", "off", "--device", "nonsense", "--out", str(tmp_path / "out")]
    assert main(argv) == 2
    assert "--device" in capsys.readouterr().err
    assert not (tmp_path / "out" / "episodes.csv").exists()


def _episodes(out) -> list[dict]:
    with open(out / "episodes.csv", newline="") as handle:
        return [{key: value for key, value in row.items() if key not in TIMING_COLUMNS} for row in csv.DictReader(handle)]


def test_device_cpu_gives_the_episodes_of_no_flag(tmp_path, monkeypatch):
    from mmpc.cli.main import main

    monkeypatch.delenv(DEVICE_ENV, raising=False)
    argv = ["evaluate", "--driver", "mpc", "--scenarios", "high_speed", "--sim", "batched", "--seeds", "0-1",
            "--duration", "1", "--lockstep", "2", "--compile", "off"]
    assert main([*argv, "--out", str(tmp_path / "plain")]) == 0
    assert main([*argv, "--device", "cpu", "--out", str(tmp_path / "cpu")]) == 0
    plain, cpu = _episodes(tmp_path / "plain"), _episodes(tmp_path / "cpu")
    assert len(plain) == 2 and plain == cpu


def _steps(monkeypatch, device):
    """Observations, rewards, dones and infos of a few steps of the batched safe environments."""
    from mmpc.rl.vec_env import SafeVecEnv

    if device is None:
        monkeypatch.delenv(DEVICE_ENV, raising=False)
    else:
        monkeypatch.setenv(DEVICE_ENV, device)
    scenario = dataclasses.replace(load_scenario("rl_highway_fast"), sim="batched", duration=1.0)
    venv = SafeVecEnv(2, scenario, SafeEnvConfig(), RewardConfig(), seed=0)
    assert venv.batch.world is None and venv.batch.device == torch.device("cpu")
    venv.seed(3)
    trace = [venv.reset()]
    actions = np.array([4, 6])  # keep lane at 15 and 25 m/s
    for _ in range(2):  # the second step ends the 1 s episodes: auto-reset
        venv.step_async(actions)
        observations, rewards, dones, infos = venv.step_wait()
        for info in infos:
            info.pop("solve_ms")
            info.pop("terminal_observation", None)
        trace.append((observations, rewards, dones, infos))
    assert venv.batch.world.sim.device == torch.device("cpu")
    return trace


def _assert_same_trace(first, second) -> None:
    np.testing.assert_array_equal(first[0], second[0])
    for (obs_a, rew_a, done_a, info_a), (obs_b, rew_b, done_b, info_b) in zip(first[1:], second[1:]):
        np.testing.assert_array_equal(obs_a, obs_b)
        np.testing.assert_array_equal(rew_a, rew_b)
        np.testing.assert_array_equal(done_a, done_b)
        assert info_a == info_b


def test_safe_vec_env_on_device_cpu_steps_as_without_it(monkeypatch):
    plain = _steps(monkeypatch, None)
    _assert_same_trace(plain, _steps(monkeypatch, "cpu"))
    observations, rewards, dones, infos = plain[1]
    assert observations.dtype == np.float32 and rewards.dtype == np.float32 and dones.dtype == np.bool_
    # the step's tallies came to the host as Python values
    assert all(type(info[key]) is bool for info in infos for key in ("intervention", "crashed", "agent_feasible"))
    assert all(type(info[key]) is int for info in infos for key in ("frames", "feasible_goals", "solved_frames"))
    assert all(type(value) is float for info in infos for value in (info["speed"], info["mean_speed"], *info["goal"]))
