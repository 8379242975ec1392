"""mmpc.rl: the safe goal-choosing environments, the batched VecEnv, training with TensorBoard
scalars, evaluation and the sb3 driver. Real highway-env, real SB3, real event files."""

from __future__ import annotations

import dataclasses
import json
import math

import gymnasium as gym
import numpy as np
import pytest
import torch
import yaml

import mmpc.rl
import mmpc.rl.runs
from mmpc.highway.runner import run_episode
from mmpc.drivers import Observation, make_driver
from mmpc.highway import HighwayEpisode
from mmpc.problem import ego_state
from mmpc.config import ConfigError, from_dict, load_config, to_dict
from mmpc.rl.config import RLConfig, TrainConfig
from mmpc.rl.reward import frame_reward
from mmpc.rl.safety import SafetyLayer
from mmpc.scenario import load_scenario


@pytest.fixture(scope="module")
def smoke() -> RLConfig:
    """The CI-sized configuration: 2 s episodes, a cheap optimizer."""
    return load_config(RLConfig, "smoke")


def make(env_id: str, smoke: RLConfig) -> gym.Env:
    return gym.make(env_id, scenario=smoke.scenario, config=smoke.env, reward=smoke.reward)


@pytest.mark.parametrize("env_id", mmpc.rl.ENV_IDS)
def test_check_env_passes_on_every_registered_id(env_id, smoke, one_thread):
    from gymnasium.utils.env_checker import check_env as gym_check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = make(env_id, smoke)
    try:
        gym_check_env(env.unwrapped, skip_render_check=True)
        sb3_check_env(env.unwrapped, warn=True)
    finally:
        env.close()
    expected = gym.spaces.Box if "Continuous" in env_id else gym.spaces.Discrete
    assert isinstance(env.action_space, expected)


def test_step_info_and_observation(smoke, one_thread):
    env = make("mmpc/SafeHighway-v0", smoke)
    observation, _ = env.reset(seed=3)
    grid = smoke.env.num_discrete_goals
    assert observation.shape == (25 + 3 * grid,)
    features = observation[25:].reshape(grid, 3)
    assert set(np.unique(features[:, 0])) <= {0.0, 1.0} and features[:, 0].sum() >= 1  # some goal is feasible
    _, reward, terminated, truncated, info = env.step(grid - 1)  # right neighbour lane, fastest speed
    for key in ("intervention", "feasible_goals", "solve_ms", "residuals", "agent_feasible", "mean_speed"):
        assert key in info
    assert info["frames"] == smoke.env.decision_frames
    assert info["solve_ms"] > 0 and info["feasible_goals"] >= 1
    assert set(info["residuals"]) == {"obstacle", "acceleration", "nonholonomic"}
    # the summed reward of k frames lies in k x [0, 1] minus the penalties
    assert -smoke.env.intervention_penalty * info["frames"] <= reward <= info["frames"]
    assert info["intervention"] == (info["intervention_frames"] > 0)
    assert not terminated
    env.close()


def test_frame_reward_equals_highway_envs_own(smoke, one_thread):
    episode = HighwayEpisode(smoke.scenario, seed=5)
    try:
        for acceleration, steering in ((1.0, 0.0), (0.0, 0.05), (-2.0, -0.05)):
            episode.apply(acceleration, steering)
            assert frame_reward(episode, smoke.reward) == pytest.approx(episode.reward, abs=1e-9)
    finally:
        episode.close()


def test_layer_follows_a_feasible_agent_and_intervenes_otherwise(smoke, one_thread):
    layer = SafetyLayer.for_scenario(smoke.scenario, smoke.env)
    ego = ego_state([0.0, 0.0], [4.0, 4.0], [0.0, 0.0], [25.0, 25.0])
    # a slow car 50 m ahead in the ego's lane (both environments); the left lane is free
    vehicles = torch.tensor([[[50.0, 4.0, 10.0, 0.0]], [[50.0, 4.0, 10.0, 0.0]]])
    commands = torch.tensor([[0.0, 25.0],    # env 0: left lane at 25 m/s: free
                             [4.0, 25.0]])   # env 1: through the slow car at 25 m/s: infeasible
    safe = layer.plan(Observation(ego, vehicles), commands)
    assert safe.agent_feasible.tolist() == [True, False]
    assert safe.intervention.tolist() == [False, True]
    index = safe.plan.selection.index
    assert int(index[0]) == 0
    # env 1 executes the feasible goal nearest to its own in (dv / 5 m/s, dy / 4 m)
    goals, feasible = safe.plan.problem.goals[1], safe.plan.result.feasible[1]
    distance = torch.hypot((goals[:, 0] - goals[0, 0]) / (8.0 * 5.0), (goals[:, 1] - goals[0, 1]) / 4.0)
    distance[~feasible] = math.inf
    assert bool(feasible[index[1]]) and int(index[1]) == int(distance.argmin())
    assert not bool(safe.fallback.any())


