"""mmpc.sim.observation against highway-env's own KinematicObservation on the same scenes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from highway_env.envs.common.observation import KinematicObservation

from mmpc.highway import HighwayEpisode
from mmpc.scenario import IDMTraffic, load_scenario
from mmpc.sim import SimConfig, vehicle_state
from mmpc.sim.observation import kinematics_observation


def _state_of(episode: HighwayEpisode, lanes: int, dtype: torch.dtype):
    vehicles = [episode.ego] + [v for v in episode.unwrapped.road.vehicles if v is not episode.ego]

    def row(values):
        return torch.tensor([values], dtype=torch.float64).to(dtype)

    return vehicle_state(row([v.position[0] for v in vehicles]), row([v.position[1] for v in vehicles]),
                         heading=row([v.heading for v in vehicles]), speed=row([v.speed for v in vehicles]),
                         length=row([v.LENGTH for v in vehicles]), config=SimConfig(lanes=lanes))


@pytest.mark.parametrize("lanes, count, rows", [(3, 30, 5), (6, 18, 7), (4, 40, 5)])
def test_observation_is_highway_env_s_along_episodes(lanes, count, rows):
    """Traffic without the window (vehicles beyond the 200 m perception distance and behind the ego), 3 seeds x 15 steps."""
    scenario = dataclasses.replace(load_scenario("cruise"), lanes=lanes, traffic=IDMTraffic(vehicles_count=count, window=None))
    worst = {torch.float64: 0.0, torch.float32: 0.0}
    for seed in range(3):
        episode = HighwayEpisode(scenario, seed)
        reference = KinematicObservation(episode.unwrapped, vehicles_count=rows)
        for step in range(15):
            episode.apply(0.5 * np.sin(step), 0.01 * np.cos(step))
            expected = np.asarray(reference.observe(), dtype=np.float64)
            for dtype in worst:
                ours = kinematics_observation(_state_of(episode, lanes, dtype), SimConfig(lanes=lanes), vehicles_count=rows)
                worst[dtype] = max(worst[dtype], float(np.abs(ours[0].double().numpy() - expected).max()))
        episode.close()
    assert worst[torch.float64] < 1e-7 and worst[torch.float32] < 1e-6  # highway-env returns float32


def test_dead_slots_missing_rows_and_the_perception_rules():
    x = torch.tensor([[100.0, 150.0, 95.0, 89.0, 350.0, 120.0]])
    y = torch.tensor([[4.0, 4.0, 8.0, 0.0, 4.0, 0.0]])
    alive = torch.tensor([[True, True, True, True, True, False]])
    observation = kinematics_observation(vehicle_state(x, y, speed=20.0, alive=alive, config=SimConfig(lanes=3)),
                                         SimConfig(lanes=3), vehicles_count=6)
    # seen: 95 m (5 m behind: within two lengths), 150 m; not seen: 89 m (11 m behind), 350 m (too far), the dead slot
    assert observation[0, :, 0].tolist() == [1.0, 1.0, 1.0, 0.0, 0.0, 0.0]
    assert observation[0, 1, 1].item() == pytest.approx(-5.0 / 200.0) and observation[0, 2, 1].item() == pytest.approx(50.0 / 200.0)
    assert observation[0, 1, 2].item() == pytest.approx(4.0 / 12.0)
    assert bool((observation[0, 3:] == 0).all())
    lone = kinematics_observation(vehicle_state(x[:, :1], y[:, :1], speed=20.0), SimConfig(lanes=3), vehicles_count=3)
    assert lone.shape == (1, 3, 5) and lone[0, 1:].abs().sum().item() == 0.0


@pytest.mark.parametrize("count", [0, 2.5, True])
def test_bad_vehicles_count_is_refused(count):
    state = vehicle_state(torch.zeros(1, 2), torch.zeros(1, 2))
    with pytest.raises(ValueError, match="`vehicles_count` must be an int >= 1"):
        kinematics_observation(state, SimConfig(), vehicles_count=count)
