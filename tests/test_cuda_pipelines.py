"""The pipelines with the run device on CUDA (``--device cuda`` / MMPC_DEVICE=cuda): the batched
evaluation, RL training and its evaluation, the safe-layer drivers, the demonstrations, the
proposer and its labelling. Each runs a few seconds of driving. Skipped without a GPU."""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from mmpc.device import DEVICE_ENV

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA"),
]


@pytest.fixture
def on_cuda(monkeypatch):
    """MMPC_DEVICE=cuda for the test (and taken away after it: ``--device`` sets it too)."""
    monkeypatch.setenv(DEVICE_ENV, "cuda")


def _episodes(out: Path) -> list[dict]:
    with open(out / "episodes.csv", newline="") as handle:
        return list(csv.DictReader(handle))


def test_batched_evaluation_on_cuda_drives_the_cpu_episodes(tmp_path, on_cuda):
    from mmpc.cli.main import main

    argv = ["evaluate", "--driver", "mpc", "--scenarios", "high_speed", "--sim", "batched", "--seeds", "0-3",
            "--duration", "2", "--lockstep", "4", "--compile", "off"]
    assert main([*argv, "--device", "cuda", "--out", str(tmp_path / "cuda")]) == 0
    assert main([*argv, "--device", "cpu", "--out", str(tmp_path / "cpu")]) == 0
    cuda, cpu = _episodes(tmp_path / "cuda"), _episodes(tmp_path / "cpu")
    assert len(cuda) == len(cpu) == 4 and all(row["status"] == "ok" for row in cuda + cpu)
    by_seed = {row["seed"]: row for row in cpu}
    for row in cuda:
        reference = by_seed[row["seed"]]
        assert int(row["collisions"]) == int(reference["collisions"]), row["seed"]
        assert float(row["mean_speed"]) == pytest.approx(float(reference["mean_speed"]), abs=0.5), row["seed"]


def test_rl_training_on_the_batched_simulator_and_its_evaluation_on_cuda(tmp_path, on_cuda):
    import json

    from mmpc.cli.main import main

    out = tmp_path / "dqn"
    argv = ["rl", "train", "--algo", "dqn", "--config", "smoke", "--sim", "batched", "--timesteps", "64",
            "--compile", "off", "--device", "cuda", "--out", str(out)]
    assert main(argv) == 0  # trains on the simulator on CUDA, evaluates in highway-env with the layer on CUDA
    assert (out / "model.zip").is_file()
    summary = json.loads((out / "eval.json").read_text())
    assert summary["episodes"] == 2
    continuous = tmp_path / "sac"
    argv = ["rl", "train", "--algo", "sac", "--config", "smoke", "--sim", "batched", "--timesteps", "16", "--no-eval",
            "--compile", "off", "--device", "cuda", "--out", str(continuous)]
    assert main(argv) == 0 and (continuous / "model.zip").is_file()


def test_the_safe_environments_on_cuda_step_like_those_on_the_cpu(monkeypatch):
    from mmpc.rl.config import RewardConfig, SafeEnvConfig
    from mmpc.rl.envs import SafeHighwayEnv
    from mmpc.rl.vec_env import SafeVecEnv
    from mmpc.scenario import load_scenario

    scenario = dataclasses.replace(load_scenario("rl_highway_fast"), duration=1.0)
    for replan in ("frame", "decision"):
        config = SafeEnvConfig(replan=replan)
        runs = {}
        for device in ("cpu", "cuda"):
            monkeypatch.setenv(DEVICE_ENV, device)
            venv = SafeVecEnv(2, dataclasses.replace(scenario, sim="batched"), config, RewardConfig(), seed=0)
            assert venv.batch.device.type == device
            venv.seed(3)
            first = venv.reset()
            venv.step_async(np.array([4, 6]))
            observations, rewards, dones, infos = venv.step_wait()
            assert venv.batch.world.sim.device.type == device
            assert observations.dtype == np.float32 and isinstance(rewards, np.ndarray) and dones.dtype == np.bool_
            assert all(type(info["crashed"]) is bool and type(info["frames"]) is int for info in infos)
            runs[device] = (first, rewards)
        # the Kinematics rows match (the solver features may differ where a goal is feasible by a hair)
        kinematics = config.kinematics_vehicles * 5
        np.testing.assert_allclose(runs["cuda"][0][:, :kinematics], runs["cpu"][0][:, :kinematics], atol=1e-4)
        assert runs["cuda"][0].shape == runs["cpu"][0].shape and np.all(np.abs(runs["cuda"][0]) <= 1.0)
        env = SafeHighwayEnv(scenario, config, RewardConfig())  # highway-env's CPU states, the layer on CUDA
        assert env.layer.device.type == "cuda"
        observation, _ = env.reset(seed=0)
        observation, reward, terminated, truncated, info = env.step(4)
        assert observation.dtype == np.float32 and isinstance(reward, float) and isinstance(info["goal"][0], float)
        env.close()


