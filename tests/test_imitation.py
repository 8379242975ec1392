"""mmpc.imitation: expert demonstrations as a Minari dataset (resumable), road-frame features,
behaviour cloning, the policy driver, DAgger (beta-mixture, batched expert labelling, resume) and
the stable-baselines3 export."""

from __future__ import annotations

import dataclasses
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

from mmpc.highway.runner import run_episode, write_outputs
from mmpc.drivers import MPCDriver, Observation, make_driver
from mmpc.config import from_dict, load_config
from mmpc.imitation.bc import TrainConfig, run_bc, train_policy
from mmpc.imitation.dagger import (
    DAGGER_POLICY,
    DaggerConfig,
    MixtureDriver,
    NoisyDriver,
    best_round,
    label_rollouts,
    label_states,
    run_dagger,
)
from mmpc.imitation.dataset import (
    MANIFEST,
    DemonstrationsError,
    Transitions,
    dataset_transitions,
    load_episode,
    open_dataset,
)
from mmpc.evaluate.tasks import lockstep_groups
from mmpc.imitation.demos import generate_demonstrations
from mmpc.imitation.features import FeatureConfig, SceneGeometry, nearest_neighbours, road_features, scene_geometry
from mmpc.imitation.policy import MLPPolicy, PolicyConfig, PolicyDriver, load_policy, save_policy
from mmpc.imitation.rollout import rollout_lockstep
from mmpc.road import Road
from mmpc.scenario import PAPER_SCHEDULE, ScenarioConfig, build_mpc, load_scenario

pytestmark = pytest.mark.usefixtures("one_thread")

SEEDS = [1000, 1001, 1002]


def short_cruise(duration: float = 2.0, *, cold: bool = False):
    """The cruise scenario, shorter; ``cold``: on the paper's schedule (no warm starts, no early exit)."""
    return load_scenario("cruise", PAPER_SCHEDULE if cold else None).replace(duration=duration)


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
    assert metadata["mmpc_seeds"] == SEEDS and metadata["mmpc_expert"] == "verified:mpc"  # the default expert
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
        # infos: the expert's decision at each observation (-1 where the check drove another command); the last row has none
        goals = episode.infos["goal_index"]
        assert goals.shape == (21,) and (goals[:-1] >= -1).all() and (goals[:-1] >= 0).mean() > 0.5 and goals[-1] == -1
        assert np.isfinite(episode.infos["residual_nonholonomic"][:-1]).all()
        # the ego's speed in the observation (feature vx, normalised by 80 m/s) is the road-frame v
        np.testing.assert_allclose(episode.observations[:, 0, 3] * 80.0, episode.infos["ego"][:, 3], atol=0.05)
        # the 8 nearest other vehicles in the scenario's ellipse, nearest first (what the policy reads)
        neighbours = episode.infos["neighbours"]
        assert neighbours.shape == (21, 8, 4) and np.isfinite(neighbours).all()  # 18 vehicles: every slot filled
        a, b = metadata["mmpc_scenario"]["optimizer"]["ellipse_a"], metadata["mmpc_scenario"]["optimizer"]["ellipse_b"]
        assert (a, b) == (8.0, 3.3)
        scaled = ((neighbours[..., 0] - episode.infos["ego"][:, None, 0]) / a) ** 2 + \
                 ((neighbours[..., 1] - episode.infos["ego"][:, None, 1]) / b) ** 2
        assert (np.diff(scaled, axis=1) >= 0).all()
    # the env spec rebuilds highway-env with the scenario's configuration
    env = dataset.recover_environment()
    assert env.unwrapped.config["lanes_count"] == 6 and env.unwrapped.config["policy_frequency"] == 10.0
    env.close()


def test_recorded_actions_are_the_experts_commands_at_the_recorded_states():
    scenario = short_cruise(1.0, cold=True)  # a warm-started expert's commands depend on its last solve too
    expert = MPCDriver(build_mpc(scenario))
    with torch.inference_mode():
        rollout = rollout_lockstep(scenario, [1000], expert, keep_states=True)[0]
        relabelled = label_states(expert, rollout.states, batch=4)  # batched, off-line: the DAgger labelling
    assert len(rollout.states) == rollout.episode.steps == 10
    np.testing.assert_allclose(relabelled, rollout.episode.actions, atol=2e-3)


def test_off_line_labels_of_a_warm_starting_expert_are_its_cold_commands_in_any_order():
    warm, cold = short_cruise(1.0), short_cruise(1.0, cold=True)
    assert warm.mpc.warm_iterations > 0
    with torch.inference_mode():
        states = rollout_lockstep(cold, [1000], MPCDriver(build_mpc(cold)), keep_states=True)[0].states
        expected = label_states(MPCDriver(build_mpc(cold)), states, batch=10)
        expert = MPCDriver(build_mpc(warm.replace(optimizer=cold.optimizer)))  # warm starts, the same schedule when cold
        in_order = label_states(expert, states, batch=2)  # consecutive states: a warm start would follow them
        shuffled = label_states(expert, states[::-1], batch=3)[::-1]
    np.testing.assert_allclose(in_order, expected, atol=2e-3)
    np.testing.assert_allclose(shuffled, expected, atol=2e-3)


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
    assert list(lockstep_groups([1000, 1001, 1002, 1005], 4).values()) == [[1000, 1001, 1002], [1005]]


