"""mmpc.rl.driver.SafeAgentDriver replans as the agent was trained (``SafeEnvConfig.replan``):
at every frame, or at the agent's decision with the plan tracked in between. A stub model with
fixed actions drives the batched simulator (:class:`mmpc.highway.worlds.BatchedWorld`)."""

from __future__ import annotations

import dataclasses
import math
import types

import numpy as np
import pytest
import yaml
import torch

from mmpc.config import load_config
from mmpc.highway.runner import run_episode
from mmpc.highway.batched_world import BatchedWorld
from mmpc.rl.config import RLConfig, SafeEnvConfig
from mmpc.rl.driver import SafeAgentDriver
from mmpc.rl.safety import SafetyLayer, observation_rows
from mmpc.rl.engine import SafeEnvs

pytestmark = pytest.mark.usefixtures("one_thread")

SEEDS = [0, 1, 2]
ACTIONS = [3, 0, 5]  # smoke grid (offset-major, speeds 15, 25): keep lane 25 m/s, left 15 m/s, right 25 m/s


@pytest.fixture(scope="module")
def smoke() -> RLConfig:
    return load_config(RLConfig, "smoke")


class FixedModel:
    """A policy that answers every row with its fixed action (row i of the batch: ``actions[i]``)."""

    def __init__(self, actions) -> None:
        self.actions = np.asarray(actions)

    def predict(self, observation: np.ndarray, deterministic: bool = True):
        return self.actions[: observation.shape[0]], None


def make_driver(smoke: RLConfig, replan: str, actions=ACTIONS, continuous: bool = False) -> SafeAgentDriver:
    """The layer's replanning alone (``verify`` off: the check's overrides are tested in test_sim_vec_env.py)."""
    env = dataclasses.replace(smoke.env, replan=replan, verify=False)
    run = types.SimpleNamespace(model=FixedModel(actions), continuous=continuous, config=types.SimpleNamespace(env=env))
    return SafeAgentDriver(run, smoke.scenario)


def count_solves(driver: SafeAgentDriver) -> list[int]:
    """Counts the driver's optimizer calls (every solve goes through ``MPC.score``)."""
    calls = [0]
    score = driver.layer.mpc.score

    def counted(problem, *args):
        calls[0] += 1
        return score(problem, *args)

    driver.layer.mpc.score = counted
    return calls


def test_frame_mode_plans_the_held_goal_afresh_at_every_frame(smoke):
    """At a decision the plan comes from the solve behind the features (as in decision mode); at
    every later frame the held goal is solved afresh, warm from the frame before: the driver's
    frames are a twin layer's fed the same states."""
    warm_iterations = smoke.scenario.mpc.warm_iterations
    assert warm_iterations > 0  # the default RL scenario warm-starts
    driver = make_driver(smoke, "frame")
    twin = SafetyLayer.for_scenario(smoke.scenario, driver.config)
    calls = count_solves(driver)
    world = BatchedWorld.start(smoke.scenario, SEEDS)
    driver.reset(len(SEEDS))
    active = list(range(len(SEEDS)))
    frames = smoke.env.decision_frames
    for frame in range(frames + 2):  # across a new decision
        observation, _ = world.observe(active)
        before = calls[0]
        decision = driver.decide(observation)
        if frame % frames == 0:
            solve = twin.decision_solve(observation)
            expected = twin.decide(solve, torch.tensor(ACTIONS))
            starts = twin.frame_starts(len(SEEDS), solve, expected.agent_index)
        else:
            expected = twin.plan(observation, expected.commands, starts)
            warm = (expected.plan.result.iterations <= warm_iterations).all(dim=1)
            assert warm.any()  # warm from the frame before (rows that had no feasible goal then: cold)
        assert calls[0] - before == 1
        assert torch.equal(decision.acceleration, expected.plan.acceleration)
        assert torch.equal(decision.steering, expected.plan.steering)
        assert torch.equal(decision.goal_index, expected.plan.selection.index)
        assert torch.equal(decision.feasible_goals, expected.feasible_goals)
        assert decision.plan is not None and decision.candidates is not None
        world.apply(active, decision.acceleration, decision.steering)


