"""The check with ``fixed_shapes``: it reads nothing on the host (the trace of the checked decision:
tests/test_decision_graph.py) and drives as the checked guard does; what it cannot hold or read it
does not verify (issue 68)."""

import pytest
import torch

import mmpc.verify.verifier as verifier_module
from mmpc.drivers.mpc_driver import MPCDriver
from mmpc.drivers.verified import guarded_command
from mmpc.highway.batched_world import BatchedWorld
from mmpc.scenario import build_mpc, load_scenario
from mmpc.verify import Guard, Verifier

SEEDS = list(range(90100, 90108))  # tuning seeds


@pytest.fixture(scope="module")
def scenario():
    return load_scenario("high_speed", {"sim": "batched"})


@pytest.fixture(scope="module")
def states(scenario):
    """Observations of 8 lockstep episodes after 10 steps of the checked MPC behind the checked guard."""
    world = BatchedWorld.start(scenario, SEEDS)
    mpc = build_mpc(scenario, compile=False)
    driver, guard, envs = MPCDriver(mpc, period=scenario.period), Guard(Verifier.for_scenario(scenario, compile=False)), list(range(8))
    driver.reset(8)
    for _ in range(10):
        observation, _ = world.observe(envs)
        decision = driver.decide(observation)
        guarded = guarded_command(guard, observation, decision.acceleration, decision.steering, decision.plan, mpc)
        world.apply(envs, guarded.acceleration, guarded.steering)
    return world.observe(envs)[0]


def checks(scenario):
    return (Verifier.for_scenario(scenario, compile=False),
            Verifier.for_scenario(scenario, compile=False, fixed_shapes=True))


def commands(observation, count=6, seed=0):
    generator = torch.Generator().manual_seed(seed)
    acceleration = torch.empty(observation.num_envs, count).uniform_(-5.0, 3.0, generator=generator)
    steering = torch.empty(observation.num_envs, count).uniform_(-0.05, 0.05, generator=generator)
    return acceleration.to(observation.ego.dtype), steering.to(observation.ego.dtype)


def test_the_fixed_shape_guard_drives_as_the_checked_one(scenario, one_thread):
    """30 steps of 8 lockstep episodes, the checked MPC asking: the same commands, verdicts and
    fail-safes from both guards, the guard stepping in at some steps."""
    world = BatchedWorld.start(scenario, SEEDS)
    mpc = build_mpc(scenario, compile=False)
    driver, envs = MPCDriver(mpc, period=scenario.period), list(range(8))
    checked, fixed = (Guard(verifier) for verifier in checks(scenario))
    driver.reset(8)
    changed = 0
    for step in range(30):
        observation, _ = world.observe(envs)
        decision = driver.decide(observation)
        expected, guarded = (guarded_command(guard, observation, decision.acceleration, decision.steering, decision.plan, mpc)
                             for guard in (checked, fixed))
        assert torch.equal(guarded.verified, expected.verified) and torch.equal(guarded.failsafe, expected.failsafe), step
        torch.testing.assert_close(guarded.acceleration, expected.acceleration, atol=1e-5, rtol=0)
        torch.testing.assert_close(guarded.steering, expected.steering, atol=1e-6, rtol=0)
        changed += int(expected.changed.sum())
        world.apply(envs, expected.acceleration, expected.steering)
    assert changed >= 5
    assert fixed.stored_ids() == checked.stored_ids() == envs


def test_fixed_shapes_give_the_checked_verdicts(scenario, states, one_thread):
    checked, fixed = checks(scenario)
    acceleration, steering = commands(states)
    expected = checked.check(states.ego, states.vehicles, states.vehicle_mask, acceleration, steering)
    verdict = fixed.check(states.ego, states.vehicles, states.vehicle_mask, acceleration, steering)
    assert expected.verified.any() and not expected.verified.all() and not verdict.crowded.any()
    assert torch.equal(verdict.verified, expected.verified) and torch.equal(verdict.lane, expected.lane)


def test_what_the_fixed_check_cannot_read_it_does_not_verify(scenario, states, one_thread):
    """A NaN ego, a NaN present car or a NaN command: that environment's (or command's) verdict is
    False, the others' unchanged; a NaN car that is absent changes nothing. The checked path raises."""
    checked, fixed = checks(scenario)
    acceleration, steering = commands(states)
    expected = fixed.check(states.ego, states.vehicles, states.vehicle_mask, acceleration, steering)
    ego, vehicles, mask = states.ego.clone(), states.vehicles.clone(), states.vehicle_mask.clone()
    ego[0, 0] = float("nan")
    vehicles[1, mask[1].nonzero()[0, 0], 2] = float("nan")
    vehicles = torch.cat([vehicles, torch.full_like(vehicles[:, :1], float("nan"))], dim=1)  # a NaN car, absent
    mask = torch.cat([mask, torch.zeros_like(mask[:, :1])], dim=1)
    acceleration[3, 1] = float("nan")
    verdict = fixed.check(ego, vehicles, mask, acceleration, steering)
    assert not verdict.verified[:2].any() and not verdict.verified[3, 1]
    kept = torch.ones_like(expected.verified)
    kept[:2], kept[3, 1] = False, False
    assert torch.equal(verdict.verified[kept], expected.verified[kept])
    with pytest.raises(ValueError, match="finite"):
        checked.check(ego, vehicles, mask, acceleration, steering)


def test_an_environment_past_the_buffer_is_not_verified(scenario, states, monkeypatch, one_thread):
    """With room for few (car, pose) tests per environment the later environments of the batch do
    not fit: their commands are not verified (never wrongly verified); the first one's verdicts hold."""
    checked, fixed = checks(scenario)
    acceleration, steering = commands(states)
    expected = checked.check(states.ego, states.vehicles, states.vehicle_mask, acceleration, steering)
    monkeypatch.setattr(verifier_module, "TRIPLES_PER_ENV", 150)  # the first ~2 of 8 fit
    verdict = fixed.check(states.ego, states.vehicles, states.vehicle_mask, acceleration, steering)
    assert verdict.crowded[-1] and not verdict.crowded[0] and not expected.crowded.any()
    assert not verdict.verified[-1].any() and expected.verified[-1].any()
    assert not (verdict.verified & ~expected.verified).any()
    assert torch.equal(verdict.verified[0], expected.verified[0])


def test_fixed_shapes_must_be_a_bool(scenario):
    with pytest.raises(TypeError, match="fixed_shapes"):
        Verifier.for_scenario(scenario, fixed_shapes="yes")


def test_both_checks_refuse_commands_of_the_wrong_shape_and_answer_an_empty_batch(scenario):
    for verifier in checks(scenario):
        ego, vehicles, mask = torch.zeros(2, 6), torch.zeros(2, 3, 4), torch.ones(2, 3, dtype=torch.bool)
        with pytest.raises(ValueError, match=r"must be \(E=2, K\) each"):
            verifier.check(ego, vehicles, mask, torch.zeros(2, 2), torch.zeros(3, 2))
        verdict = verifier.check(ego[:0], vehicles[:0], mask[:0], torch.zeros(0, 2), torch.zeros(0, 2))
        assert verdict.verified.shape == verdict.lane.shape == (0, 2) and verdict.crowded.shape == (0,)
        guarded = Guard(verifier).choose(ego[:0], vehicles[:0], None, torch.zeros(0, dtype=torch.long), torch.zeros(0),
                                         torch.zeros(0))
        assert guarded.acceleration.shape == guarded.verified.shape == (0,)
