"""The worlds the episode runner drives in: highway-env episodes one by one (the reference), or
all of them at once on the batched simulator (:mod:`mmpc.sim`); ``ScenarioConfig.sim`` chooses.

A world holds one environment per seed and answers the runner at every control step: what the
running environments observe (one batch for the driver), apply their commands, which episodes
are over; its ``episodes`` are what observers and step records read of each environment.
"""

from __future__ import annotations

from typing import NamedTuple, Optional, Protocol, Sequence

import numpy as np
import torch

from mmpc.device import run_device
from mmpc.drivers import Observation
from mmpc.highway.episode import HighwayEpisode
from mmpc.scenario import ScenarioConfig
from mmpc.sim import SimEpisodes, kinematics_observation
from mmpc.sim.reward import highway_reward


class World(Protocol):
    """E environments of one scenario stepped by the runner."""

    episodes: Sequence  # one view per environment: scenario, seed, ego.crashed, ego.on_road, done, observe()

    def observe(self, active: Sequence[int]) -> tuple[Observation, Sequence[Observation]]:
        """The batch the driver decides from (one row per ``active`` environment) and each row alone (E = 1)."""

    def apply(self, active: Sequence[int], acceleration: torch.Tensor, steering: torch.Tensor) -> None:
        """Apply one command per ``active`` environment, (A,) each [m/s^2], [rad]."""

    def observe_impact(self, index: int) -> Observation:
        """Environment ``index`` (E = 1) after the step in which its ego crashed, with that step's
        collision pushes taken back: the cars where they met (both worlds push colliding cars apart)."""

    def done(self) -> list[bool]:
        """Per environment: its episode is over."""

    def close(self) -> None:
        """Release the environments."""


def make_world(scenario: ScenarioConfig, seeds: Sequence[int], *, render: bool = False) -> World:
    """The world of ``scenario.sim`` with one environment per seed (``render``: highway-env only);
    the batched simulator runs on the run's device (:func:`mmpc.device.run_device`)."""
    if scenario.sim == "batched":
        if render:
            raise ValueError(f"scenario {scenario.name!r}: videos are drawn by highway-env; run it with --sim highway-env")
        return BatchedWorld(scenario, seeds, device=run_device())
    return HighwayEnvWorld(scenario, seeds, render=render)


class HighwayEnvWorld:
    """One highway-env episode per seed (:class:`mmpc.highway.HighwayEpisode`), stepped one after another."""

    def __init__(self, scenario: ScenarioConfig, seeds: Sequence[int], *, render: bool = False) -> None:
        self.episodes: list[HighwayEpisode] = []
        try:
            for seed in seeds:
                self.episodes.append(HighwayEpisode(scenario, seed, render=render))
        except BaseException:
            self.close()
            raise

    def observe(self, active: Sequence[int]) -> tuple[Observation, list[Observation]]:
        singles = [self.episodes[i].observe() for i in active]
        return stack_observations(singles, active), singles

    def apply(self, active: Sequence[int], acceleration: torch.Tensor, steering: torch.Tensor) -> None:
        for row, i in enumerate(active):
            self.episodes[i].apply(float(acceleration[row]), float(steering[row]))

    def observe_impact(self, index: int) -> Observation:
        return self.episodes[index].observe_impact()

    def done(self) -> list[bool]:
        return [episode.done for episode in self.episodes]

    def close(self) -> None:
        for episode in self.episodes:
            episode.close()


class EgoStatus(NamedTuple):
    """What a step record reads of the ego (as highway-env's vehicle attributes)."""

    crashed: bool
    on_road: bool


class SimEpisodeView:
    """Environment ``index`` of a :class:`BatchedWorld`, read as a :class:`mmpc.highway.HighwayEpisode` is."""

    def __init__(self, world: "BatchedWorld", index: int) -> None:
        self.world = world
        self.index = index
        self.scenario = world.scenario
        self.seed = world.seeds[index]

    @property
    def ego(self) -> EgoStatus:
        return EgoStatus(self.world.crashed[self.index], self.world.on_road[self.index])

    @property
    def done(self) -> bool:
        return self.world.ended[self.index]

    @property
    def reward(self) -> float:
        """highway-env's reward of the current state (:func:`mmpc.sim.reward.highway_reward`)."""
        return self.world.rewards[self.index]

    def observe(self) -> Observation:
        """The environment's current state for a driver (E = 1)."""
        return self.world.observe([self.index])[1][0]

    def kinematics(self) -> np.ndarray:
        """highway-env's ``Kinematics`` observation of the current state, (rows, features) float32."""
        return self.world.observe([self.index])[0].kinematics[0]


