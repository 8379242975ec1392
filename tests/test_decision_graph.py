"""The decision with ``fixed_shapes``: the MPC's reads nothing on the host and decides as the
checked MPC does; behind the check (tests/test_fixed_check.py) the whole decision traces as one
graph (issue 68, the decision as one graph)."""

import dataclasses

import pytest
import torch
from torch._dynamo.testing import CompileCounter

from mmpc.drivers.mpc_driver import MPCDriver
from mmpc.drivers.verified import VerifiedDriver
from mmpc.highway.batched_world import BatchedWorld
from mmpc.mpc import MPC
from mmpc.scenario import build_mpc, load_scenario
from mmpc.verify import Verifier

SEEDS = list(range(90100, 90108))  # tuning seeds


@pytest.fixture(scope="module")
def scenario():
    return load_scenario("high_speed", {"sim": "batched"})


def test_fixed_shapes_decide_as_the_checked_mpc(scenario, one_thread):
    """12 warm-started steps of 8 lockstep episodes (scheduled restarts coincide at a step): the same
    goals and commands to float32 rounding; a restarting problem also ran the warm iterations."""
    checked = MPCDriver(build_mpc(scenario, compile=False), period=scenario.period)
    fixed = MPCDriver(build_mpc(scenario, compile=False, fixed_shapes=True), period=scenario.period)
    world = BatchedWorld.start(scenario, SEEDS)
    envs = list(range(len(SEEDS)))
    checked.reset(len(SEEDS))
    fixed.reset(len(SEEDS))
    restarts = 0
    for step in range(12):
        observation, _ = world.observe(envs)
        expected, decision = checked.decide(observation), fixed.decide(observation)
        assert torch.equal(decision.goal_index, expected.goal_index), step
        torch.testing.assert_close(decision.acceleration, expected.acceleration, atol=1e-3, rtol=0)
        torch.testing.assert_close(decision.steering, expected.steering, atol=1e-4, rtol=0)
        if step > 0:
            restarted = expected.iterations == 100
            warm = scenario.mpc.warm_iterations
            assert torch.equal(decision.iterations, torch.where(restarted, 100 + warm, warm))
            restarts += int(restarted.sum())
        assert expected.solve_ms > 0 and decision.solve_ms != decision.solve_ms  # NaN: not timed inside a graph
        world.apply(envs, expected.acceleration, expected.steering)
    assert restarts >= 4


def test_the_checked_decision_runs_as_one_graph(scenario, one_thread):
    """``verified:mpc`` with fixed shapes: the MPC's decision, the check and the guard compile with
    ``fullgraph=True`` (dynamo's graph, run eager) and, warm-started with fail-safes stored, drive as
    a twin decided eagerly, the second step without tracing again (the state carried between graphs)."""
    def expert():
        return VerifiedDriver(MPCDriver(build_mpc(scenario, compile=False, fixed_shapes=True), period=scenario.period),
                              Verifier.for_scenario(scenario, compile=False, fixed_shapes=True))

    graphed, eager = expert(), expert()
    traced = CompileCounter()  # runs dynamo's graphs eagerly and counts them
    decide = torch.compile(graphed.decide, fullgraph=True, backend=traced)
    world = BatchedWorld.start(scenario, SEEDS[:4])
    envs = list(range(4))
    graphed.reset(4)
    eager.reset(4)
    for step in range(4):  # the first step solves cold; the next ones warm-started, with a fail-safe stored
        observation, _ = world.observe(envs)
        expected = eager.decide(observation)
        decision = decide(observation) if step >= 2 else graphed.decide(observation)
        for name in ("acceleration", "steering", "verified", "failsafe", "goal_index"):
            assert torch.equal(getattr(decision, name), getattr(expected, name)), (step, name)
        world.apply(envs, expected.acceleration, expected.steering)
    assert traced.frame_count == 1


def test_fixed_shapes_are_refused_with_early_exits(scenario):
    exiting = dataclasses.replace(scenario.optimizer, exit_checks=(10,))
    with pytest.raises(ValueError, match="exit_checks"):
        build_mpc(scenario.replace(optimizer=exiting), compile=False, fixed_shapes=True)
    mpc = build_mpc(scenario, compile=False)
    with pytest.raises(TypeError, match="fixed_shapes"):
        MPC(mpc.optimizer, mpc.goal_sampler, mpc.meta_cost, mpc.road, fixed_shapes=1)