def test_demonstrations_record_the_verified_expert_unless_told_the_mpc_alone(demos_dir, tmp_path):
    assert json.loads((demos_dir / MANIFEST).read_text())["expert"] == "verified:mpc"
    plain = tmp_path / "plain"
    report = generate_demonstrations(short_cruise(1.0), SEEDS[:2], plain, lockstep=2, expert="mpc")
    assert report.generated == SEEDS[:2]
    assert json.loads((plain / MANIFEST).read_text())["expert"] == "mpc"
    with pytest.raises(DemonstrationsError, match=r"differs in: expert \(mpc there, verified:mpc asked\).*--expert \(mpc\)"):
        generate_demonstrations(short_cruise(1.0), SEEDS[:2], plain, lockstep=2)
    with pytest.raises(DemonstrationsError, match=r"differs in: expert \(verified:mpc there, mpc asked\)"):
        generate_demonstrations(short_cruise(), SEEDS, demos_dir, lockstep=2, expert="mpc")
    with pytest.raises(ValueError, match="`expert` must be one of"):
        generate_demonstrations(short_cruise(1.0), SEEDS[:2], tmp_path / "other", lockstep=2, expert="verified:bc")
    assert not (tmp_path / "other").exists()  # refused before anything was written


INTERRUPTED_EPISODES = 8


def _demos_command(out: Path) -> list[str]:
    # one episode per lockstep chunk: after the first episode is staged, seven chunks (several
    # seconds of solving) remain to be interrupted, even when the test process is slow to wake up
    return [sys.executable, "-m", "mmpc.cli", "imitate", "demos", "--scenario", "cruise", "--duration", "1", "--episodes",
            str(INTERRUPTED_EPISODES), "--lockstep", "1", "--out", str(out)]