def test_discrete_and_continuous_commands(smoke):
    layer = SafetyLayer.for_scenario(smoke.scenario, smoke.env)
    ego = ego_state([0.0, 0.0], [0.0, 8.0], [0.0, 0.0], [20.0, 20.0])
    speeds = len(smoke.env.speeds)
    # offset -1 from lane 0 clamps to lane 0; offset +1 from lane 2 (the right lane) clamps to lane 2
    commands = layer.discrete_commands(ego, torch.tensor([0, 2 * speeds + 1]))
    assert commands.tolist() == [[0.0, smoke.env.speeds[0]], [8.0, smoke.env.speeds[1]]]
    continuous = layer.continuous_commands(ego, torch.tensor([[1.0, -1.0], [-0.5, 1.0]]))
    assert continuous.tolist() == [[4.0, smoke.env.speed_range[0]], [6.0, smoke.env.speed_range[1]]]
    with pytest.raises(ValueError, match="discrete actions must lie in"):
        layer.discrete_commands(ego, torch.tensor([0, 99]))
    with pytest.raises(ValueError, match="must be finite"):
        layer.continuous_commands(ego, torch.tensor([[math.nan, 0.0], [0.0, 0.0]]))


def test_batched_vecenv_matches_separate_solves(smoke, one_thread):
    """One optimizer call per frame for all environments drives as each environment alone."""
    from stable_baselines3.common.vec_env import DummyVecEnv

    from mmpc.rl.envs import SafeHighwayEnv
    from mmpc.rl.vec_env import SafeVecEnv

    results = []
    alone = lambda: SafeHighwayEnv(smoke.scenario, smoke.env, smoke.reward)  # noqa: E731
    for venv in (SafeVecEnv(3, smoke.scenario, smoke.env, smoke.reward), DummyVecEnv([alone] * 3)):
        venv.seed(11)
        observations = [venv.reset()]
        rewards = []
        for action in ([0, 3, 5], [4, 1, 2]):
            observation, reward, _, _ = venv.step(np.array(action))
            observations.append(observation)
            rewards.append(reward)
        venv.close()
        results.append((np.stack(observations), np.stack(rewards)))
    (obs_batched, rew_batched), (obs_separate, rew_separate) = results
    np.testing.assert_allclose(obs_batched, obs_separate, atol=1e-3)
    np.testing.assert_allclose(rew_batched, rew_separate, atol=1e-3)


def test_config_rejects_unknown_keys_and_wrong_action_spaces(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump({"env": {"decision_frame": 5}}))
    with pytest.raises(ValueError, match="unknown key"):
        load_config(RLConfig, path)
    with pytest.raises(ValueError, match="cannot train on continuous"):
        RLConfig(action="continuous").action_for("dqn")
    with pytest.raises(ValueError, match="must be >="):
        RLConfig(env=dataclasses.replace(RLConfig().env, speeds=(40.0,)))
    assert from_dict(RLConfig, to_dict(RLConfig())) == RLConfig()