def _evaluate_on_cuda(out: Path, drivers: str, scenario: str) -> list[dict]:
    """``mmpc evaluate`` of ``drivers`` on seeds 0-1 x 1 s of the batched simulator on CUDA; its episode rows."""
    from mmpc.cli.main import main

    argv = ["evaluate", "--driver", drivers, "--scenarios", scenario, "--sim", "batched", "--seeds", "0-1", "--duration", "1",
            "--lockstep", "2", "--compile", "off", "--device", "cuda", "--out", str(out)]
    assert main(argv) == 0
    return _episodes(out)


def test_the_safe_layer_drivers_drive_on_cuda(tmp_path, on_cuda):
    rows = _evaluate_on_cuda(tmp_path, "safe-random:smoke,safe-expert:smoke", "rl_highway_fast")
    assert len(rows) == 4 and all(row["status"] == "ok" for row in rows), rows


def test_demonstrations_on_cuda(tmp_path, on_cuda):
    pytest.importorskip("minari", reason="the demonstrations are written as a Minari dataset (mmpc[datasets])")
    from mmpc.cli.main import main
    from mmpc.imitation.dataset import load_episode

    out = tmp_path / "demos"
    argv = ["imitate", "demos", "--scenario", "cruise", "--sim", "batched", "--duration", "1", "--episodes", "2",
            "--lockstep", "2", "--compile", "off", "--device", "cuda", "--out", str(out)]
    assert main(argv) == 0
    episodes = sorted((out / "episodes").glob("seed_*.npz"))
    assert len(episodes) == 2
    episode = load_episode(episodes[0])
    assert episode.steps > 0 and np.isfinite(episode.actions).all() and np.isfinite(episode.infos["ego"]).all()


def test_a_shipped_proposer_drives_on_cuda(tmp_path, on_cuda):
    from mmpc.imitation.proposer_driver import shipped_proposers

    if "high_speed" not in shipped_proposers():
        pytest.skip("no shipped high_speed proposer under imitation/models/")
    rows = _evaluate_on_cuda(tmp_path, "proposer:high_speed", "high_speed")
    assert len(rows) == 2 and all(row["status"] == "ok" for row in rows), rows


def test_proposer_labelling_and_check_on_cuda(tmp_path, on_cuda):
    """Round 0 (the expert labels), round 1 (the proposer drives half the steps) and the check drives."""
    import json

    pytest.importorskip("minari", reason="the labels are written as a Minari dataset (mmpc[datasets])")

    from mmpc.cli.main import main

    out = tmp_path / "proposer"
    argv = ["imitate", "proposer", "--scenario", "high_speed", "--sim", "batched", "--duration", "0.5", "--rounds", "1",
            "--set", "episodes=2", "--set", "lockstep=2", "--set", "check_episodes=2", "--set", "train.epochs=2",
            "--set", "train.proposer.hidden=[16]", "--compile", "off", "--device", "cuda", "--out", str(out)]
    assert main(argv) == 0
    report = json.loads((out / "proposer.json").read_text())
    assert [entry["round"] for entry in report["rounds"]] == [0, 1] and (out / "proposer.pt").is_file()