def test_decision_mode_solves_once_at_the_decision_and_tracks_the_plan_between(smoke):
    driver = make_driver(smoke, "decision")
    layer = driver.layer
    calls = count_solves(driver)
    period = 1.0 / smoke.scenario.frequency
    world = BatchedWorld.start(smoke.scenario, SEEDS)
    driver.reset(len(SEEDS))
    active = list(range(len(SEEDS)))
    tracked_frames = 0
    for frame in range(smoke.env.decision_frames):
        observation, _ = world.observe(active)
        before = calls[0]
        decision = driver.decide(observation)
        solves = calls[0] - before
        if frame == 0:
            commands = layer.discrete_commands(observation.ego, torch.tensor(ACTIONS))
            decided = layer.decide(layer.decision_solve(observation), torch.tensor(ACTIONS))
            expected = layer.frame(observation, commands, 0.0, None, decided)
            assert solves == 1  # the solve behind the features is the decision's
            assert torch.equal(decision.goal_index, decided.plan.selection.index) and decision.plan is not None
        else:
            expected = layer.frame(observation, commands, frame * period, expected.held)
            assert solves == int(bool(expected.solved.any()))  # one call for the rows solved again, if any
            tracked_frames += solves == 0
            assert decision.plan is None and decision.candidates is None
            assert decision.goal_index.tolist() == [-1] * len(SEEDS) and bool(decision.plan_cost.isnan().all())
        assert torch.equal(decision.acceleration, expected.acceleration)
        assert torch.equal(decision.steering, expected.steering)
        assert torch.equal(decision.fallback, expected.fallback)
        assert torch.equal(decision.feasible_goals, expected.feasible_goals)
        world.apply(active, decision.acceleration, decision.steering)
    assert tracked_frames >= 1  # the seeds give frames on which every row just tracked its plan


def test_rows_leaving_the_batch_keep_the_others_held_plans(smoke):
    seeds, actions = [0, 1, 2, 3], [3, 0, 5, 3]
    driver = make_driver(smoke, "decision", actions)
    layer = driver.layer
    period = 1.0 / smoke.scenario.frequency
    world = BatchedWorld.start(smoke.scenario, seeds)
    driver.reset(len(seeds))
    active = list(range(len(seeds)))
    for frame in range(smoke.env.decision_frames):
        if frame == 2:
            active = [0, 2, 3]  # environment 1 ends
        if frame == 3:
            active = [2, 3]  # and then environment 0
        observation, _ = world.observe(active)
        decision = driver.decide(observation)
        if frame == 0:
            commands = layer.discrete_commands(observation.ego, torch.tensor(actions))
            decided = layer.decide(layer.decision_solve(observation), torch.tensor(actions))
            expected, expected_rows = layer.frame(observation, commands, 0.0, None, decided), list(range(len(seeds)))
        else:
            keep = torch.tensor([env in active for env in expected_rows])
            expected = layer.frame(observation_rows(observation, torch.arange(len(active))), commands[active],
                                   frame * period, expected.held.take(keep))
            expected_rows = active
        assert torch.equal(decision.acceleration, expected.acceleration)
        assert torch.equal(decision.steering, expected.steering)
        world.apply(active, decision.acceleration, decision.steering)


@pytest.mark.parametrize("replan", ["frame", "decision"])
@pytest.mark.parametrize("continuous", [False, True])
def test_the_driver_drives_two_agent_steps_as_the_training_environment(replan, continuous, smoke):
    actions = [[0.0, 1.0], [-1.0, -0.5], [1.0, 0.3]] if continuous else ACTIONS
    driver = make_driver(smoke, replan, actions, continuous)
    batch = SafeEnvs(len(SEEDS), smoke.scenario.replace(sim="batched"), driver.config, smoke.reward, continuous=continuous)
    batch.reset(SEEDS)
    world = BatchedWorld.start(smoke.scenario, SEEDS)
    driver.reset(len(SEEDS))
    active = list(range(len(SEEDS)))
    interventions = [0] * len(SEEDS)
    for _ in range(2):
        step = batch.advance(actions)
        assert not step.terminated.any() and not step.truncated.any()
        interventions = [total + info["intervention_frames"] for total, info in zip(interventions, step.infos)]
        for _ in range(smoke.env.decision_frames):
            observation, _ = world.observe(active)
            decision = driver.decide(observation)
            world.apply(active, decision.acceleration, decision.steering)
        for name in ("x", "y", "heading", "speed"):
            assert torch.equal(getattr(world.sim.state, name)[:, 0], getattr(batch.world.sim.state, name)[:, 0]), name
    assert [driver.intervention_frames[i] for i in active] == interventions


def test_the_runner_records_a_decision_mode_episode(smoke):
    scenario = dataclasses.replace(smoke.scenario, sim="batched")
    driver = make_driver(smoke, "decision", [3])
    result = run_episode(scenario, seed=2, driver=driver)
    records = result.records
    assert len(records) == round(scenario.duration * scenario.frequency)
    frames = smoke.env.decision_frames
    assert all(r.goal_index >= 0 and not math.isnan(r.plan_cost) for r in records[::frames])
    assert all(r.goal_index == -1 and math.isnan(r.goal_x) for i, r in enumerate(records) if i % frames)
    assert all(r.feasible_goals >= 1 for r in records)


