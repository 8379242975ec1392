"""mmpc.imitation: expert demonstrations as a Minari dataset (resumable), behaviour cloning,
the policy driver, batched expert labelling (DAgger) and the stable-baselines3 export."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from mmpc.drive import run_episode, write_outputs
from mmpc.drivers import MPCDriver, make_driver
from mmpc.imitation.bc import TrainConfig, run_bc, train_policy
from mmpc.imitation.dagger import DaggerConfig, label_states, run_dagger
from mmpc.imitation.dataset import (
    DemonstrationsError,
    Transitions,
    dataset_transitions,
    load_episode,
    open_dataset,
)
from mmpc.imitation.demos import chunks, generate_demonstrations
from mmpc.imitation.policy import PolicyConfig, PolicyDriver, load_policy, save_policy
from mmpc.imitation.rollout import rollout_lockstep
from mmpc.scenario import build_mpc, load_scenario

pytestmark = pytest.mark.usefixtures("one_thread")

SEEDS = [1000, 1001, 1002]


def short_cruise(duration: float = 2.0):
    return load_scenario("cruise").replace(duration=duration)


@pytest.fixture(scope="module")
def demos_dir(tmp_path_factory) -> Path:
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("demos")
    generate_demonstrations(short_cruise(), SEEDS, out, lockstep=2)
    torch.set_num_threads(previous)
    return out


@pytest.fixture(scope="module")
def bc_run(demos_dir, tmp_path_factory) -> Path:
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("bc")
    config = TrainConfig(epochs=8, batch_size=32, validation_fraction=0.34, policy=PolicyConfig(hidden=(32, 32)))
    run_bc(demos_dir, out, config)
    torch.set_num_threads(previous)
    return out


def test_minari_loads_the_demonstrations_and_iterates_their_episodes(demos_dir, monkeypatch):
    import minari

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(demos_dir / "minari"))
    dataset = minari.load_dataset("mmpc/cruise-expert-v0")
    assert dataset.total_episodes == len(SEEDS)
    assert dataset.observation_space.shape == (5, 5)
    assert np.allclose(dataset.action_space.high, [5.0, math.pi / 4])
    metadata = dataset.storage.metadata
    assert metadata["mmpc_seeds"] == SEEDS
    assert metadata["mmpc_scenario"]["objective"]["v_cruise"] == 15.0
    assert metadata["mmpc_packages"]["minari"] == minari.__version__
    episodes = list(dataset.iterate_episodes())
    assert [e.id for e in episodes] == [0, 1, 2]
    for episode, seed in zip(episodes, SEEDS):
        staged = load_episode(demos_dir / "episodes" / f"seed_{seed:06d}.npz")
        steps = len(episode.actions)
        assert steps == 20 and episode.observations.shape == (21, 5, 5)
        np.testing.assert_array_equal(episode.observations, staged.observations)
        np.testing.assert_array_equal(episode.actions, staged.actions)
        assert episode.truncations[-1] and not episode.terminations.any()  # 2 s, no collision
        assert (episode.rewards > 0).all()
        # infos: the expert's decision at each observation; the last row has none
        assert episode.infos["goal_index"].shape == (21,)
        assert (episode.infos["goal_index"][:-1] >= 0).all() and episode.infos["goal_index"][-1] == -1
        assert np.isfinite(episode.infos["residual_nonholonomic"][:-1]).all()
        # the ego's speed in the observation (feature vx, normalised by 80 m/s) is the road-frame v
        np.testing.assert_allclose(episode.observations[:, 0, 3] * 80.0, episode.infos["ego"][:, 3], atol=0.05)
    # the env spec rebuilds highway-env with the scenario's configuration
    env = dataset.recover_environment()
    assert env.unwrapped.config["lanes_count"] == 6 and env.unwrapped.config["policy_frequency"] == 10.0
    env.close()


def test_recorded_actions_are_the_experts_commands_at_the_recorded_states():
    scenario = short_cruise(1.0)
    expert = MPCDriver(build_mpc(scenario))
    with torch.inference_mode():
        rollout = rollout_lockstep(scenario, [1000], expert, keep_states=True)[0]
        relabelled = label_states(expert, rollout.states, batch=4)  # batched, off-line: the DAgger labelling
    assert len(rollout.states) == rollout.episode.steps == 10
    np.testing.assert_allclose(relabelled, rollout.episode.actions, atol=2e-3)


def test_rerun_reuses_everything_and_foreign_or_other_runs_directories_are_refused(demos_dir, tmp_path):
    report = generate_demonstrations(short_cruise(), SEEDS, demos_dir, lockstep=2)
    assert report.generated == [] and report.reused == SEEDS and not report.rebuilt
    with pytest.raises(DemonstrationsError, match="differs in: duration"):
        generate_demonstrations(short_cruise(3.0), SEEDS, demos_dir, lockstep=2)
    with pytest.raises(DemonstrationsError, match="differs in: lockstep"):
        generate_demonstrations(short_cruise(), SEEDS, demos_dir, lockstep=3)
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    with pytest.raises(DemonstrationsError, match="not an mmpc demonstrations directory"):
        generate_demonstrations(short_cruise(), SEEDS, foreign)
    assert (foreign / "notes.txt").read_text() == "mine" and len(list(foreign.iterdir())) == 1
    corrupt = tmp_path / "corrupt"
    corrupt.mkdir()
    (corrupt / "manifest.json").write_text('{"format": "mmpc-demonstrations", "version": 1, "sce')
    with pytest.raises(DemonstrationsError, match="manifest.json is corrupt"):
        generate_demonstrations(short_cruise(), SEEDS, corrupt)
    assert chunks([1000, 1001, 1002, 1005], 4) == [[1000, 1001, 1002], [1005]]


def _demos_command(out: Path) -> list[str]:
    return [sys.executable, "-m", "mmpc.cli", "demos", "--scenario", "cruise", "--duration", "1", "--episodes", "6",
            "--lockstep", "2", "--out", str(out)]


def test_interrupted_generation_resumes_to_exactly_the_uninterrupted_episodes(tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    interrupted = tmp_path / "interrupted"  # given relative to the working directory, as users do
    process = subprocess.Popen(_demos_command(Path("interrupted")), env=env, cwd=tmp_path, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while time.time() < deadline and not list((interrupted / "episodes").glob("seed_*.npz")):
        assert process.poll() is None, process.communicate()
        time.sleep(0.05)
    process.send_signal(signal.SIGINT)
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == 130, stderr
    assert "re-run the same command to resume" in stderr
    kept = sorted(p.name for p in (interrupted / "episodes").glob("seed_*.npz"))
    assert 1 <= len(kept) < 6, kept
    assert not (interrupted / "minari").exists()
    assert not list((interrupted / "episodes").glob(".tmp-*"))

    resumed = subprocess.run(_demos_command(Path("interrupted")), env=env, cwd=tmp_path, capture_output=True, text=True,
                             timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    assert f"{len(kept)} from an earlier run" in resumed.stdout
    fresh = tmp_path / "fresh"  # the same command, uninterrupted (in this process: one thread, as the CLI)
    generate_demonstrations(short_cruise(1.0), range(1000, 1006), fresh, lockstep=2)

    a, b = open_dataset(interrupted), open_dataset(fresh)
    assert a.total_episodes == b.total_episodes == 6
    for x, y in zip(a.iterate_episodes(), b.iterate_episodes()):
        assert x.id == y.id
        for name in ("observations", "actions", "rewards", "terminations", "truncations"):
            np.testing.assert_array_equal(getattr(x, name), getattr(y, name), err_msg=name)
        for name in x.infos:
            if name != "solve_ms":  # a wall time
                np.testing.assert_array_equal(x.infos[name], y.infos[name], err_msg=name)
    assert a.storage.metadata["mmpc_seeds"] == list(range(1000, 1006))


def test_behaviour_cloning_writes_a_checkpoint_tensorboard_and_a_held_out_loss(bc_run, demos_dir):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    report = json.loads((bc_run / "train.json").read_text())
    assert report["samples"] == 60 and report["episodes"] == 3
    assert len(report["train_loss"]) == 8
    assert report["train_loss"][-1] < report["train_loss"][0]
    assert report["val_loss"] == min(report["val_loss_per_epoch"])
    events = EventAccumulator(str(bc_run / "tb"))
    events.Reload()
    assert {"train/loss", "val/loss", "val/rmse_acceleration", "val/rmse_steering"} <= set(events.Tags()["scalars"])
    assert [e.value for e in events.Scalars("val/loss")] == pytest.approx(report["val_loss_per_epoch"])
    # the checkpoint reproduces the trained statistics and bounds
    policy = load_policy(bc_run / "policy.pt")
    data = dataset_transitions(open_dataset(demos_dir))
    with torch.no_grad():
        command = policy(torch.as_tensor(data.observations), torch.as_tensor(data.commands))
    assert command.shape == (60, 2)
    assert float(command[:, 0].abs().max()) <= 5.0 and float(command[:, 1].abs().max()) <= math.pi / 4


def test_cloned_policy_drives_as_bc_driver_and_writes_metrics(bc_run, tmp_path):
    scenario = short_cruise(1.0)
    driver = make_driver(f"bc:{bc_run / 'policy.pt'}", scenario)
    assert isinstance(driver, PolicyDriver)
    result = run_episode(scenario, 7, driver=driver)
    assert result.metrics["steps"] == 10
    assert all(r.goal_index == -1 and math.isnan(r.plan_cost) for r in result.records)
    paths = write_outputs(result, tmp_path / "drive")
    metrics = json.loads(paths[0].read_text())
    assert metrics["seed"] == 7 and "meta_cost_mean" in metrics and metrics["collisions"] == 0
    with pytest.raises(ValueError, match="needs a checkpoint path"):
        make_driver("bc", scenario)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        make_driver(f"bc:{tmp_path / 'missing.pt'}", scenario)
    (tmp_path / "junk.pt").write_text("not a checkpoint")
    with pytest.raises(ValueError, match="not a readable torch checkpoint"):
        make_driver(f"bc:{tmp_path / 'junk.pt'}", scenario)


def test_policy_learns_a_known_map_and_rejects_bad_shapes(tmp_path):
    rng = np.random.default_rng(0)
    observations = rng.normal(size=(2000, 5, 5)).astype(np.float32)
    commands = rng.normal(size=(2000, 2)).astype(np.float32)
    actions = np.stack([np.tanh(observations[:, 1, 1]) * 2 + 0.5 * commands[:, 0],
                        0.1 * observations[:, 2, 2] + 0.05 * commands[:, 1]], axis=1).astype(np.float32)
    data = Transitions(observations, commands, actions, np.repeat(np.arange(20), 100))
    policy, history = train_policy(data, TrainConfig(epochs=30, batch_size=64, policy=PolicyConfig(hidden=(64, 64))))
    assert history.val_loss[history.best_epoch] < 0.05  # standardised: 1.0 is the mean predictor
    rmse_acc, rmse_steer = history.val_rmse[history.best_epoch]
    assert rmse_acc < 0.3 and rmse_steer < 0.02
    save_policy(tmp_path / "p.pt", policy, scenario="synthetic")
    again = load_policy(tmp_path / "p.pt")
    probe, probe_commands = torch.as_tensor(observations[:5]), torch.as_tensor(commands[:5])
    torch.testing.assert_close(again(probe, probe_commands), policy(probe, probe_commands))
    # the driver runs the folded network (statistics inside the layers): the same commands
    from mmpc.drivers import Observation

    ego = torch.zeros(5, 6)
    ego[:, 4:6] = probe_commands
    decision = PolicyDriver(policy).decide(Observation(ego, torch.zeros(5, 0, 4), None, observations[:5]))
    with torch.no_grad():
        expected = policy(probe, probe_commands)
    torch.testing.assert_close(torch.stack([decision.acceleration, decision.steering], dim=1), expected, atol=1e-5, rtol=1e-5)
    with pytest.raises(ValueError, match=r"shape \(B, 5, 5\)"):
        policy(torch.zeros(2, 4, 5), torch.zeros(2, 2))
    with pytest.raises(ValueError, match=r"`ego_command` must have shape \(2, 2\); got None"):
        policy(torch.zeros(2, 5, 5))
    with pytest.raises(ValueError, match="NaN"):
        train_policy(Transitions(observations * np.nan, commands, actions, data.episodes), TrainConfig(epochs=1))
    with pytest.raises(ValueError, match="`hidden`"):
        PolicyConfig(hidden=())
    with pytest.raises(ValueError, match="unknown key"):
        TrainConfig.from_dict({"epoch": 3})


def test_sb3_export_acts_like_the_cloned_policy(bc_run, demos_dir, tmp_path):
    import gymnasium as gym
    from stable_baselines3.common.policies import ActorCriticPolicy

    from mmpc.highway import command_to_action, env_config
    from mmpc.imitation.export import EgoCommandObservation, export_sb3, ppo_from_policy

    path = export_sb3(bc_run / "policy.pt", tmp_path / "sb3_policy.zip")
    sb3 = ActorCriticPolicy.load(str(path))
    policy = load_policy(bc_run / "policy.pt")
    data = dataset_transitions(open_dataset(demos_dir))
    flat = np.concatenate([data.observations.reshape(len(data.actions), -1), data.commands], axis=1)
    actions, _ = sb3.predict(flat, deterministic=True)
    with torch.no_grad():
        commands = policy(torch.as_tensor(data.observations), torch.as_tensor(data.commands))
    expected = np.stack([command_to_action(*c) for c in commands.tolist()])
    np.testing.assert_allclose(actions, expected, atol=1e-5)

    # PPO on the wrapped highway-env starts from the same actor; the wrapper reads what the driver reads
    scenario = short_cruise()
    env = gym.make(scenario.env_id, config=env_config(scenario))
    model = ppo_from_policy(bc_run / "policy.pt", env, n_steps=8, batch_size=8)
    ppo_actions, _ = model.predict(flat[:10], deterministic=True)
    np.testing.assert_allclose(ppo_actions, expected[:10], atol=1e-5)
    wrapped = EgoCommandObservation(gym.make(scenario.env_id, config=env_config(scenario)))
    observation, _ = wrapped.reset(seed=0)
    for _ in range(3):
        observation, *_ = wrapped.step(np.array([0.4, 0.1], dtype=np.float32))
    from mmpc.highway import RoadFrame, road_state

    state = road_state(wrapped.unwrapped, RoadFrame.of(wrapped.unwrapped))
    np.testing.assert_allclose(observation[-2:], state.ego[0, 4:6].numpy(), rtol=1e-5)
    np.testing.assert_allclose(observation[:-2], wrapped.unwrapped.observation_type.observe().ravel(), rtol=1e-6)
    env.close()
    wrapped.close()


@pytest.mark.slow
def test_dagger_round_trip_labels_the_learners_states(tmp_path):
    scenario = short_cruise(3.0)
    config = DaggerConfig(iterations=1, initial_episodes=2, episodes_per_iteration=2, lockstep=2, label_batch=16,
                          train=TrainConfig(epochs=5, batch_size=32, policy=PolicyConfig(hidden=(32,))))
    report = run_dagger(scenario, tmp_path, config)
    first, second = report["rounds"]
    assert first["source"] == "expert" and second["source"] == "learner"
    assert second["samples"] == first["samples"] + second["steps"]
    data = np.load(tmp_path / "data.npz")
    assert data["actions"].shape == (second["samples"], 2)
    assert len(np.unique(data["episodes"])) == 4
    assert (tmp_path / "policy.pt").is_file() and (tmp_path / "round_1" / "policy.pt").is_file()


def test_cli_evaluates_expert_and_policy_side_by_side_and_benchmarks_them(bc_run, tmp_path, capsys):
    from mmpc.cli import main

    policy = bc_run / "policy.pt"
    out = tmp_path / "eval"
    code = main(["imitate", "evaluate", "--drivers", f"mpc,bc:{policy}", "--names", "expert,bc", "--seeds", "3,4",
                 "--duration", "1", "--lockstep", "2", "--out", str(out)])
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    assert [e["driver"] for e in summary["summary"]] == ["mpc", f"bc:{policy}"]
    assert [(r["driver"], r["seed"]) for r in summary["episodes"]] == [
        ("mpc", 3), ("mpc", 4), (f"bc:{policy}", 3), (f"bc:{policy}", 4)]
    assert all(r["steps"] == 10 for r in summary["episodes"])
    assert "| collision rate |" in (out / "table.md").read_text()
    assert "expert" in capsys.readouterr().out

    bench = tmp_path / "bench.json"
    assert main(["imitate", "bench", "--policy", str(policy), "--steps", "5", "--out", str(bench)]) == 0
    report = json.loads(bench.read_text())
    assert report["rows"]["expert"]["steps"] == report["rows"]["policy"]["steps"] == 5
    assert report["speedup_mean"] == pytest.approx(report["rows"]["expert"]["mean_ms"] / report["rows"]["policy"]["mean_ms"])
