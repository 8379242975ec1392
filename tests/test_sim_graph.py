"""The simulator's step as one graph: fixed-size compactions, their overflow flags, and a trace
of the whole step with no graph break (what a CUDA graph can capture)."""

from __future__ import annotations

import functools

import pytest
import torch

from mmpc.scenario import load_scenario
from mmpc.sim import HighwaySimulator, SimConfig, SimEpisodes, vehicle_state
from mmpc.sim import collision
from mmpc.compaction import capacity, compact
from mmpc.sim.episodes import episode_step
from mmpc.sim.threats import Orders


def test_compact_keeps_the_first_entries_in_row_major_order_and_marks_the_rest():
    mask = torch.tensor([[False, True, True], [True, False, True]])
    found = compact(mask, 3)
    assert [index.tolist() for index in found.index] == [[0, 0, 1], [1, 2, 0]]
    assert found.valid.tolist() == [True, True, True]
    assert found.dropped.tolist() == [[False, False, False], [False, False, True]]
    roomy = compact(mask, 6, fill=7)
    assert roomy.valid.tolist() == [True] * 4 + [False] * 2
    assert roomy.index[0][4:].tolist() == [7, 7] and not roomy.dropped.any()
    with pytest.raises(ValueError, match="`capacity` must be >= 1; got 0"):
        compact(mask, 0)


def test_capacity_is_an_average_per_environment_within_a_floor_and_everything():
    assert capacity(True, 1024, 2.0, 64, 10**6) == 2048
    assert capacity(True, 3, 2.0, 64, 10**6) == 64
    assert capacity(True, 3, 2.0, 64, 20) == 20
    assert capacity(False, 1024, 2.0, 64, 10**6) is None  # exact sizes, read on the host


def test_a_collision_buffer_too_small_is_reported_not_hidden(monkeypatch):
    """Three cars nose to tail make three close pairs; a buffer of one leaves two untested."""
    state = vehicle_state(torch.tensor([[0.0, 3.0, 6.0]]), torch.zeros(1, 3), speed=20.0)
    for fixed in (False, True):
        test, untested = collision.pair_collisions(state, 0.1, fixed)
        assert not untested.any() and test.intersecting[0].sum() == 2
    monkeypatch.setattr(collision, "PAIRS_PER_ENV", 0.0)
    monkeypatch.setattr(collision, "PAIRS_FLOOR", 1)
    test, untested = collision.pair_collisions(state, 0.1, True)
    assert untested.tolist() == [True] and test.intersecting[0].sum() == 1  # the first pair only
    with pytest.raises(RuntimeError, match="buffers hold"):
        HighwaySimulator(SimConfig(lanes=1, fixed_shapes=True)).step(state, torch.zeros(1, 2))


def test_fixed_shapes_drive_the_episodes_of_exact_sizes():
    """Buffers that hold the traffic and a window's rounds that suffice change nothing."""
    scenario = load_scenario("cruise", {"sim": "batched"})
    exact, fixed = (SimEpisodes(scenario, list(range(16)), fixed_shapes=flag) for flag in (False, True))
    generator = torch.Generator().manual_seed(0)
    for _ in range(60):
        command = torch.stack([torch.rand(16, generator=generator) * 4 - 2,
                               (torch.rand(16, generator=generator) - 0.5) * 0.05], dim=1)
        exact.step(command)
        fixed.step(command)
    assert exact.crashed.any()  # the random commands crash some egos: pile-ups are compared too
    assert all(torch.equal(a, b) for a, b in zip(exact.state, fixed.state))
    assert not fixed.overflowed.any() and not fixed.refused.any()


@pytest.mark.parametrize("name, orders", [("cruise", False), ("cruise_threats", False), ("high_speed", True)])
def test_a_step_traces_as_one_graph(name, orders):
    """``torch.compile(fullgraph=True)`` can take the step whole: no graph break, no
    data-dependent shape, no value read on the host."""
    scenario = load_scenario(name, {"sim": "batched"})
    episodes = SimEpisodes(scenario, [0, 1, 2, 3], fixed_shapes=True)
    step = functools.partial(episode_step, episodes.simulator, scenario.traffic.window, scenario.frequency)
    given = Orders(torch.ones_like(episodes.state.lane), -torch.ones_like(episodes.state.lane)) if orders else None
    arguments = (episodes.state, torch.zeros(4, 2), torch.ones(4, dtype=torch.bool), episodes.seeds, episodes.steps,
                 episodes.applied, episodes.refused, episodes.overflowed, given)
    explained = torch._dynamo.explain(step)(*arguments)
    assert (explained.graph_count, explained.graph_break_count) == (1, 0), explained.break_reasons
    traced = torch.compile(step, fullgraph=True, backend="eager")(*arguments)
    expected = step(*arguments)
    assert all(torch.equal(a, b) for a, b in zip(traced.state, expected.state))
    for field in expected._fields[1:]:
        assert torch.equal(getattr(traced, field), getattr(expected, field)), field