def test_smoke_training_writes_tensorboard_scalars_eval_and_drives(smoke, tmp_path, one_thread):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from mmpc.rl.callbacks import SCALAR_TAGS
    from mmpc.rl.train import train

    out = tmp_path / "run"
    summary = train(smoke, "dqn", 24, out, seed=1)
    (run_dir,) = (out / "tb").iterdir()
    events = EventAccumulator(str(run_dir))
    events.Reload()
    tags = set(events.Tags()["scalars"])
    assert set(SCALAR_TAGS) <= tags
    assert "rollout/exploration_rate" in tags  # SB3's own scalars in the same files
    for tag in SCALAR_TAGS:
        values = [event.value for event in events.Scalars(tag)]
        assert values and all(math.isfinite(v) for v in values)
    assert 0.0 <= events.Scalars("safety/intervention_rate")[-1].value <= 1.0
    assert events.Scalars("driving/mean_speed")[-1].value > 5.0

    written = json.loads((out / "eval.json").read_text())
    for key in ("collision_rate", "mean_speed", "mean_return", "intervention_rate", "episodes"):
        assert written[key] == summary[key]
    assert written["episodes"] == smoke.train.eval_episodes
    assert written["seeds"] == [smoke.train.eval_seed + i for i in range(smoke.train.eval_episodes)]
    assert (out / "model.zip").is_file() and list((out / "checkpoints").glob("dqn_*_steps.zip"))

    # the report reads the same event files and eval.json back
    from mmpc.rl.report import plot_curves, results_table

    table, figures = results_table({"safe": out})
    assert figures["safe"]["collision_rate"] == summary["collision_rate"] and "| safe | dqn | safe | 24 |" in table
    assert figures["safe"]["training_crashes_per_1e5_steps"] == events.Scalars("safety/crashes")[-1].value / 24 * 1e5
    assert plot_curves({"safe": out}, tmp_path / "curves.png").stat().st_size > 10_000

    # the trained agent drives through the driver registry, its goals through the safety layer
    driver = make_driver(f"sb3:{out / 'model.zip'}", smoke.scenario)
    result = run_episode(smoke.scenario, seed=2, driver=driver)
    assert len(result.records) == round(smoke.scenario.duration * smoke.scenario.frequency)
    assert all(record.goal_index >= 0 and record.feasible_goals >= 1 for record in result.records)


def test_the_callback_counts_every_finished_episode_and_its_collisions():
    from mmpc.rl.callbacks import SafetyTensorboardCallback

    callback = SafetyTensorboardCallback(log_every=10**9, window=2)
    for crashed in ([True, False, None], [True, None, True], [False, False, False]):
        callback.locals = {"infos": [{} if c is None else {"crashed": c} for c in crashed],
                           "dones": np.array([c is not None for c in crashed])}
        callback._on_step()
    assert (callback.total_crashes, callback.total_episodes) == (3, 7)
    assert list(callback.crashes) == [False, False]  # the rate's window keeps only the last two


def test_plain_highway_baseline_trains_and_its_meta_actions_drive(smoke, tmp_path, one_thread):
    from mmpc.rl.train import train

    out = tmp_path / "plain"
    summary = train(smoke, "dqn", 16, out, env_kind="highway", seed=1)
    assert summary["intervention_rate"] is None and summary["episodes"] == smoke.train.eval_episodes
    driver = make_driver(f"sb3:{out / 'model.zip'}", smoke.scenario)
    result = run_episode(smoke.scenario, seed=2, driver=driver)
    speeds = [record.v for record in result.records]
    assert len(speeds) == 20 and 15.0 < np.mean(speeds) < 32.0
    # lane keeping: the meta-action controller holds the ego near a lane centre
    assert all(abs(record.y - 4.0 * round(record.y / 4.0)) < 2.0 for record in result.records)


def test_the_plain_baseline_trains_on_the_batched_world_and_drives_both_worlds_through_the_runner(smoke, tmp_path, one_thread):
    """--env plain: no layer, the recipe's world and traffic; the run drives as MetaActionDriver in
    either world, and its evaluation (highway-env, the reference) counts no interventions."""
    from mmpc.rl.runs import load_run
    from mmpc.rl.train import train

    out = tmp_path / "plain"
    config = dataclasses.replace(smoke, scenario=smoke.scenario.replace(sim="batched"))
    summary = train(config, "ppo", 64, out, env_kind="plain", seed=1)
    assert summary["env"] == "plain" and summary["intervention_rate"] is None and summary["episodes"] == smoke.train.eval_episodes
    run = load_run(out / "model.zip")
    assert run.env_kind == "plain" and run.model.action_space.n == 5 and run.model.observation_space.shape == (25,)
    for sim in ("batched", "highway-env"):
        scenario = smoke.scenario.replace(sim=sim)
        driver = make_driver(f"sb3:{out / 'model.zip'}", scenario)
        assert type(driver).__name__ == "MetaActionDriver"
        result = run_episode(scenario, seed=2, driver=driver)
        assert len(result.records) == 20 and all(15.0 < record.v < 32.0 for record in result.records)
    with pytest.raises(ConfigError, match="DiscreteMetaAction"):
        train(config, "sac", 16, tmp_path / "plain_sac", env_kind="plain")