class ObservationRows(Sequence[Observation]):
    """Each row of a batch :class:`Observation` as its own (E = 1) observation on the host, made
    when it is read: a lockstep step of thousands of environments often reads none of them."""

    def __init__(self, batch: Observation) -> None:
        self._batch = batch
        self._host: Optional[Observation] = None

    def __len__(self) -> int:
        return self._batch.num_envs

    def __getitem__(self, row: int) -> Observation:
        row = range(len(self))[row]  # negative rows counted from the end; IndexError past it
        if self._host is None:
            self._host = self._batch.to("cpu")
        host, rows = self._host, slice(row, row + 1)
        kinematics = None if host.kinematics is None else host.kinematics[rows]
        mask = None if host.vehicle_mask is None else host.vehicle_mask[rows]
        return Observation(host.ego[rows], host.vehicles[rows], mask, kinematics)


class BatchedWorld:
    """One batched-simulator environment per seed (:class:`mmpc.sim.SimEpisodes`), all stepped
    by one simulator call; finished episodes stay as they ended. The batch it observes is on the
    simulator's ``device``; the single-environment observations are host copies."""

    def __init__(self, scenario: ScenarioConfig, seeds: Sequence[int], *, dtype: torch.dtype = torch.float32,
                 device: torch.device | str = "cpu") -> None:
        self.scenario = scenario
        self.seeds = [int(seed) for seed in seeds]
        self.sim = SimEpisodes(scenario, self.seeds, dtype=dtype, device=device)
        self.episodes = [SimEpisodeView(self, i) for i in range(self.sim.num_envs)]
        self._read_status()

    def _read_status(self) -> None:
        rewards = highway_reward(self.sim.state, self.sim.config)
        flags = torch.stack([self.sim.done, self.sim.crashed, self.sim.on_road]).to(rewards.dtype)
        ended, crashed, on_road, rewards = torch.cat([flags, rewards[None]]).tolist()  # one copy to the host
        self.ended: list[bool] = [flag == 1 for flag in ended]
        self.crashed: list[bool] = [flag == 1 for flag in crashed]
        self.on_road: list[bool] = [flag == 1 for flag in on_road]
        self.rewards: list[float] = rewards

    def observe(self, active: Sequence[int]) -> tuple[Observation, ObservationRows]:
        device = self.sim.device
        rows = torch.as_tensor(list(active), dtype=torch.long, device=device)
        ego, vehicles, mask = self.sim.road_state()
        kinematics = kinematics_observation(self.sim.state, self.sim.config, check=False)[rows].float().cpu().numpy()
        batch = Observation(ego[rows], vehicles[rows], mask[rows], kinematics, rows)
        return batch, ObservationRows(batch)

    def apply(self, active: Sequence[int], acceleration: torch.Tensor, steering: torch.Tensor) -> None:
        device, dtype = self.sim.device, self.sim.state.x.dtype
        rows = torch.as_tensor(list(active), dtype=torch.long, device=device)
        command = torch.zeros(self.sim.num_envs, 2, dtype=dtype, device=device)
        command[rows] = torch.stack([acceleration, steering], dim=1).to(device, dtype)
        running = torch.zeros(self.sim.num_envs, dtype=torch.bool, device=device)
        running[rows] = True
        self.sim.step(command, running)
        self._read_status()

    def observe_impact(self, index: int) -> Observation:
        ego, vehicles, mask = (field[index:index + 1].cpu() for field in self.sim.road_state(at_impact=True))
        return Observation(ego, vehicles, mask, None)

    def done(self) -> list[bool]:
        return self.ended

    def close(self) -> None:
        """Nothing to release."""


def stack_observations(observations: Sequence[Observation], env_ids: Sequence[int]) -> Observation:
    """Single-environment observations -> one batch; vehicle rows padded to the largest count
    (padding masked out)."""
    count = max(o.vehicles.shape[1] for o in observations)
    vehicles = observations[0].vehicles.new_zeros(len(observations), count, 4)
    mask = torch.zeros(len(observations), count, dtype=torch.bool)
    for row, o in enumerate(observations):
        present = o.vehicles.shape[1]
        vehicles[row, :present] = o.vehicles[0]
        mask[row, :present] = True if o.vehicle_mask is None else o.vehicle_mask[0]
    kinematics: Optional[np.ndarray] = None
    if all(o.kinematics is not None for o in observations):
        kinematics = np.concatenate([o.kinematics for o in observations], axis=0)
    return Observation(
        torch.cat([o.ego for o in observations], dim=0), vehicles, mask, kinematics,
        torch.as_tensor(list(env_ids), dtype=torch.long),
    )