def test_a_row_joining_mid_step_is_decided_while_the_others_track(smoke):
    driver = make_driver(smoke, "decision", [3, 0, 5])
    layer = driver.layer
    world = BatchedWorld.start(smoke.scenario, SEEDS)
    driver.reset(len(SEEDS))
    observation, _ = world.observe([0, 1])
    first = driver.decide(observation)
    world.apply([0, 1], first.acceleration, first.steering)
    observation, _ = world.observe([0, 1, 2])  # environment 2 joins at the others' second frame
    mixed = driver.decide(observation)
    joining = observation_rows(observation, torch.tensor([2]))
    decided = layer.decide(layer.decision_solve(joining), torch.tensor([3]))  # the model answers row 0 of its batch
    assert mixed.goal_index.tolist() == [-1, -1, int(decided.plan.selection.index[0])] and mixed.candidates is None
    assert float(mixed.acceleration[2]) == float(decided.plan.acceleration[0])
    assert math.isnan(float(mixed.plan_cost[0])) and not math.isnan(float(mixed.plan_cost[2]))


@pytest.mark.parametrize("replan", ["frame", "decision"])
def test_random_goals_behind_the_layer_drive_highway_env_from_the_registry(replan, smoke, tmp_path):
    from mmpc.drivers import make_driver as make_registered
    from mmpc.rl.driver import RandomGoals

    scenario = dataclasses.replace(smoke.scenario, duration=3.0)
    config = tmp_path / "random.yaml"
    config.write_text(f"env: {{replan: {replan}, speeds: [15.0, 25.0]}}\n")
    driver = make_registered(f"safe-random:{config}", scenario)
    assert driver.config.replan == replan and isinstance(driver.model, RandomGoals) and driver.model.num_goals == 6
    result = run_episode(scenario, seed=3, driver=driver)
    assert result.metrics["collisions"] == 0 and result.metrics["steps"] == 30
    # the goals are a function of the episode's own states: driving it again gives the same
    first = [record.goal_index for record in result.records]
    result = run_episode(scenario, seed=3, driver=driver)
    assert [record.goal_index for record in result.records] == first
    assert make_registered("safe-random", scenario).config == SafeEnvConfig()  # the defaults
    # a training run's folder (or its config.yaml) gives the agent's own settings
    from mmpc.config import to_dict
    from mmpc.rl.config import RLConfig

    record = {"algo": "ppo", "env": "safe", "action": "discrete", "seed": 0, "timesteps": 10,
              "config": to_dict(RLConfig(env=SafeEnvConfig(decision_frames=3, speeds=(12.0,))))}
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "config.yaml").write_text(yaml.safe_dump(record))
    for spec in (tmp_path / "run", tmp_path / "run" / "config.yaml"):
        recorded = make_registered(f"safe-random:{spec}", scenario).config
        assert recorded.decision_frames == 3 and recorded.speeds == (12.0,)
    with pytest.raises(FileNotFoundError, match="sometimes"):
        make_registered("safe-random:sometimes", scenario)


def test_random_goals_cover_the_grid_and_depend_on_the_row_alone():
    from mmpc.rl.driver import RandomGoals

    model = RandomGoals(12, key_size=2, seed=5)
    rows = np.random.default_rng(0).normal(size=(2000, 4)).astype(np.float32)
    actions, _ = model.predict(rows)
    assert set(actions.tolist()) == set(range(12))
    # the same row gets the same goal in any batch, whatever follows its key (e.g. solver features)
    shuffled = rows[::-1].copy()
    shuffled[:, 2:] = 0.0
    assert model.predict(shuffled)[0].tolist() == actions[::-1].tolist()
    assert RandomGoals(12, key_size=2, seed=6).predict(rows)[0].tolist() != actions.tolist()


def test_the_expert_stand_in_drives_the_mpcs_own_choice_at_every_decision(smoke, tmp_path):
    from mmpc.drivers import make_driver as make_registered
    from mmpc.highway.runner import Observer

    scenario = dataclasses.replace(smoke.scenario, duration=2.0)
    config = tmp_path / "every_frame.yaml"
    config.write_text("env: {decision_frames: 1}\n")
    driver = make_registered(f"safe-expert:{config}", scenario)
    assert driver.config.expert_action and driver.config.replan == "decision"
    layer = driver.layer

    class Decisions(Observer):
        def __init__(self):
            self.seen = []

        def decided(self, observation, decision, active):
            self.seen.append((observation, decision.goal_index.clone()))

    decisions = Decisions()
    result = run_episode(scenario, seed=5, driver=driver, observers=[decisions])
    assert result.metrics["collisions"] == 0 and len(decisions.seen) == 20
    for observation, chosen in decisions.seen:  # the same candidates solved again: the expert picks the same one
        assert int(chosen[0]) == int(layer.decision_solve(observation).expert[0])