def test_a_stopped_run_resumes_from_its_latest_checkpoint(smoke, tmp_path, one_thread):
    """--resume: the run goes on from its latest checkpoint (the model's steps, DQN's replay buffer,
    the TensorBoard run and the crash log continued); other settings or no checkpoint are refused."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from mmpc.files import OutputFolderError
    from mmpc.rl.checkpoints import latest_checkpoint
    from mmpc.rl.train import train

    config = dataclasses.replace(smoke, scenario=smoke.scenario.replace(sim="batched"),
                                 train=dataclasses.replace(smoke.train, n_envs=4, checkpoint_every=32))
    out = tmp_path / "dqn"
    train(config, "dqn", 48, out, env_kind="plain", evaluate_after=False)
    (out / "checkpoints" / "dqn_48_steps.zip").unlink()  # as if stopped before its end
    (out / "crashes.csv").write_text((out / "crashes.csv").read_text() + "40,0,7,3,0.6,[1, 1, 1]\n")
    checkpoint = latest_checkpoint(out / "checkpoints", "dqn")
    assert checkpoint.steps == 32 and checkpoint.replay_buffer is None  # the buffer of 48 went with a newer one
    with pytest.raises(OutputFolderError, match="neither resumes nor overwrites"):
        train(config, "dqn", 96, out, env_kind="plain", evaluate_after=False)
    with pytest.raises(OutputFolderError, match=r"differ in \['seed'\]"):
        train(config, "dqn", 96, out, env_kind="plain", seed=5, evaluate_after=False, resume=True)
    from mmpc.cli.main import main

    assert main(["rl", "train", "--resume", "--seed", "0", "--out", str(out), "--timesteps", "96"]) == 2  # even seed 0
    train(config, "dqn", 96, out, env_kind="plain", evaluate_after=False, resume=True)
    record = yaml.safe_load((out / "config.yaml").read_text())
    assert record["resumed_at"] == [32] and record["trained_timesteps"] == 96 and record["timesteps"] == 96
    assert latest_checkpoint(out / "checkpoints", "dqn").steps == 96
    assert sorted(p.name for p in (out / "checkpoints").glob("*.pkl")) == ["dqn_replay_buffer_96_steps.pkl"]
    assert "40,0,7,3,0.6" in (out / "crashes.csv").read_text()  # the rows before the resume are kept
    (folder,) = (out / "tb").iterdir()  # one TensorBoard run, its steps going on past the checkpoint
    events = EventAccumulator(str(folder))
    events.Reload()
    steps = [event.step for event in events.Scalars("driving/mean_speed")]
    assert max(steps) == 96 and 32 in steps
    episodes = [(event.step, event.value) for event in events.Scalars("safety/episodes")]
    at_checkpoint = max(value for step, value in episodes if step <= 32)
    assert at_checkpoint > 0 and min(value for step, value in episodes if step > 32) >= at_checkpoint  # counted on
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(OutputFolderError, match="no training run to resume"):
        train(config, "dqn", 96, empty, env_kind="plain", evaluate_after=False, resume=True)


def test_rl_command_lines_reject_bad_arguments(capsys, tmp_path):
    import re

    from mmpc.cli.main import main

    assert main(["rl", "train", "--algo", "dqn", "--config", "smoke", "--timesteps", "0", "--out", str(tmp_path)]) == 2
    assert "--timesteps must be >= 1" in capsys.readouterr().err
    assert main(["rl", "report", "no-label-here"]) == 2
    assert "expected LABEL=RUN_DIR" in capsys.readouterr().err
    assert main(["rl", "train", "--algo", "dqn", "--config", "no_such_config", "--timesteps", "8", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err  # one line, no traceback
    assert err.count("\n") == 1 and err.startswith("mmpc rl train: error: FileNotFoundError: RLConfig 'no_such_config'")
    assert re.search(r"shipped rl: \[.*'smoke'", err), err


@pytest.mark.parametrize("algo", ["ppo", "sac"])
def test_ppo_and_sac_train_on_their_action_spaces(algo, smoke, tmp_path, one_thread):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from mmpc.rl.runs import load_run
    from mmpc.rl.train import train

    out = tmp_path / algo
    assert train(smoke, algo, 16, out, seed=0, evaluate_after=False) == {}
    run = load_run(out / "model.zip")
    assert run.algo == algo and run.env_kind == "safe" and run.continuous == (algo == "sac")
    (folder,) = (out / "tb").iterdir()
    events = EventAccumulator(str(folder))
    events.Reload()
    assert {"solver/solve_ms", "safety/intervention_rate"} <= set(events.Tags()["scalars"])


def test_rl_default_scenario_keeps_the_high_speed_ellipse_and_band():
    """Fast traffic: the RL scenario (a shipped file, RLConfig's default) has the high-speed
    scenario's obstacle ellipse and heading band (not cruise's 13 degrees); the two must not drift apart."""
    from mmpc.scenario import load_scenario

    keys = ("ellipse_a", "ellipse_b", "max_heading_deg", "heading_target_deg")
    high_speed, rl = load_scenario("high_speed").optimizer, RLConfig().scenario.optimizer
    assert [getattr(rl, k) for k in keys] == [getattr(high_speed, k) for k in keys] == [8.0, 3.0, 8.0, 7.2]
    assert load_config(RLConfig, "smoke").scenario.optimizer.ellipse == (8.0, 3.0)  # smoke starts from it


def test_the_defaults_are_the_documented_training_run():
    """RLConfig() is what configs/rl/safe_highway.yaml used to restate (the README's run); where the
    two had drifted apart, the YAML's values won except the heading target the test above keeps."""
    config = RLConfig()
    assert (config.train.n_envs, config.train.log_every, config.train.checkpoint_every) == (8, 400, 2000)
    assert config.scenario.objective.near_lane_speeds == (12.0, 20.0) and config.scenario.seeds == (0,)
    assert config.algorithms["dqn"]["gradient_steps"] == 2 and config.algorithms["ppo"]["n_steps"] == 128
    assert config.algorithms["sac"]["policy_kwargs"] == {"net_arch": [256, 256]}


#: configs/rl/safe_highway.yaml as shipped before the RL config named its scenario (a whole scenario inline).
OLD_SAFE_HIGHWAY = """
scenario:
  name: rl_highway_fast
  duration: 30.0
  frequency: 10.0
  seeds: [0]
  env_id: highway-fast-v0
  lanes: 3
  objective: {type: cruise, v_cruise: 25.0, near_lane_speeds: [12.0, 20.0], near_lanes: 1}
  ego: {speed: 25.0, lane: null}
  traffic: {type: idm, vehicles_count: 20, vehicles_density: 1.0, target_speeds: null, window: null,
            initial_clearance: 10.0, lane_changes: true}
  optimizer: {ellipse_a: 8.0, ellipse_b: 3.0, max_heading_deg: 8.0, v_max: 30.0}
  mpc: {num_obstacles: 6, ignore_behind: 20.0, command_window: 0.3, road_margin: 1.0}
env: {decision_frames: 5, lane_offsets: [-1, 0, 1], speeds: [15.0, 20.0, 25.0, 28.0], lateral_range: 1.0,
      speed_range: [10.0, 28.0], solver_features: true, intervention_penalty: 0.1, intervention_speed_scale: 5.0}
reward: {collision_reward: -1.0, right_lane_reward: 0.1, high_speed_reward: 0.4, reward_speed_range: [20.0, 30.0],
         normalize: true}
train: {n_envs: 8, log_every: 400, checkpoint_every: 2000, eval_episodes: 50, eval_seed: 100000, eval_envs: 10,
        torch_threads: 1}
algorithms:
  dqn: {learning_rate: 5.0e-4, buffer_size: 15000, learning_starts: 200, batch_size: 32, gamma: 0.8, train_freq: 1,
        gradient_steps: 2, target_update_interval: 50, exploration_fraction: 0.7, policy_kwargs: {net_arch: [256, 256]}}
  ppo: {n_steps: 128, batch_size: 64, n_epochs: 10, learning_rate: 5.0e-4, gamma: 0.8, policy_kwargs: {net_arch: [256, 256]}}
  sac: {learning_rate: 5.0e-4, buffer_size: 15000, learning_starts: 200, batch_size: 64, gamma: 0.8,
        policy_kwargs: {net_arch: [256, 256]}}
"""


def test_an_old_rl_yaml_with_an_inline_scenario_still_loads(tmp_path):
    path = tmp_path / "safe_highway.yaml"
    path.write_text(OLD_SAFE_HIGHWAY)
    old = load_config(RLConfig, path)
    # what it trained with: today's defaults but the heading target the shipped file left unset, and
    # cold solves (the default scenario warm-starts since; the old file's runs stay as trained)
    new = RLConfig()
    assert old == dataclasses.replace(new, scenario=new.scenario.replace(
        optimizer=dataclasses.replace(new.scenario.optimizer, heading_target_deg=None),
        mpc=dataclasses.replace(new.scenario.mpc, warm_iterations=0)))


def test_the_config_an_old_trained_run_recorded_still_loads(tmp_path, caplog):
    """rl/train.py wrote config.yaml with RLConfig.to_dict(): the scenario inline, with the
    mpc.compile and mpc.wheelbase keys of then; load_run reads it (warning about the retired keys)."""
    from mmpc.rl.runs import load_run

    old = yaml.safe_load(OLD_SAFE_HIGHWAY)
    old["scenario"]["mpc"].update(wheelbase=5.0, compile="auto", obstacle_lookahead=3.0, prediction="lanes")
    old["action"] = None
    run = {"algo": "dqn", "env": "safe", "action": "discrete", "timesteps": 10000, "seed": 0, "config": old}
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(run, sort_keys=False))
    with caplog.at_level("WARNING", logger="mmpc.scenario"):
        config = from_dict(RLConfig, yaml.safe_load((tmp_path / "config.yaml").read_text())["config"])
    assert "mpc.compile" in caplog.text and "mpc.wheelbase" in caplog.text
    assert config.scenario.mpc == dataclasses.replace(RLConfig().scenario.mpc, warm_iterations=0)  # cold, as trained
    assert config.train == RLConfig().train
    caplog.clear()
    (tmp_path / "model.zip").write_bytes(b"")  # load_run reads the config, then fails on this empty model
    with caplog.at_level("WARNING", logger="mmpc.scenario"), pytest.raises(Exception) as failure:
        load_run(tmp_path / "model.zip")
    assert "config.yaml: config: scenario" in caplog.text and "RLConfig" not in str(failure.value)


