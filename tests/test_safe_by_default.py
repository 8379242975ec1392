"""Safe by default (issue 66): the safety layer verifies unless told not to, in highway-env's
training environments as on the batched simulator; the guarded command is written once; runs
recorded before the check existed read as they were trained."""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest
import torch
import yaml

import mmpc.drivers.verified as verified_module
import mmpc.rl.safety as safety_module
from mmpc.config import load_config, to_dict
from mmpc.drivers import Observation, make_driver
from mmpc.problem import ego_state
from mmpc.rl.config import RLConfig, SafeEnvConfig
from mmpc.rl.envs import SafeHighwayEnv
from mmpc.rl.runs import load_run, recorded_config
from mmpc.rl.vec_env import SafeVecEnv

RECIPES = ("smoke", "high_speed", "high_speed_task", "cruise_task")


@pytest.fixture(scope="module")
def smoke() -> RLConfig:
    """The CI-sized configuration: 2 s episodes, a cheap optimizer."""
    return load_config(RLConfig, "smoke")


def test_the_layer_verifies_by_default_in_every_shipped_recipe():
    assert SafeEnvConfig().verify
    for name in RECIPES:
        assert load_config(RLConfig, name).env.verify, name
    with pytest.raises(ValueError, match="`verify` must be true or false"):
        SafeEnvConfig(verify="yes")
    assert gym.make("mmpc/SafeHighway-v0").unwrapped.layer.guard is not None


def test_highway_env_training_envs_verify_each_under_its_own_id(smoke, one_thread):
    """Environments get distinct ids from their layer, so each keeps its own stored fail-safe;
    every frame's command verified or the fail-safe drove (infos count both); a reset forgets
    only its own environment's fail-safe."""
    assert smoke.env.verify and smoke.scenario.sim == "highway-env"
    venv = SafeVecEnv(2, smoke.scenario, smoke.env, smoke.reward)
    assert venv.batch.ids.tolist() == [0, 1] and venv.layer.guard is not None
    venv.reset()
    fastest = smoke.env.num_actions - 1
    for _ in range(2):
        _, _, _, infos = venv.step(np.array([fastest, 0]))
        for info in infos:
            assert info["verified_frames"] + info["failsafe_frames"] == info["frames"] >= 1
    assert set(venv.layer.guard.stored_ids()) == {0, 1}
    # single environments that share a layer keep their fail-safes apart too, and a reset drops its own
    first = SafeHighwayEnv(smoke.scenario, smoke.env, smoke.reward)
    second = SafeHighwayEnv(smoke.scenario, smoke.env, smoke.reward, layer=first.layer)
    assert (first.env_id, second.env_id) == (0, 1)
    first.reset(seed=1)
    second.reset(seed=2)
    first.step(fastest)
    second.step(fastest)
    assert set(first.layer.guard.stored_ids()) == {0, 1}
    first.reset(seed=3)
    assert set(first.layer.guard.stored_ids()) == {1}
    # without the check the infos say nothing of it
    plain = SafeHighwayEnv(smoke.scenario, dataclasses.replace(smoke.env, verify=False), smoke.reward)
    plain.reset(seed=3)
    assert plain.layer.guard is None and "verified_frames" not in plain.step(0)[4]
    for env in (venv, first, second, plain):
        env.close()


def test_one_guarded_command_serves_the_verified_driver_and_the_layer(smoke, monkeypatch):
    """The verified driver and the RL layer take their command from one function."""
    assert safety_module.guarded_command is verified_module.guarded_command
    calls = []
    original = verified_module.guarded_command

    def counting(*args, **kwargs):
        calls.append(type(args[0]).__name__)
        return original(*args, **kwargs)

    monkeypatch.setattr(verified_module, "guarded_command", counting)
    monkeypatch.setattr(safety_module, "guarded_command", counting)
    scenario = smoke.scenario
    ego = ego_state(0.0, 4.0, 0.0, 25.0)
    observation = Observation(ego, torch.tensor([[[30.0, 4.0, 20.0, 0.0]]]), env_ids=torch.tensor([0]))
    driver = make_driver("verified:mpc", scenario)
    driver.reset(1)
    decision = driver.decide(observation)
    assert calls == ["Guard"] and decision.verified is not None
    layer = safety_module.SafetyLayer.for_scenario(scenario, smoke.env, warm_starts=False)
    control = layer.frame(observation, layer.discrete_commands(ego, torch.tensor([0])), 0.0)
    assert calls == ["Guard", "Guard"] and control.verified is not None


def test_a_run_recorded_before_the_check_reads_as_it_was_trained(tmp_path, caplog):
    values = to_dict(RLConfig())
    del values["env"]["verify"]
    run = {"algo": "ppo", "env": "safe", "action": "discrete", "config": values}
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(run, sort_keys=False))
    with caplog.at_level("WARNING", logger="mmpc.rl.runs"):
        assert recorded_config(tmp_path).env.verify is False
    assert "env.verify: false" in caplog.text and "verified:sb3" in caplog.text
    caplog.clear()
    values["env"]["verify"] = True  # a run recorded since says what it trained with
    (tmp_path / "config.yaml").write_text(yaml.safe_dump({**run, "config": values}, sort_keys=False))
    with caplog.at_level("WARNING", logger="mmpc.rl.runs"):
        assert recorded_config(tmp_path).env.verify is True
    assert "env.verify" not in caplog.text
    for name in ("high_speed_ppo", "cruise_task_ppo"):  # the shipped agents were trained without the check
        assert load_run(name).config.env.verify is False
