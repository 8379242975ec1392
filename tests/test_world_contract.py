"""The world protocol (:class:`mmpc.highway.worlds.World`), checked the same way over every world:
highway-env's and the batched simulator's, as the episode runner makes them (Kinematics rows,
float32) and as the safe RL agent step does (no Kinematics rows, float64).

Shapes, dtypes and devices of what ``observe`` / ``done`` / ``speeds`` / ``observe_impact`` /
``kinematics`` / ``ego_terms`` return, the per-environment views the runner reads, that ``apply``
advances and ``restart`` starts again exactly the rows asked, episodes that end stay ended, and ``close``.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import pytest
import torch

from mmpc.drivers import Observation
from mmpc.highway import HighwayEpisode
from mmpc.highway.batched_world import BatchedWorld
from mmpc.highway.highway_env_world import HighwayEnvWorld
from mmpc.highway.worlds import World, make_world
from mmpc.problem import EGO_V, EGO_X
from mmpc.scenario import load_scenario
from mmpc.sim import SimEpisodes

SCENARIO = load_scenario("cruise").replace(duration=0.5)
SEEDS = [3, 4, 5]

#: World name -> (it for the seeds, the dtype it observes in, it observes Kinematics rows).
WORLDS: dict[str, tuple[Callable[[], World], torch.dtype, bool]] = {
    "highway-env": (lambda: HighwayEnvWorld.start(SCENARIO, SEEDS), torch.float32, True),
    "highway-env, agent step": (lambda: HighwayEnvWorld([HighwayEpisode(SCENARIO, seed) for seed in SEEDS],
                                                        dtype=torch.float64, kinematics=False), torch.float64, False),
    "batched": (lambda: BatchedWorld.start(SCENARIO.replace(sim="batched"), SEEDS), torch.float32, True),
    "batched, agent step": (lambda: BatchedWorld(SimEpisodes(SCENARIO, SEEDS), dtype=torch.float64, kinematics=False),
                            torch.float64, False),
}


@pytest.fixture(params=list(WORLDS))
def world(request):
    make, dtype, kinematics = WORLDS[request.param]
    made = make()
    made.expected = (dtype, kinematics)  # what this world promises, for the checks
    yield made
    made.close()


def check_batch(world, batch: Observation, rows: list[int]) -> None:
    dtype, kinematics = world.expected
    count = len(rows)
    assert batch.ego.shape == (count, 6) and batch.ego.dtype == dtype and batch.ego.device == world.device
    assert batch.vehicles.dim() == 3 and batch.vehicles.shape[::2] == (count, 4) and batch.vehicles.dtype == dtype
    assert batch.vehicles.device == world.device
    assert batch.vehicle_mask.shape == batch.vehicles.shape[:2] and batch.vehicle_mask.dtype == torch.bool
    assert batch.env_ids.dtype == torch.long and batch.env_ids.tolist() == rows
    if kinematics:
        assert isinstance(batch.kinematics, np.ndarray) and batch.kinematics.dtype == np.float32
        assert batch.kinematics.ndim == 3 and batch.kinematics.shape[0] == count
    else:
        assert batch.kinematics is None


def test_a_new_world_holds_one_running_episode_per_seed(world):
    assert world.num_envs == len(world.episodes) == len(SEEDS)
    assert [episode.seed for episode in world.episodes] == SEEDS
    assert all(episode.scenario.name == SCENARIO.name for episode in world.episodes)
    done = world.done()
    assert done.shape == (len(SEEDS),) and done.dtype == torch.bool and done.device == world.device
    assert not bool(done.any())
    for episode in world.episodes:
        assert episode.done is False and episode.ego.crashed is False and bool(episode.ego.on_road) is True
        assert isinstance(episode.reward, float)


def test_observe_returns_the_rows_asked_in_their_order_and_each_alone_on_the_host(world):
    batch, singles = world.observe([2, 0])
    check_batch(world, batch, [2, 0])
    assert len(singles) == 2
    for row, single in enumerate(singles):
        assert single.ego.shape == (1, 6) and single.ego.device.type == "cpu"
        assert torch.equal(single.ego, batch.ego[row:row + 1].cpu())
        present = single.vehicles.shape[1]
        assert torch.equal(single.vehicles[0], batch.vehicles[row, :present].cpu())
    alone, _ = world.observe([0])
    assert torch.equal(alone.ego[0], batch.ego[1])
    from_tensor, _ = world.observe(torch.tensor([2, 0], device=world.device))
    assert torch.equal(from_tensor.ego, batch.ego) and torch.equal(from_tensor.vehicles, batch.vehicles)


def test_speeds_are_the_observed_egos_speeds(world):
    batch, _ = world.observe([1, 2])
    speeds = world.speeds(torch.tensor([1, 2], device=world.device))
    assert speeds.shape == (2,) and speeds.dtype == torch.float64 and speeds.device == world.device
    assert torch.allclose(speeds, batch.ego[:, EGO_V].double(), rtol=1e-6)
    assert torch.equal(world.speeds([1, 2]), speeds)


def test_apply_advances_exactly_the_rows_asked(world):
    before, _ = world.observe([0, 1, 2])
    acceleration, steering = torch.tensor([1.0, -1.0]), torch.zeros(2)
    world.apply([2, 0], acceleration, steering)
    after, _ = world.observe([0, 1, 2])
    assert torch.equal(after.ego[1], before.ego[1]) and torch.equal(after.vehicles[1], before.vehicles[1])
    assert bool((after.ego[[0, 2], EGO_X] > before.ego[[0, 2], EGO_X]).all())
    assert float(after.ego[2, EGO_V]) > float(after.ego[0, EGO_V])  # row 2 accelerated, row 0 braked
    world.apply(torch.tensor([1], device=world.device), torch.zeros(1), torch.zeros(1))  # rows as a tensor
    moved, _ = world.observe([0, 1, 2])
    assert torch.equal(moved.ego[[0, 2]], after.ego[[0, 2]]) and bool(moved.ego[1, EGO_X] > after.ego[1, EGO_X])


def test_episodes_end_with_their_time_and_stay_ended(world):
    steps = round(SCENARIO.duration * SCENARIO.frequency)
    for step in range(steps):
        assert not bool(world.done().any()), step
        world.apply([0, 1, 2], torch.zeros(3), torch.zeros(3))
    assert bool(world.done().all()) and all(episode.done for episode in world.episodes)
    impact = world.observe_impact(1)
    assert impact.ego.shape == (1, 6) and impact.ego.device.type == "cpu" and impact.kinematics is None
    assert impact.vehicles.dim() == 3 and impact.vehicles.shape[0] == 1


def test_restart_starts_the_rows_asked_from_their_seeds(world):
    start, _ = world.observe([0, 1, 2])
    world.apply([0, 1, 2], torch.ones(3), torch.zeros(3))
    world.restart(torch.tensor([1]), [SEEDS[1]])
    again, _ = world.observe([0, 1, 2])
    assert torch.equal(again.ego[1], start.ego[1]) and not torch.equal(again.ego[0], start.ego[0])
    world.restart(torch.tensor([2]), [9])
    assert [episode.seed for episode in world.episodes] == [3, 4, 9] and not bool(world.done().any())
    scenario = SCENARIO.replace(sim="batched") if isinstance(world, BatchedWorld) else SCENARIO
    reference = make_world(scenario, [9])
    torch.testing.assert_close(world.observe([2])[0].ego.double(), reference.observe([0])[0].ego.double())
    reference.close()


def test_kinematics_and_ego_terms_of_the_rows_asked(world):
    """What the safe environments read: the agent's Kinematics rows and what a task reward reads of the egos."""
    kinematics = world.kinematics_rows([2, 0], 4)
    assert kinematics.shape == (2, 4, 5) and kinematics.dtype == np.float32
    assert (kinematics[:, 0, 0] == 1).all()  # the ego's row is present
    np.testing.assert_array_equal(kinematics[1], world.kinematics_rows([0], 4)[0])
    terms = world.ego_terms([2, 0])
    for term in terms:
        assert term.shape == (2,) and term.dtype == torch.float64 and term.device == world.device
    assert torch.equal(terms.speed, world.speeds([2, 0]))
    observed = world.observe([2, 0])[0].ego.double()
    torch.testing.assert_close(terms.y, observed[:, 1], atol=1e-4, rtol=0)
    assert terms.crashed.tolist() == [0, 0] and terms.on_road.tolist() == [1, 1]
    assert all(0 <= lane < SCENARIO.lanes for lane in terms.lane.tolist())


def test_make_world_chooses_the_scenario_s_world():
    highway = make_world(SCENARIO, [0])
    try:
        assert isinstance(highway, HighwayEnvWorld)
    finally:
        highway.close()
    assert isinstance(make_world(SCENARIO.replace(sim="batched"), [0]), BatchedWorld)
    with pytest.raises(ValueError, match="highway-env"):
        make_world(SCENARIO.replace(sim="batched"), [0], render=True)