@pytest.mark.parametrize("length", [5.0, 4.0])
def test_meta_action_steering_turns_highway_envs_bicycle_at_the_asked_rate(length):
    """The meta-action controller inverts highway-env's kinematic bicycle with the scenario's
    vehicle length (the authors' cars are 4 m, highway-env's 5 m): a real highway-env vehicle of
    that length, stepped for 10 ms with the steering, turns at the asked heading rate."""
    from highway_env.road.road import Road, RoadNetwork
    from highway_env.vehicle.kinematics import Vehicle

    from mmpc.rl.meta_actions import bicycle_steering

    rates, speeds = torch.tensor([-0.3, -0.05, 0.0, 0.02, 0.25]), torch.tensor([8.0, 15.0, 20.0, 25.0, 30.0])
    steering = bicycle_steering(rates, speeds, length)
    turned = []
    for delta, speed in zip(steering.tolist(), speeds.tolist()):
        vehicle = Vehicle(Road(RoadNetwork.straight_road_network(lanes=1)), [10.0, 0.0], heading=0.0, speed=speed)
        vehicle.LENGTH = length
        vehicle.act({"steering": delta, "acceleration": 0.0})
        vehicle.step(0.01)
        turned.append(vehicle.heading / 0.01)
    assert turned == pytest.approx(rates.tolist(), abs=1e-6)
    other = bicycle_steering(rates, speeds, 9.0 - length)  # the other length asks for another angle
    assert not torch.allclose(other[rates != 0], steering[rates != 0])


