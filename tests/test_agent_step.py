"""mmpc.rl.agent_step: the one agent step of the training environments and the safe-agent driver.
Its contract: a step lasts ``decision_frames`` frames, rows may only leave it, and a row's commands
do not depend on the order or the company its rows come in."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from mmpc.config import load_config
from mmpc.drivers import Observation
from mmpc.rl.agent_step import AgentStep
from mmpc.rl.config import RLConfig
from mmpc.rl.safety import SafetyLayer, observation_rows
from mmpc.sim import SimEpisodes

pytestmark = pytest.mark.usefixtures("one_thread")

SEEDS = [0, 1, 2]
ACTIONS = torch.tensor([3, 0, 5])  # smoke grid (offset-major, speeds 15, 25)


@pytest.fixture(scope="module", params=["frame", "decision"])
def setup(request):
    smoke = load_config(RLConfig, "smoke")
    config = dataclasses.replace(smoke.env, replan=request.param, decision_frames=3)
    layer = SafetyLayer.for_scenario(smoke.scenario, config)
    return smoke.scenario, layer


def road_observation(sim: SimEpisodes, rows: list[int]) -> Observation:
    ego, vehicles, mask = sim.road_state()
    index = torch.as_tensor(rows)
    return Observation(ego[index], vehicles[index], mask[index], None, index)


def begin(scenario, layer, sim, count: int = 1) -> list[AgentStep]:
    """``count`` agent steps of the same actions at the same states, from one decision solve (the
    layer warm-starts each environment's decision solve from its last one)."""
    observation = road_observation(sim, list(range(len(SEEDS))))
    solve = layer.decision_solve(observation) if layer.config.replan == "decision" else None
    return [AgentStep.begin(layer, observation, ACTIONS, continuous=False, period=scenario.period, solve=solve)
            for _ in range(count)]


def test_a_step_lasts_its_frames_and_then_refuses_more(setup):
    scenario, layer = setup
    sim = SimEpisodes(scenario, SEEDS)
    step, = begin(scenario, layer, sim)
    rows = torch.arange(len(SEEDS))
    for frame in range(layer.config.decision_frames):
        assert not step.over and step.frames_done == frame
        control = step.frame(road_observation(sim, rows.tolist()), rows)
        assert control.acceleration.shape == (len(SEEDS),) and bool(torch.isfinite(control.acceleration).all())
    assert step.over
    with pytest.raises(RuntimeError, match="over"):
        step.frame(road_observation(sim, rows.tolist()), rows)


def test_every_row_starts_a_step_then_rows_may_leave_it_but_not_join_it(setup):
    scenario, layer = setup
    sim = SimEpisodes(scenario, SEEDS)
    step, = begin(scenario, layer, sim)
    with pytest.raises(ValueError, match=r"first frame of an agent step executes every row in order, \[0, 1, 2\]; got rows \[0, 2\]"):
        step.frame(road_observation(sim, [0, 2]), torch.tensor([0, 2]))
    step.frame(road_observation(sim, [0, 1, 2]), torch.arange(3))
    step.frame(road_observation(sim, [0, 2]), torch.tensor([0, 2]))
    with pytest.raises(ValueError, match=r"rows \[1\] must be among the last frame's \[0, 2\]"):
        step.frame(road_observation(sim, [1]), torch.tensor([1]))


def test_a_rows_commands_do_not_depend_on_the_order_or_company_of_its_rows(setup):
    """After the first frame, the same states handed in order, reversed, or without row 1 give
    every row the same commands: a held plan follows its row, not its position in the batch."""
    scenario, layer = setup
    sim = SimEpisodes(scenario, SEEDS)
    steps = begin(scenario, layer, sim, 3)
    everyone = torch.arange(3)
    first = [step.frame(road_observation(sim, everyone.tolist()), everyone) for step in steps][0]
    for _ in range(layer.config.decision_frames - 1):
        sim.step(torch.stack([first.acceleration, first.steering], dim=1).to(sim.state.x.dtype))
        states = road_observation(sim, everyone.tolist())
        forward = steps[0].frame(states, everyone)
        backward = steps[1].frame(observation_rows(states, everyone.flip(0)), everyone.flip(0))
        without = steps[2].frame(observation_rows(states, torch.tensor([0, 2])), torch.tensor([0, 2]))
        torch.testing.assert_close(backward.acceleration.flip(0), forward.acceleration)
        torch.testing.assert_close(backward.steering.flip(0), forward.steering)
        torch.testing.assert_close(without.acceleration, forward.acceleration[[0, 2]])
        first = forward
