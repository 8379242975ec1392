"""The safety layer's guarantees in both replanning modes (frame, decision): it never executes an
infeasible candidate while a feasible one exists, never tracks a plan that now runs into an
obstacle, and keeps a collision-free scripted scene collision-free whatever the agent asks
(real highway-env)."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mmpc.config import load_config
from mmpc.drivers import Observation
from mmpc.problem import ego_state
from mmpc.rl.config import RLConfig
from mmpc.rl.envs import SafeHighwayEnv
from mmpc.rl.safety import SafetyLayer
from mmpc.scenario import EgoConfig, load_scenario
from mmpc.traffic_config import ScriptedTraffic, ScriptedVehicle
from mmpc.tracking import plan_clearance

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def smoke() -> RLConfig:
    return load_config(RLConfig, "smoke")


@pytest.fixture(scope="module")
def layers(smoke) -> dict[str, SafetyLayer]:
    return {mode: SafetyLayer.for_scenario(smoke.scenario, dataclasses.replace(smoke.env, replan=mode))
            for mode in ("frame", "decision")}


def random_scenes(seed: int, count: int, vehicles: int) -> Observation:
    """``count`` egos on the 3-lane road among ``vehicles`` cars each, some of them close."""
    generator = torch.Generator().manual_seed(seed)

    def uniform(low: float, high: float, *shape: int) -> torch.Tensor:
        return low + (high - low) * torch.rand(*shape, generator=generator)

    lanes = torch.randint(0, 3, (count,), generator=generator).float() * 4.0
    ego = ego_state(torch.zeros(count), lanes + uniform(-0.5, 0.5, count), uniform(-0.03, 0.03, count), uniform(15.0, 28.0, count))
    x = uniform(-25.0, 90.0, count, vehicles)
    y = torch.randint(0, 3, (count, vehicles), generator=generator).float() * 4.0
    speed = uniform(8.0, 26.0, count, vehicles)
    cars = torch.stack([x, y, speed, torch.zeros_like(x)], dim=-1)
    # no car starts on the ego (the optimizer refuses an infeasible start as START_IN_COLLISION anyway)
    clear = ((x.abs() > 9.0) | ((y - ego[:, 1:2]).abs() > 3.5))
    return Observation(ego, cars, clear)


def random_choices(layer: SafetyLayer, seed: int) -> tuple[Observation, torch.Tensor, torch.Tensor]:
    """8 random scenes (:func:`random_scenes`), a random grid goal for each, and its goal command."""
    observation = random_scenes(seed, count=8, vehicles=8)
    actions = torch.randint(0, layer.num_discrete_goals, (8,), generator=torch.Generator().manual_seed(seed))
    return observation, actions, layer.discrete_commands(observation.ego, actions)


def assert_feasible_first(plan, fallback: torch.Tensor) -> None:
    """The executed candidate is feasible wherever any candidate is; the fallback only where none is."""
    feasible = plan.result.feasible
    rows = torch.arange(feasible.shape[0])
    any_feasible = feasible.any(dim=1)
    assert bool((feasible[rows, plan.selection.index] | ~any_feasible).all())
    assert torch.equal(fallback, ~any_feasible)


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 10_000))
def test_the_layer_never_executes_an_infeasible_candidate_while_a_feasible_one_exists(seed, layers):
    layer = layers["decision"]
    observation, actions, commands = random_choices(layer, seed)
    fresh = layer.plan(observation, commands)  # per-frame mode: the agent's goal + the standard goals
    assert_feasible_first(fresh.plan, fresh.fallback)
    decided = layer.decide(layer.decision_solve(observation), actions)  # decision mode: the grid's candidates
    assert_feasible_first(decided.plan, decided.fallback)
    # the agent's own candidate is executed exactly where it is feasible
    rows = torch.arange(8)
    assert torch.equal((decided.plan.selection.index == actions) & ~decided.fallback, decided.agent_feasible)
    assert torch.equal(fresh.plan.selection.index[fresh.agent_feasible], torch.zeros(int(fresh.agent_feasible.sum()), dtype=torch.long))
    assert bool(decided.plan.result.feasible[rows, actions].eq(decided.agent_feasible).all())


def test_a_decision_from_the_features_solve_is_the_plan_a_fresh_solve_of_the_agents_goal_gives(layers):
    layer = layers["decision"]
    observation = random_scenes(7, count=6, vehicles=6)
    actions = torch.arange(6) * 2 % layer.num_discrete_goals
    layer.forget()  # both solves cold: no other test's decision at these ids to start from
    decided = layer.decide(layer.decision_solve(observation), actions)
    fresh = layer.plan(observation, layer.discrete_commands(observation.ego, actions))
    assert torch.equal(decided.agent_feasible, fresh.agent_feasible)
    both = decided.agent_feasible
    for name in ("x", "y", "psi", "v"):
        torch.testing.assert_close(getattr(decided.plan.trajectory, name)[both], getattr(fresh.plan.trajectory, name)[both],
                                   atol=1e-4, rtol=1e-4)


def test_decision_mode_tracks_the_plan_and_solves_again_only_where_it_is_blocked(layers):
    layer = layers["decision"]
    ego = ego_state([0.0, 0.0], [4.0, 4.0], [0.0, 0.0], [25.0, 25.0])
    far = torch.tensor([[[200.0, 0.0, 25.0, 0.0]], [[200.0, 0.0, 25.0, 0.0]]])
    observation = Observation(ego, far)
    actions = torch.tensor([5, 5])  # keep the lane at 25 m/s
    decided = layer.decide(layer.decision_solve(observation), actions)
    commands = layer.discrete_commands(ego, actions)
    first = layer.frame(observation, commands, 0.0, None, decided)
    assert first.solved.tolist() == [True, True] and first.agent_feasible.tolist() == [True, True]
    # 0.1 s later both egos are where their plans say; in environment 1 a car has appeared 50 m
    # ahead in its lane at 15 m/s, on the plan held
    moved = ego.clone()
    moved[:, 0] += 2.5
    cars = torch.tensor([[[200.0, 0.0, 25.0, 0.0]], [[52.5, 4.0, 15.0, 0.0]]])
    second = layer.frame(Observation(moved, cars), commands, 0.1, first.held)
    assert second.solved.tolist() == [False, True] and not bool(second.fallback.any())
    assert float(second.held.planned_at[0]) == 0.0 and float(second.held.planned_at[1]) == pytest.approx(0.1)
    mpc = layer.mpc
    states, mask = mpc.nearest_obstacles(moved, cars, None)
    clearance = plan_clearance(second.held.trajectory, 0.1 - second.held.planned_at, states, mask, mpc.predict, mpc.ellipse)
    assert bool((clearance >= 1.0 - mpc.optimizer.config.obstacle_tolerance).all())


@settings(max_examples=4, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 10_000))
def test_decision_mode_never_tracks_a_plan_that_runs_into_an_obstacle_as_predicted_now(seed, layers):
    layer = layers["decision"]
    observation, actions, commands = random_choices(layer, seed)
    control = layer.frame(observation, commands, 0.0, None, layer.decide(layer.decision_solve(observation), actions))
    # every car changes speed by up to +-5 m/s and the egos are where their plans say 0.2 s on
    generator = torch.Generator().manual_seed(seed + 1)
    cars = observation.vehicles.clone()
    cars[..., 0] += 0.2 * cars[..., 2]
    cars[..., 2] += 10.0 * torch.rand(cars.shape[:2], generator=generator) - 5.0
    plan = control.held.trajectory
    at = torch.full((8,), 0.2)
    from mmpc.tracking import sample

    here = sample(plan, at[:, None])
    ego = torch.stack([here.x[:, 0], here.y[:, 0], here.psi[:, 0], torch.hypot(here.xdot, here.ydot)[:, 0],
                       torch.zeros(8), here.psidot[:, 0]], dim=1)
    later = layer.frame(Observation(ego, cars, observation.vehicle_mask), commands, 0.2, control.held)
    tracked = ~later.solved
    mpc = layer.mpc
    states, mask = mpc.nearest_obstacles(ego, cars, observation.vehicle_mask)
    clearance = plan_clearance(later.held.trajectory, 0.2 - later.held.planned_at, states, mask, mpc.predict, mpc.ellipse)
    assert bool((clearance[tracked] >= 1.0 - mpc.optimizer.config.obstacle_tolerance).all())
    assert bool(later.held.valid[tracked].all())  # a row in fallback is solved again at every frame


#: The ego boxed in: a slow car 40 m ahead in its lane, cars alongside on both sides.
BOXED_IN = (
    ScriptedVehicle(lane=1, x=40.0, speed=15.0),
    ScriptedVehicle(lane=0, x=4.0, speed=25.0),
    ScriptedVehicle(lane=2, x=-6.0, speed=25.0),
    ScriptedVehicle(lane=0, x=45.0, speed=20.0),
    ScriptedVehicle(lane=2, x=35.0, speed=18.0),
)


@pytest.mark.parametrize("replan", ["frame", "decision"])
def test_a_collision_free_scripted_scene_stays_collision_free_whatever_the_agent_asks(replan, smoke):
    scenario = load_scenario("rl_highway_fast")
    scenario = dataclasses.replace(scenario, name="boxed_in", duration=6.0, ego=EgoConfig(speed=25.0, lane=1),
                                   traffic=ScriptedTraffic(BOXED_IN))
    config = dataclasses.replace(smoke.env, replan=replan, speeds=(15.0, 28.0))
    layer = SafetyLayer.for_scenario(scenario, config)
    env = SafeHighwayEnv(scenario, config, smoke.reward, layer=layer)
    fastest = len(config.speeds) - 1
    # into the car on the left, into the slow car ahead, into the car on the right: each at full speed
    for action in (fastest, len(config.speeds) + fastest, 2 * len(config.speeds) + fastest):
        env.reset(seed=0)
        crashed, steps, interventions = False, 0, 0
        done = False
        while not done:
            _, _, terminated, truncated, info = env.step(action)
            crashed |= info["crashed"]
            interventions += info["intervention_frames"]
            steps += 1
            done = terminated or truncated
        assert not crashed, f"action {action} ({replan}) crashed after {steps} agent steps"
        assert steps == int(scenario.duration * scenario.frequency) // config.decision_frames
        assert interventions > 0  # the layer overrode the agent somewhere
    env.close()



def test_the_expert_action_drives_exactly_what_the_mpc_expert_would(smoke):
    config = dataclasses.replace(smoke.env, replan="decision", expert_action=True)
    layer = SafetyLayer.for_scenario(smoke.scenario, config)
    grid = layer.num_discrete_goals
    assert layer.num_actions == grid + 1
    observation = random_scenes(11, count=8, vehicles=8)
    solve = layer.decision_solve(observation)
    expert = layer.mpc.choose(solve.problem, solve.scored)  # the MPC's own choice over the same candidates
    decided = layer.decide(solve, torch.full((8,), grid))
    assert torch.equal(decided.plan.selection.index, expert.selection.index)
    assert torch.equal(decided.plan.acceleration, expert.acceleration) and torch.equal(decided.plan.steering, expert.steering)
    assert torch.equal(decided.agent_feasible, expert.selection.feasible)  # an intervention only where nothing is feasible
    # its goal command reaches the expert's goal; grid actions keep the grid's commands
    goals = layer.goals(solve.problem.ego, decided.commands[:, None])[:, 0]
    torch.testing.assert_close(goals, solve.problem.goals[torch.arange(8), expert.selection.index], atol=1e-4, rtol=0)
    actions = torch.arange(8) % grid
    assert torch.equal(layer.decide(solve, actions).commands, layer.discrete_commands(observation.ego, actions))
    # the observation's features: the grid's goals, then the expert's candidate
    features = layer.features(solve)
    assert features.shape == (8, grid + 1, 3)
    feasible = solve.scored.result.feasible[torch.arange(8), expert.selection.index]
    assert features[:, grid, 0].tolist() == feasible.float().tolist()
    with pytest.raises(ValueError, match=rf"\[0, {grid + 1}\)"):
        layer.decide(solve, torch.full((8,), grid + 1))


def test_the_expert_action_needs_decision_replanning_and_discrete_goals(smoke):
    with pytest.raises(ValueError, match="expert_action.*replan: decision"):
        dataclasses.replace(smoke.env, replan="frame", expert_action=True)
    config = dataclasses.replace(smoke.env, replan="decision", expert_action=True)
    with pytest.raises(ValueError, match="continuous"):
        SafeHighwayEnv(smoke.scenario, config, smoke.reward, continuous=True)
    env = SafeHighwayEnv(smoke.scenario, config, smoke.reward)
    assert env.action_space.n == config.num_discrete_goals + 1
    env.reset(seed=3)
    _, _, _, _, info = env.step(config.num_discrete_goals)
    assert info["frames"] == config.decision_frames and info["solved_frames"] >= 1
    with pytest.raises(ValueError, match="expert's choice"):
        env.step(1.5)
    env.close()