def test_meta_action_driver_reads_the_scenarios_vehicle_length():
    from mmpc.rl.driver import MetaActionDriver
    from mmpc.scenario import load_scenario

    run = type("Run", (), {"model": None, "config": load_config(RLConfig, "smoke")})()
    assert MetaActionDriver(run, load_scenario("cruise_paper")).meta.length == 4.0
    assert MetaActionDriver(run, load_scenario("cruise")).meta.length == 5.0


def test_the_expert_prior_starts_ppo_at_the_expert_action_and_is_refused_or_ignored_elsewhere(smoke, tmp_path):
    from stable_baselines3 import PPO

    from mmpc.rl.train import prefer_expert_action, train

    env = gym.make("CartPole-v1")
    model = PPO("MlpPolicy", env, seed=0, n_steps=64, batch_size=64)
    prefer_expert_action(model, 0.9)
    observations = torch.as_tensor(np.stack([env.observation_space.sample() for _ in range(16)]))
    probs = model.policy.get_distribution(observations).distribution.probs
    torch.testing.assert_close(probs[:, -1], torch.full((16,), 0.9), atol=0.02, rtol=0)
    with pytest.raises(ValueError, match="expert_prior"):
        TrainConfig(expert_prior=1.0)
    config = dataclasses.replace(smoke, train=dataclasses.replace(smoke.train, expert_prior=0.9))
    with pytest.raises(ValueError, match="expert_action: true"):  # the smoke grid has no expert action
        train(config, "ppo", 64, tmp_path / "run")
    assert not (tmp_path / "run").exists()
    # a recipe's plain highway-env baseline trains without it: highway-env's actions hold no expert
    train(config, "ppo", 16, tmp_path / "plain", env_kind="highway", evaluate_after=False)
    assert yaml.safe_load((tmp_path / "plain" / "config.yaml").read_text())["env"] == "highway"
    # the shipped recipe starts PPO at the expert; it reproduces the shipped agent's settings, but for the
    # layer's warm starts and the check: the agents were trained before the scenarios warm-started (every
    # decision solve cold), before `env.verify` existed (read false, as trained) and before
    # `traffic.ego_as_follower` (its default)
    def settings(config: dict) -> dict:
        config["scenario"]["mpc"].pop("warm_iterations")
        config["env"].pop("verify", None)
        config["env"].pop("meta_speeds", None)  # the plain agents' setting, added since
        config["train"].pop("n_envs")  # the task recipes train 256 environments since (throughput), with
        config["train"].pop("log_every")  # DQN's gradient steps per transition kept
        config["algorithms"]["dqn"].pop("gradient_steps")
        config["algorithms"]["ppo"].pop("n_steps")
        config["scenario"]["traffic"].setdefault("ego_as_follower", False)
        return config

    recipe = load_config(RLConfig, "high_speed")
    shipped = yaml.safe_load((mmpc.rl.runs.SHIPPED_MODELS / "high_speed_ppo" / "config.yaml").read_text())
    assert shipped["config"]["scenario"]["mpc"]["warm_iterations"] == 0 and recipe.scenario.mpc.warm_iterations == 10
    assert recipe.train.expert_prior == 0.9 and settings(to_dict(recipe)) == settings(shipped["config"])
    shipped = yaml.safe_load((mmpc.rl.runs.SHIPPED_MODELS / "cruise_task_ppo" / "config.yaml").read_text())
    assert settings(to_dict(load_config(RLConfig, "cruise_task"))) == settings(shipped["config"])  # the task-reward agent too


def test_the_shipped_agent_drives_by_name():
    from mmpc.rl.runs import load_run, shipped_models

    assert {"cruise_task_ppo", "high_speed_ppo"} <= set(shipped_models())
    run = load_run("high_speed_ppo")
    assert run.algo == "ppo" and run.env_kind == "safe" and run.config.env.expert_action
    scenario = dataclasses.replace(load_scenario("high_speed"), duration=1.0)
    result = run_episode(scenario, seed=1, driver=make_driver("sb3:high_speed_ppo", scenario))
    assert result.metrics["collisions"] == 0 and result.metrics["steps"] == 10
    with pytest.raises(FileNotFoundError, match="shipped agents: .*high_speed_ppo"):
        load_run("no_such_agent")