def test_interrupted_generation_resumes_to_exactly_the_uninterrupted_episodes(tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    interrupted = tmp_path / "interrupted"  # given relative to the working directory, as users do
    # Ctrl-C's disposition as in a terminal's foreground job, even when pytest itself runs as a
    # background job of a shell without job control (which starts it with SIGINT ignored, and
    # an ignored SIGINT is inherited: the run then finished all eight episodes uninterrupted).
    process = subprocess.Popen(_demos_command(Path("interrupted")), env=env, cwd=tmp_path, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True,
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.time() + 120
    while time.time() < deadline and not list((interrupted / "episodes").glob("seed_*.npz")):
        assert process.poll() is None, process.communicate()
        time.sleep(0.01)
    process.send_signal(signal.SIGINT)
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == 130, stderr
    assert "re-run the same command to resume" in stderr
    kept = sorted(p.name for p in (interrupted / "episodes").glob("seed_*.npz"))
    assert 1 <= len(kept) < INTERRUPTED_EPISODES, kept
    assert not (interrupted / "minari").exists()
    assert not list((interrupted / "episodes").glob(".tmp-*"))

    resumed = subprocess.run(_demos_command(Path("interrupted")), env=env, cwd=tmp_path, capture_output=True, text=True,
                             timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    assert f"{len(kept)} from an earlier run" in resumed.stdout
    fresh = tmp_path / "fresh"  # the same command, uninterrupted (in this process: one thread, as the CLI)
    generate_demonstrations(short_cruise(1.0), range(1000, 1000 + INTERRUPTED_EPISODES), fresh, lockstep=1)

    a, b = open_dataset(interrupted), open_dataset(fresh)
    assert a.total_episodes == b.total_episodes == INTERRUPTED_EPISODES
    for x, y in zip(a.iterate_episodes(), b.iterate_episodes()):
        assert x.id == y.id
        for name in ("observations", "actions", "rewards", "terminations", "truncations"):
            np.testing.assert_array_equal(getattr(x, name), getattr(y, name), err_msg=name)
        for name in x.infos:
            if name != "solve_ms":  # a wall time
                np.testing.assert_array_equal(x.infos[name], y.infos[name], err_msg=name)
    assert a.storage.metadata["mmpc_seeds"] == list(range(1000, 1000 + INTERRUPTED_EPISODES))


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
    assert policy.road == Road(num_lanes=6) and policy.config == PolicyConfig(hidden=(32, 32))
    data = dataset_transitions(open_dataset(demos_dir))
    with torch.no_grad():
        command = policy(torch.as_tensor(policy.features(data.ego, data.neighbours)))
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


def test_nearest_neighbours_and_road_features_on_a_hand_made_scene():
    road = Road(num_lanes=3)  # lane centres 0, 4, 8; edges -2 and 10
    ego = np.array([[100.0, 4.5, 0.1, 10.0, 0.5, -0.2]])
    vehicles = np.array([[[130.0, 4.0, 8.0, 0.0],    # r^2 = (30/8)^2 + (0.5/3)^2 = 14.09
                          [90.0, 0.0, 12.0, 0.5],    # r^2 = (10/8)^2 + (4.5/3)^2 = 3.81: nearest
                          [60.0, 8.0, 9.0, 0.0],     # masked out
                          [110.0, 8.0, 9.0, 0.0]]])  # r^2 = 1.5625 + 1.36 = 2.92: nearest of all
    mask = np.array([[True, True, False, True]])
    scene = SceneGeometry(5.0, (8.0, 3.0))  # 5 m cars, distances in (8 m, 3 m) units
    near = nearest_neighbours(ego, vehicles, mask, count=4, ellipse=scene.ellipse)
    np.testing.assert_array_equal(near[0, :3], vehicles[0, [3, 1, 0]])
    assert np.isnan(near[0, 3]).all()  # fewer real vehicles than slots
    features = road_features(ego, near, road, FeatureConfig(scene, neighbours=4, ego_command=True))
    config = FeatureConfig(scene, neighbours=4, ego_command=True)
    assert features.shape == (1, config.size) == (1, 27) and len(config.names()) == 27
    np.testing.assert_allclose(features[0, :7], [0.5, 6.5, 5.5, 0.1, 10.0, 0.5, -0.2], rtol=1e-6)
    vx, vy = 10.0 * math.cos(0.1), 10.0 * math.sin(0.1)
    np.testing.assert_allclose(features[0, 7:12], [1.0, 10.0, 3.5, 9.0 - vx, -vy], rtol=1e-5)
    np.testing.assert_allclose(features[0, 12:17], [1.0, -10.0, -4.5, 12.0 - vx, 0.5 - vy], rtol=1e-5)
    np.testing.assert_array_equal(features[0, 22:], 0.0)  # empty slot: presence 0 and zeros
    # without the command and with fewer neighbours: a prefix of the same layout
    short = road_features(ego, near, road, FeatureConfig(scene, neighbours=1))
    np.testing.assert_array_equal(short[0], np.concatenate([features[0, :5], features[0, 7:12]]))
    with pytest.raises(ValueError, match=r"`neighbours` must have shape \(1, >= 4, 4\)"):
        road_features(ego, near[:, :2], road, config)
    with pytest.raises(ValueError, match="not finite"):
        road_features(ego * np.nan, near, road, config)
    with pytest.raises(ValueError, match=r"`neighbours` must be an int in \[0, 8\]"):
        FeatureConfig(scene, neighbours=9)
    assert nearest_neighbours(ego, np.zeros((1, 0, 4)), None, 2, ellipse=scene.ellipse).shape == (1, 2, 4)
    # lane slots: ego lane 1 (y = 4.5); ahead in lane 2 the vehicle at x = 110, behind in lane 0 the one at 90,
    # ahead in lane 1 the one at 130; the other three slots are empty
    slotted = FeatureConfig(scene, neighbours=0, lane_slots=True)
    lanes = road_features(ego, near, road, slotted)[0, 5:].reshape(6, 5)  # (left ahead, left behind, own ..., right ...)
    assert slotted.size == 35 and len(slotted.names()) == 35 and slotted.names()[5] == "lane-1_ahead_present"
    np.testing.assert_array_equal(lanes[[0, 3, 5], 0], 0.0)
    np.testing.assert_allclose(lanes[1], [1.0, -10.0, -4.5, 12.0 - vx, (12.0 - vx) / 5.0], rtol=1e-5)  # faster car behind
    np.testing.assert_allclose(lanes[2], [1.0, 30.0, -0.5, 8.0 - vx, (vx - 8.0) / 25.0], rtol=1e-5)
    np.testing.assert_allclose(lanes[4], [1.0, 10.0, 3.5, 9.0 - vx, (vx - 9.0) / 5.0], rtol=1e-5)


def test_features_read_the_scenes_vehicle_length_and_ellipse():
    """The inverse time to collision subtracts the scenario's vehicle length, and the neighbours
    are read nearest first in the scenario's ellipse, however they were ranked when stored."""
    road = Road(num_lanes=3)
    ego = np.array([[100.0, 4.0, 0.0, 10.0, 0.0, 0.0]])
    vehicles = np.array([[[112.0, 4.0, 8.0, 0.0],    # 12 m ahead in the ego's lane
                          [104.0, 8.0, 9.0, 0.0]]])  # 4 m ahead one lane over
    long_cars, short_cars = SceneGeometry(5.0, (8.0, 3.0)), SceneGeometry(4.0, (8.0, 3.0))
    near = nearest_neighbours(ego, vehicles, ellipse=long_cars.ellipse)
    ttc = {scene.vehicle_length: road_features(ego, near, road, FeatureConfig(scene, neighbours=0, lane_slots=True))[0, 5:]
           .reshape(6, 5)[2, 4] for scene in (long_cars, short_cars)}
    assert ttc == pytest.approx({5.0: 2.0 / 7.0, 4.0: 2.0 / 8.0})
    # (8, 3): the car beside is nearer (r^2 = 0.25 + 1.78 < 2.25); (30, 3): the car ahead (0.16 < 1.79)
    np.testing.assert_array_equal(near[0, 0], vehicles[0, 1])
    ranked = {ellipse: road_features(ego, near, road, FeatureConfig(SceneGeometry(5.0, ellipse), neighbours=1))[0, 6]
              for ellipse in ((8.0, 3.0), (30.0, 3.0))}
    assert ranked == {(8.0, 3.0): 4.0, (30.0, 3.0): 12.0}  # dx of the first neighbour read
    assert scene_geometry(load_scenario("cruise_paper")) == SceneGeometry(4.0, (5.6, 3.1))


def _synthetic_states(count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    ego = np.column_stack([rng.uniform(0, 500, count), rng.uniform(0, 20, count), rng.normal(0, 0.05, count),
                           rng.uniform(8, 16, count), rng.normal(0, 0.5, count), rng.normal(0, 0.05, count)])
    neighbours = ego[:, None, :4] + rng.normal(0, 1, (count, 8, 4)) * np.array([30.0, 4.0, 3.0, 0.3])
    neighbours[rng.random((count, 8)) < 0.2] = np.nan
    return ego.astype(np.float32), neighbours.astype(np.float32)


def test_policy_learns_a_known_map_and_rejects_bad_shapes(tmp_path):
    road = Road()
    ego, neighbours = _synthetic_states(2000)
    config = PolicyConfig(hidden=(64, 64), neighbours=2, lane_slots=False)  # 15 features, indexed below
    scene = SceneGeometry(5.0, (8.0, 3.3))
    features = road_features(ego, neighbours, road, config.feature_config(scene))
    # acceleration from the first neighbour's gap, steering from the lane offset and heading
    actions = np.stack([np.tanh(features[:, 6] / 20.0) * 2, -0.05 * features[:, 0] - 0.5 * features[:, 3]], axis=1)
    data = Transitions(ego, neighbours, actions.astype(np.float32), np.repeat(np.arange(20), 100))
    policy, history = train_policy(data, road, TrainConfig(epochs=30, batch_size=64, policy=config), scene=scene)
    assert history.val_loss[history.best_epoch] < 0.05  # standardised: 1.0 is the mean predictor
    rmse_acc, rmse_steer = history.val_rmse[history.best_epoch]
    assert rmse_acc < 0.3 and rmse_steer < 0.02
    save_policy(tmp_path / "p.pt", policy, scenario="synthetic")
    again = load_policy(tmp_path / "p.pt")
    probe = torch.as_tensor(features[:5])
    torch.testing.assert_close(again(probe), policy(probe))
    # the driver picks the neighbours itself and runs the folded network: the same commands
    vehicles = torch.as_tensor(np.nan_to_num(neighbours[:5], nan=1e4))  # "absent" vehicles far away ...
    mask = torch.as_tensor(np.isfinite(neighbours[:5]).all(axis=2))  # ... and masked out
    decision = PolicyDriver(policy).decide(Observation(torch.as_tensor(ego[:5]), vehicles, mask))
    near = nearest_neighbours(ego[:5], neighbours[:5], ellipse=scene.ellipse)  # NaN rows are no vehicles either
    with torch.no_grad():
        expected = policy(torch.as_tensor(policy.features(ego[:5], near)))
    torch.testing.assert_close(torch.stack([decision.acceleration, decision.steering], dim=1), expected, atol=1e-5, rtol=1e-5)
    with pytest.raises(ValueError, match=r"shape \(B, 15\)"):
        policy(torch.zeros(2, 14))
    bad = data._replace(actions=actions * np.nan)
    with pytest.raises(ValueError, match="NaN"):
        train_policy(bad, road, TrainConfig(epochs=1))
    with pytest.raises(ValueError, match="`hidden`"):
        PolicyConfig(hidden=())
    with pytest.raises(ValueError, match="unknown key"):
        from_dict(TrainConfig, {"epoch": 3})
    with pytest.raises(ValueError, match="was trained on Road"):
        make_driver(f"bc:{tmp_path / 'p.pt'}", short_cruise().replace(lanes=4))


def test_mixture_driver_and_labels_take_the_expert_where_it_drove():
    scenario = short_cruise(1.0, cold=True)  # the expert's commands a function of the state alone
    expert = MPCDriver(build_mpc(scenario))
    policy = MLPPolicy(scenario.road, PolicyConfig(hidden=(8,)), scene=scene_geometry(scenario))
    learner = PolicyDriver(policy)
    with torch.inference_mode():
        rollouts = rollout_lockstep(scenario, [5, 6], MixtureDriver(expert, learner, 0.5, np.random.default_rng(0)),
                                    keep_states=True)
        labels, expert_steps = label_rollouts(expert, rollouts, batch=8)
        relabelled = [label_states(expert, r.states, batch=8) for r in rollouts]
        states = [state for r in rollouts for state in r.states]
        learner_only = MixtureDriver(expert, learner, 0.0, np.random.default_rng(0)).decide(states[0])
        expert_only = MixtureDriver(expert, learner, 1.0, np.random.default_rng(0)).decide(states[0])
    drove = [r.episode.infos["feasible_goals"][:-1] >= 0 for r in rollouts]
    assert expert_steps == sum(int(d.sum()) for d in drove) and 0 < expert_steps < 20  # about half of 20 steps
    for rollout, label, again, expert_drove in zip(rollouts, labels, relabelled, drove):
        np.testing.assert_array_equal(label[expert_drove], rollout.episode.actions[expert_drove])
        np.testing.assert_allclose(label, again, atol=2e-3)  # every label is the expert's command at that state
        assert not np.allclose(rollout.episode.actions[~expert_drove], again[~expert_drove], atol=2e-3)
    assert int(learner_only.goal_index[0]) == -1 and int(expert_only.goal_index[0]) >= 0
    with torch.inference_mode():
        np.testing.assert_allclose(float(expert_only.acceleration[0]), float(expert.decide(states[0]).acceleration[0]))
        # DART: the expert drives with noise on its commands; every step is relabelled with its clean command
        noisy = rollout_lockstep(scenario, [7], NoisyDriver(expert, (0.5, 0.01), np.random.default_rng(1)), keep_states=True)
        clean, _ = label_rollouts(expert, noisy, batch=8, noisy=True)
        np.testing.assert_allclose(clean[0], label_states(expert, noisy[0].states, batch=8), atol=2e-3)
        # a reversing ego (outside the MPC's domain): the learner drives it even at beta = 1, and it gets no label
        reversing = states[0]._replace(ego=states[0].ego.clone())
        reversing.ego[0, 3] = -0.5
        assert int(MixtureDriver(expert, learner, 1.0, np.random.default_rng(0)).decide(reversing).goal_index[0]) == -1
        backwards = noisy[0]._replace(episode=noisy[0].episode._replace(infos=dict(noisy[0].episode.infos)))
        backwards.episode.infos["ego"] = backwards.episode.infos["ego"].copy()
        backwards.episode.infos["ego"][3, 3] = -0.5
        dropped, _ = label_rollouts(expert, [backwards], batch=8, noisy=True)
        assert np.isnan(dropped[0][3]).all() and np.isfinite(np.delete(dropped[0], 3, axis=0)).all()
    error = noisy[0].episode.actions - clean[0]
    assert 0.2 < error[:, 0].std() < 0.9 and 0.004 < error[:, 1].std() < 0.02  # the executed commands carry the noise
    with pytest.raises(ValueError, match="`beta` must be in"):
        DaggerConfig(beta=1.5)
    with pytest.raises(ValueError, match="`noise` must be two finite stds"):
        DaggerConfig(noise=(0.5, -0.1))


def test_sb3_export_acts_like_the_cloned_policy(bc_run, demos_dir, tmp_path):
    import gymnasium as gym
    from stable_baselines3.common.policies import ActorCriticPolicy

    from mmpc.highway import RoadFrame, command_to_action, env_config, road_state
    from mmpc.imitation.export import RoadFeatureObservation, export_sb3, ppo_from_policy

    path = export_sb3(bc_run / "policy.pt", tmp_path / "sb3_policy.zip")
    sb3 = ActorCriticPolicy.load(str(path))
    policy = load_policy(bc_run / "policy.pt")
    data = dataset_transitions(open_dataset(demos_dir))
    features = policy.features(data.ego, data.neighbours)
    actions, _ = sb3.predict(features, deterministic=True)
    with torch.no_grad():
        commands = policy(torch.as_tensor(features))
    expected = np.stack([command_to_action(*c) for c in commands.tolist()])
    np.testing.assert_allclose(actions, expected, atol=1e-5)

    # PPO on the wrapped highway-env starts from the same actor; the wrapper computes what the driver computes
    scenario = short_cruise()
    env = gym.make(scenario.env_id, config=env_config(scenario))
    model = ppo_from_policy(bc_run / "policy.pt", env, n_steps=8, batch_size=8)
    assert model.observation_space.shape == (policy.input_size,)
    ppo_actions, _ = model.predict(features[:10], deterministic=True)
    np.testing.assert_allclose(ppo_actions, expected[:10], atol=1e-5)
    wrapped = RoadFeatureObservation(gym.make(scenario.env_id, config=env_config(scenario)), policy.road,
                                     policy.feature_config)
    observation, _ = wrapped.reset(seed=0)
    for _ in range(3):
        observation, *_ = wrapped.step(np.array([0.4, 0.1], dtype=np.float32))
    state = road_state(wrapped.unwrapped, RoadFrame.of(wrapped.unwrapped))
    driver_view = policy.features(state.ego.numpy(), nearest_neighbours(state.ego.numpy(), state.vehicles.numpy(),
                                                                        ellipse=policy.scene.ellipse))
    assert observation.shape == (policy.input_size,)
    np.testing.assert_allclose(observation, driver_view[0], rtol=1e-6)
    env.close()
    wrapped.close()


def test_dagger_aggregates_labelled_rounds_and_resumes(tmp_path):
    scenario = short_cruise(0.5)  # 5 steps per episode
    config = DaggerConfig(iterations=1, initial_episodes=2, episodes_per_iteration=2, beta=0.5, noise=(0.3, 0.005),
                          lockstep=2, label_batch=4, check_episodes=2,
                          train=TrainConfig(epochs=2, batch_size=4, policy=PolicyConfig(hidden=(8,))))
    report = run_dagger(scenario, tmp_path, config)
    first, second = report["rounds"]
    assert first["source"] == "expert" and first["steps"] == 10 and second["source"] == "mixture"
    assert second["beta"] == 0.5 and 0.0 <= second["expert_share"] <= 1.0
    assert second["samples"] == first["samples"] + second["steps"] == 20
    # every round's policy drove the 2 check episodes alone; policy.pt is the best round's
    assert all(e["check_steps"] == 10 and 0 <= e["check_collisions"] <= 2 for e in report["rounds"])
    assert report["best_round"] == best_round(report["rounds"])
    best = load_policy(tmp_path / f"round_{report['best_round']}" / "policy.pt").state_dict()
    for name, value in load_policy(tmp_path / "policy.pt").state_dict().items():
        torch.testing.assert_close(value, best[name])
    data = np.load(tmp_path / "data.npz")
    assert data["actions"].shape == (20, 2) and data["neighbours"].shape == (20, 8, 4)
    assert len(np.unique(data["episodes"])) == 4
    assert (tmp_path / "policy.pt").is_file() and (tmp_path / "round_1" / "policy.pt").is_file()
    assert json.loads((tmp_path / "dagger.json").read_text())["rounds"] == report["rounds"]

    # a re-run with more iterations keeps rounds 0-1 (their files untouched) and adds round 2
    stamp = (tmp_path / "round_1" / "policy.pt").stat().st_mtime_ns
    seen = []
    extended = run_dagger(scenario, tmp_path, dataclasses.replace(config, iterations=2), on_round=seen.append)
    assert [e["round"] for e in seen] == [0, 1, 2] and extended["rounds"][:2] == report["rounds"]
    assert extended["rounds"][2]["samples"] == 30 and extended["rounds"][2]["beta"] == 0.25
    assert (tmp_path / "round_1" / "policy.pt").stat().st_mtime_ns == stamp
    with pytest.raises(ValueError, match="differs in: config"):
        run_dagger(scenario, tmp_path, dataclasses.replace(config, beta=0.1))


def test_a_dagger_folder_written_with_retired_scenario_keys_resumes(tmp_path):
    scenario = short_cruise(0.5)
    config = DaggerConfig(iterations=0, initial_episodes=1, lockstep=1, check_episodes=0,
                          train=TrainConfig(epochs=1, batch_size=4, policy=PolicyConfig(hidden=(8,))))
    first = run_dagger(scenario, tmp_path, config)
    path = tmp_path / "dagger.json"
    record = json.loads(path.read_text())
    record["scenario"]["mpc"].update(compile="auto", wheelbase=5.0)  # as an earlier mmpc wrote it
    path.write_text(json.dumps(record))
    seen = []
    again = run_dagger(scenario, tmp_path, config, on_round=seen.append)
    assert [e["round"] for e in seen] == [0] and json.dumps(again["rounds"]) == json.dumps(first["rounds"])
    record["scenario"]["mpc"]["wheelbase"] = 4.0  # not the scenario's car: refused, saying why
    path.write_text(json.dumps(record))
    with pytest.raises(ValueError, match="cannot read.*wheelbase"):
        run_dagger(scenario, tmp_path, config)
    record["scenario"]["mpc"]["wheelbase"] = 5.0
    del record["config"]["verify"]  # a run labelled before the check existed resumes as it was labelled
    path.write_text(json.dumps(record))
    with pytest.raises(ValueError, match=r"differs in: config: verify"):
        run_dagger(scenario, tmp_path, config)
    resumed = run_dagger(scenario, tmp_path, dataclasses.replace(config, verify=False))
    assert json.dumps(resumed["rounds"]) == json.dumps(first["rounds"])


def test_dagger_refuses_demonstrations_of_another_expert_than_its_labels(demos_dir, tmp_path):
    config = DaggerConfig(iterations=0, lockstep=1, check_episodes=0, verify=False,
                          train=TrainConfig(epochs=1, batch_size=4, policy=PolicyConfig(hidden=(8,))))
    with pytest.raises(ValueError, match=r"holds demonstrations of verified:mpc; this run labels with mpc"):
        run_dagger(short_cruise(), tmp_path / "run", config, dataset_dir=demos_dir)


def test_best_round_has_the_fewest_check_collisions_and_the_most_data_among_ties():
    rounds = [{"round": 0, "check_collisions": 3}, {"round": 1, "check_collisions": 1},
              {"round": 2, "check_collisions": 4}, {"round": 3, "check_collisions": 1}]
    assert best_round(rounds) == 3
    assert best_round(rounds[:3]) == 1
    assert best_round([{"round": 0}, {"round": 1}]) == 1  # no check: the last round
    with pytest.raises(ValueError, match="`check_episodes`"):
        DaggerConfig(check_episodes=-1)


def test_cli_evaluates_expert_and_policy_side_by_side_and_benchmarks_them(bc_run, tmp_path, capsys):
    import bench_imitation_inference

    from mmpc.cli.main import main
    from mmpc.evaluate import read_episodes

    policy = bc_run / "policy.pt"
    out = tmp_path / "eval"
    code = main(["evaluate", "--driver", f"mpc,bc:{policy}", "--scenarios", "cruise", "--seeds", "3,4",
                 "--duration", "1", "--lockstep", "2", "--out", str(out)])
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    assert [e["driver"] for e in summary["summary"]] == ["mpc", f"bc:{policy}"]
    rows = read_episodes(out / "episodes.csv")
    assert [(r["driver"], r["seed"]) for r in rows] == [("mpc", 3), ("mpc", 4), (f"bc:{policy}", 3), (f"bc:{policy}", 4)]
    assert all(r["steps"] == 10 and r["status"] == "ok" for r in rows)
    assert "collision rate" in (out / "summary.md").read_text()
    assert f"bc:{policy}" in capsys.readouterr().out

    bench = tmp_path / "bench.json"
    assert bench_imitation_inference.main(["--policy", str(policy), "--steps", "5", "--out", str(bench)]) == 0
    report = json.loads(bench.read_text())
    assert report["rows"] == report["modes"]["consecutive"]["rows"]
    for mode, block in (("consecutive", 50), ("interleaved", 1)):
        entry = report["modes"][mode]
        assert entry["block"] == block
        assert entry["rows"]["expert"]["steps"] == entry["rows"]["policy"]["steps"] == 5
        assert entry["speedup_mean"] == pytest.approx(entry["rows"]["expert"]["mean_ms"] / entry["rows"]["policy"]["mean_ms"])


def test_library_defaults_are_what_the_command_line_trains():
    """``run_bc(...)`` / ``run_dagger(...)`` from Python train what ``mmpc imitate bc|dagger`` do
    without --config: the dataclass defaults, written once."""
    assert load_config(TrainConfig) == TrainConfig()
    assert load_config(DaggerConfig, None, {"train.epochs": 5}) == DaggerConfig(train=TrainConfig(epochs=5, policy=DAGGER_POLICY))
    assert DaggerConfig().train.policy != TrainConfig().policy  # DAgger's 2 x 128 ReLU, BC's 2 x 256 tanh


# ----------------------------------------------------------------------------------- artefacts of earlier versions


def test_a_checkpoint_without_a_scene_keeps_the_geometry_it_was_trained_with(tmp_path):
    """Checkpoints written before the features read the scenario hold no ``scene``: they load with
    5 m cars and the (8, 3) ellipse every feature used then, and drive as before."""
    from mmpc.imitation.features import LEGACY_SCENE

    road = Road(num_lanes=3)
    policy = MLPPolicy(road, PolicyConfig(hidden=(8,), neighbours=2), scene=SceneGeometry(5.0, (8.0, 3.0)))
    old = {  # the checkpoint of then: every key but "scene"
        "format": "mmpc-policy", "version": 2, "scenario": "cruise", "info": {"round": 3},
        "config": {"hidden": [8], "activation": "tanh", "neighbours": 2, "ego_command": False, "lane_slots": True},
        "road": {"num_lanes": 3, "lane_width": 4.0}, "state_dict": policy.state_dict(),
    }
    torch.save(old, tmp_path / "old.pt")
    loaded = load_policy(tmp_path / "old.pt")
    assert loaded.scene == LEGACY_SCENE == SceneGeometry(5.0, (8.0, 3.0)) and loaded.config == policy.config
    ego, neighbours = _synthetic_states(50, seed=3)
    np.testing.assert_array_equal(loaded.features(ego, neighbours), policy.features(ego, neighbours))
    # a new checkpoint stores its scene; another scene reads other features
    save_policy(tmp_path / "new.pt", MLPPolicy(road, PolicyConfig(hidden=(8,)), scene=SceneGeometry(4.0, (5.6, 3.1))))
    assert torch.load(tmp_path / "new.pt", weights_only=True)["scene"] == {"vehicle_length": 4.0, "ellipse": [5.6, 3.1]}
    assert load_policy(tmp_path / "new.pt").scene == SceneGeometry(4.0, (5.6, 3.1))


def test_an_old_manifest_with_compile_and_wheelbase_is_the_same_scenario(tmp_path, caplog):
    """A demonstrations directory written before mpc.compile and mpc.wheelbase were retired is
    resumed by a run of the same scenario; one whose wheelbase differs from the length is refused
    with what to do."""
    from mmpc.config import to_dict
    from mmpc.imitation.dataset import MANIFEST, DemonstrationsDir, DemonstrationsError, Manifest

    scenario = short_cruise()
    old = to_dict(scenario)
    old["mpc"] = {**old["mpc"], "wheelbase": 5.0, "compile": "auto"}
    (tmp_path / "demos").mkdir()
    (tmp_path / "demos" / MANIFEST).write_text(Manifest(old, 4, {"mmpc": "0.1.0"}).to_json())  # hashed as then
    with caplog.at_level("WARNING", logger="mmpc.scenario"):
        DemonstrationsDir(tmp_path / "demos", Manifest(to_dict(scenario), 4, {}))
    assert "mpc.compile" in caplog.text
    with pytest.raises(DemonstrationsError, match="another configuration"):
        DemonstrationsDir(tmp_path / "demos", Manifest(to_dict(scenario.replace(lanes=5)), 4, {}))
    old["mpc"]["wheelbase"] = 4.0
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / MANIFEST).write_text(Manifest(old, 4, {}).to_json())
    with pytest.raises(DemonstrationsError, match=r"cannot read the scenario.*`mpc.wheelbase` is 4.0 m.*another --out"):
        DemonstrationsDir(tmp_path / "other", Manifest(to_dict(scenario), 4, {}))


def test_the_dagger_config_record_of_an_earlier_run_is_unchanged():
    """dagger.json's ``config`` (asdict of DaggerConfig without ``iterations``) is what a resumed
    run compares; the config's fields kept their form, so a run of then still matches. Its
    ``scenario`` (written with mpc.compile and mpc.wheelbase) reads as today's scenario."""
    from mmpc.config import to_dict

    old_record = {  # dagger.json of a run with the default settings, as written before this change
        "initial_episodes": 20, "episodes_per_iteration": 20, "beta": 0.3, "beta_decay": 0.5, "noise": [0.5, 0.01],
        "label_window": 1.0, "seed_start": 2000, "lockstep": 8, "label_batch": 256, "duration": None,
        "check_episodes": 20, "check_seed_start": 3000,
        "train": {"epochs": 30, "batch_size": 256, "learning_rate": 0.001, "weight_decay": 0.0001,
                  "validation_fraction": 0.2, "seed": 0,
                  "policy": {"hidden": [128, 128], "activation": "relu", "neighbours": 8, "ego_command": False,
                             "lane_slots": True}},
    }
    settings = json.loads(json.dumps(dataclasses.asdict(DaggerConfig(verify=False)), default=list))
    settings.pop("iterations")
    assert settings == {**old_record, "verify": False}  # the one key added since: the run of then labelled without the check
    assert from_dict(DaggerConfig, {**old_record, "iterations": 12}) == DaggerConfig()
    scenario = load_scenario("cruise")
    old_scenario = {**to_dict(scenario), "mpc": {**to_dict(scenario)["mpc"], "wheelbase": 5.0, "compile": "auto"}}
    assert to_dict(from_dict(ScenarioConfig, old_scenario)) == to_dict(scenario)


@pytest.mark.parametrize("warm_iterations", [0, 10])  # 10: the expert warm-starts at the scenario's control period
def test_demonstrations_on_the_batched_simulator_have_the_highway_env_layout(tmp_path, warm_iterations):
    scenario = short_cruise(1.0).replace(sim="batched")
    scenario = scenario.replace(mpc=dataclasses.replace(scenario.mpc, warm_iterations=warm_iterations))
    report = generate_demonstrations(scenario, SEEDS, tmp_path, lockstep=3)
    assert report.seeds == SEEDS
    for seed in SEEDS:
        episode = load_episode(tmp_path / "episodes" / f"seed_{seed:06d}.npz")
        assert episode.observations.shape == (11, 5, 5) and episode.actions.shape == (10, 2)
        assert episode.truncations[-1] and not episode.terminations.any() and (episode.rewards > 0).all()
        np.testing.assert_allclose(episode.observations[:, 0, 3] * 80.0, episode.infos["ego"][:, 3], atol=0.05)
        assert (episode.infos["goal_index"][:-1] >= 0).all()


def test_dagger_runs_on_the_batched_simulator(tmp_path):
    scenario = short_cruise(0.5).replace(sim="batched")
    config = DaggerConfig(iterations=1, initial_episodes=2, episodes_per_iteration=2, beta=0.5, noise=(0.3, 0.005),
                          lockstep=2, label_batch=4, check_episodes=2,
                          train=TrainConfig(epochs=2, batch_size=4, policy=PolicyConfig(hidden=(8,))))
    report = run_dagger(scenario, tmp_path, config)
    assert [r["source"] for r in report["rounds"]] == ["expert", "mixture"]
    assert report["rounds"][1]["samples"] == 20 and all(r["check_steps"] == 10 for r in report["rounds"])
    assert json.loads((tmp_path / "dagger.json").read_text())["scenario"]["sim"] == "batched"
