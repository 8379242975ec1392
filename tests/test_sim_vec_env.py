"""The safe environments on the batched simulator: SB3 VecEnv and gymnasium VectorEnv, their
observations, rewards and infos against the highway-env environments', auto-reset, bad input."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from mmpc.rl.config import RewardConfig, SafeEnvConfig
from mmpc.rl.envs import SafeHighwayEnv
from mmpc.rl.safety import SafetyLayer
from mmpc.rl.vec_env import SafeVecEnv, SafeVectorEnv
from mmpc.scenario import build_mpc, load_scenario
from mmpc.sim.observation import kinematics_observation
from mmpc.sim.reward import highway_reward

SCENARIO = dataclasses.replace(load_scenario("rl_highway_fast"), sim="batched", duration=1.0)
CONFIG = SafeEnvConfig()
REWARD = RewardConfig()


def test_sb3_vec_env_steps_every_environment_with_the_highway_env_meaning():
    venv = SafeVecEnv(4, SCENARIO, CONFIG, REWARD, seed=0)
    venv.seed(7)
    observations = venv.reset()
    reference = SafeHighwayEnv(SCENARIO, CONFIG, REWARD)
    assert venv.observation_space == reference.observation_space and venv.action_space == reference.action_space
    assert observations.shape == (4, reference.observation_space.shape[0]) and observations.dtype == np.float32
    assert [info["episode_seed"] for info in venv.reset_infos] == [7, 8, 9, 10]
    kinematics = kinematics_observation(venv.batch.world.sim.state, venv.batch.world.sim.config, vehicles_count=CONFIG.kinematics_vehicles)
    assert np.allclose(observations[:, :kinematics[0].numel()], kinematics.flatten(1).clamp(-1, 1).numpy(), atol=1e-6)
    venv.step_async(np.array([4, 4, 5, 6]))  # keep lane at 15 / 15 / 20 / 25 m/s
    observations, rewards, dones, infos = venv.step_wait()
    reference.reset(seed=0)
    _, _, _, _, reference_info = reference.step(4)
    assert set(infos[0]) - {"TimeLimit.truncated"} == set(reference_info)
    for info in infos:
        assert info["frames"] == CONFIG.decision_frames and not info["crashed"] and info["goal"][1] in (15.0, 20.0, 25.0)
    # every frame's reward is in [0, 1] minus the penalty: 5 frames
    assert np.all(rewards <= CONFIG.decision_frames + 1e-6) and np.all(rewards >= -CONFIG.decision_frames * (1 + CONFIG.intervention_penalty))
    assert not dones.any()
    venv.step_async(np.array([4, 4, 5, 6]))
    _, _, dones, infos = venv.step_wait()  # 1 s episodes: time is up, auto-reset
    assert dones.all() and all(info["TimeLimit.truncated"] and "terminal_observation" in info for info in infos)
    assert bool((venv.batch.world.sim.steps == 0).all()) and [i["episode_seed"] for i in venv.reset_infos] != [7, 8, 9, 10]
    reference.close()


def test_reward_is_highway_env_s_reward_summed_over_the_frames():
    config = dataclasses.replace(CONFIG, intervention_penalty=0.0, decision_frames=1)
    venv = SafeVecEnv(3, SCENARIO, config, REWARD, seed=1)
    venv.reset()
    venv.step_async(np.array([5, 5, 5]))
    _, rewards, _, _ = venv.step_wait()
    expected = highway_reward(venv.batch.world.sim.state, venv.batch.world.sim.config).double().numpy()
    assert np.allclose(rewards, expected, atol=1e-6)


def test_gymnasium_vector_env_resets_from_seeds_and_reports_final_observations():
    first, second = SafeVectorEnv(3, SCENARIO, CONFIG, REWARD), SafeVectorEnv(3, SCENARIO, CONFIG, REWARD)
    observations, infos = first.reset(seed=11)
    again, _ = second.reset(seed=11)
    assert np.array_equal(observations, again) and infos["episode_seed"].tolist() == [11, 12, 13]
    assert first.observation_space.shape == (3, first.single_observation_space.shape[0])
    for step in range(2):
        observations, rewards, terminated, truncated, infos = first.step(np.array([1, 4, 7]))
    assert truncated.all() and not terminated.any() and rewards.shape == (3,)
    assert infos["_final_obs"].all() and infos["final_obs"][0].shape == first.single_observation_space.shape
    assert first.observation_space.contains(observations)


def test_continuous_actions_drive_too():
    venv = SafeVecEnv(2, SCENARIO, CONFIG, REWARD, continuous=True, seed=2)
    venv.reset()
    venv.step_async(np.array([[0.0, 1.0], [1.0, -1.0]], dtype=np.float32))
    _, _, _, infos = venv.step_wait()
    assert infos[0]["goal"][1] == pytest.approx(CONFIG.speed_range[1]) and infos[1]["goal"][1] == pytest.approx(CONFIG.speed_range[0])


def test_bad_input_is_refused():
    venv = SafeVecEnv(2, SCENARIO, CONFIG, REWARD)
    with pytest.raises(RuntimeError, match="reset"):
        venv.step_async(np.array([0, 0]))
        venv.step_wait()
    venv.reset()
    with pytest.raises(ValueError, match=r"environment 1: `action` must be an int in \[0, 12\)"):
        venv.step_async(np.array([0, 99]))
        venv.step_wait()
    with pytest.raises(ValueError, match="`num_envs` must be an int >= 1"):
        SafeVecEnv(0, SCENARIO, CONFIG, REWARD)
    with pytest.raises(ValueError, match="--sim highway-env"):  # the world the scenario names must run it
        load_scenario("cruise_ngsim", {"sim": "batched"})
    assert torch.equal(venv.batch.world.sim.steps, torch.zeros(2, dtype=torch.long))  # the refused step moved nothing


def test_rl_train_on_the_batched_simulator_records_the_world(tmp_path):
    import yaml

    from mmpc.cli.main import main

    out = tmp_path / "run"
    argv = ["rl", "train", "--algo", "dqn", "--config", "smoke", "--sim", "batched", "--timesteps", "32", "--no-eval",
            "--compile", "off", "--out", str(out)]
    assert main(argv) == 0
    assert yaml.safe_load((out / "config.yaml").read_text())["config"]["scenario"]["sim"] == "batched"
    assert (out / "model.zip").exists() and any((out / "tb").rglob("events.out.tfevents.*"))


def test_the_verified_layer_executes_only_commands_that_keep_a_way_out():
    """``env.verify``: every frame's executed command verifies at the state it was taken in (or,
    where none did, the stored fail-safe drove and says so); an override is an intervention."""
    config = dataclasses.replace(CONFIG, verify=True)
    venv = SafeVecEnv(4, dataclasses.replace(SCENARIO, duration=2.0), config, REWARD, seed=0)
    layer = venv.layer
    executed = []
    guarded = layer._guarded

    def record(observation, control):
        result = guarded(observation, control)
        executed.append((observation.to("cpu"), control, result))
        return result

    layer._guarded = record
    venv.reset()
    for _ in range(2):
        venv.step_async(np.array([11, 0, 11, 3]))  # the grid's fastest goals and its slowest
        venv.step_wait()
    assert len(executed) == 2 * config.decision_frames
    for observation, asked, control in executed:
        assert bool((control.verified ^ control.failsafe).all())
        mask = observation.vehicle_mask
        verdict = layer.guard.verifier.check(observation.ego, observation.vehicles, mask, control.acceleration[:, None].cpu(),
                                             control.steering[:, None].cpu())
        assert bool((verdict.verified[:, 0] | control.failsafe.cpu()).all())
        overridden = (control.acceleration != asked.acceleration) | (control.steering != asked.steering)
        assert bool((control.intervention | ~overridden).all())


def test_verification_needs_its_verifier():
    config = dataclasses.replace(CONFIG, verify=True)
    with pytest.raises(ValueError, match="verifier"):
        SafetyLayer(build_mpc(SCENARIO), config)
    assert SafetyLayer.for_scenario(SCENARIO, config).guard is not None
    assert SafetyLayer.for_scenario(SCENARIO, dataclasses.replace(CONFIG, verify=False)).guard is None
