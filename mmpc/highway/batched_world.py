"""The batched simulator (:mod:`mmpc.sim`) as a :class:`mmpc.highway.worlds.World`: every
environment a row of one :class:`mmpc.sim.SimEpisodes`, all stepped by one simulator call."""

from __future__ import annotations

from typing import NamedTuple, Optional, Sequence

import numpy as np
import torch

from mmpc.drivers import Observation
from mmpc.highway.ego_terms import EgoTerms
from mmpc.scenario import ScenarioConfig
from mmpc.sim import SimEpisodes, kinematics_observation
from mmpc.sim.reward import highway_reward
from mmpc.sim.simulator import OVERFLOW
from mmpc.sim.state import on_road


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

    @property
    def seed(self) -> int:
        return self.world.seeds[self.index]

    @property
    def ego(self) -> EgoStatus:
        status = self.world.status()
        return EgoStatus(status.crashed[self.index], status.on_road[self.index])

    @property
    def done(self) -> bool:
        return self.world.status().ended[self.index]

    @property
    def reward(self) -> float:
        """highway-env's reward of the current state (:func:`mmpc.sim.reward.highway_reward`)."""
        return self.world.status().rewards[self.index]

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


class Status(NamedTuple):
    """Per environment, on the host: the episode ended, the ego crashed, is on the road, highway-env's reward."""

    ended: list[bool]
    crashed: list[bool]
    on_road: list[bool]
    rewards: list[float]


class BatchedWorld:
    """The environments of one :class:`mmpc.sim.SimEpisodes` as one world; finished episodes stay
    as they ended. The batch it observes is on the simulator's ``device``; the single-environment
    observations are host copies.

    Args:
        sim: the simulator's episodes (the world steps them).
        dtype: the dtype of the states observed (default: the simulator's).
        kinematics: observations carry highway-env's ``Kinematics`` rows.
    """

    def __init__(self, sim: SimEpisodes, *, dtype: Optional[torch.dtype] = None, kinematics: bool = True) -> None:
        self.sim = sim
        self.scenario = sim.scenario
        self.dtype = sim.state.x.dtype if dtype is None else dtype
        self.kinematics = kinematics
        self.seeds: list[int] = sim.seeds.tolist()
        self.episodes = [SimEpisodeView(self, i) for i in range(sim.num_envs)]
        self._status: Optional[Status] = None

    @classmethod
    def start(cls, scenario: ScenarioConfig, seeds: Sequence[int], *, dtype: torch.dtype = torch.float32,
              device: torch.device | str = "cpu") -> "BatchedWorld":
        """A new episode of ``scenario`` per seed on ``device``, observed with Kinematics rows."""
        return cls(SimEpisodes(scenario, [int(seed) for seed in seeds], dtype=dtype, device=device))

    @property
    def device(self) -> torch.device:
        return self.sim.device

    @property
    def num_envs(self) -> int:
        return self.sim.num_envs

    def status(self) -> Status:
        """The current states' :class:`Status`, read in one copy to the host after each step (when asked for);
        ``ValueError`` if an environment was given a non-finite command or overflowed the simulator's
        buffers (:class:`mmpc.sim.SimEpisodes`, which checks both on the device)."""
        if self._status is None:
            sim = self.sim
            rewards = highway_reward(sim.state, sim.config)
            flags = torch.stack([sim.done, sim.crashed, sim.on_road, sim.refused, sim.overflowed]).to(rewards.dtype)
            ended, crashed, on_road, refused, overflowed, rewards = torch.cat([flags, rewards[None]]).tolist()  # one copy
            for flags, what in ((refused, "were given a command that is not finite (NaN or inf)"),
                                (overflowed, OVERFLOW)):
                if any(flags):
                    rows = [row for row, flag in enumerate(flags) if flag == 1]
                    raise ValueError(f"environments {rows[:8]} (seeds {[self.seeds[row] for row in rows[:8]]}) {what}")
            self._status = Status([flag == 1 for flag in ended], [flag == 1 for flag in crashed],
                                  [flag == 1 for flag in on_road], rewards)
        return self._status

    def _rows(self, rows: torch.Tensor | Sequence[int]) -> torch.Tensor:
        return torch.as_tensor(rows if isinstance(rows, torch.Tensor) else list(rows), dtype=torch.long, device=self.device)

    def observe(self, rows: torch.Tensor | Sequence[int]) -> tuple[Observation, ObservationRows]:
        rows = self._rows(rows)
        ego, vehicles, mask = self.sim.road_state()
        kinematics = None
        if self.kinematics:
            kinematics = kinematics_observation(self.sim.state, self.sim.config, check=False)[rows].float().cpu().numpy()
        batch = Observation(ego[rows].to(self.dtype), vehicles[rows].to(self.dtype), mask[rows], kinematics, rows)
        return batch, ObservationRows(batch)

    def apply(self, rows: torch.Tensor | Sequence[int], acceleration: torch.Tensor, steering: torch.Tensor) -> None:
        device, dtype = self.device, self.sim.state.x.dtype
        rows = self._rows(rows)
        command = torch.zeros(self.num_envs, 2, dtype=dtype, device=device)
        command[rows] = torch.stack([acceleration, steering], dim=1).to(device, dtype)
        running = torch.zeros(self.num_envs, dtype=torch.bool, device=device)
        running[rows] = True
        self.sim.step(command, running)
        self._status = None

    def restart(self, rows: torch.Tensor, seeds: Sequence[int]) -> None:
        """Start a new episode in each environment of ``rows`` (R,) from its seed in ``seeds``."""
        self.sim.reset(rows, seeds)
        for row, seed in zip(rows.tolist(), seeds):
            self.seeds[row] = int(seed)
        self._status = None

    def kinematics_rows(self, rows: torch.Tensor | Sequence[int], vehicles_count: int) -> np.ndarray:
        observation = kinematics_observation(self.sim.state, self.sim.config, vehicles_count=vehicles_count, check=False)
        return observation[self._rows(rows)].float().cpu().numpy()

    def ego_terms(self, rows: torch.Tensor | Sequence[int]) -> EgoTerms:
        state, rows = self.sim.state, self._rows(rows)
        speed, heading, y = state.speed[rows, 0].double(), state.heading[rows, 0].double(), state.y[rows, 0].double()
        return EgoTerms(speed, speed * torch.cos(heading), y, state.lane[rows, 0].double(), state.crashed[rows, 0].double(),
                        on_road(state.y[rows, 0], self.sim.config).double())

    def observe_impact(self, index: int) -> Observation:
        ego, vehicles, mask = (field[index:index + 1].cpu() for field in self.sim.road_state(at_impact=True))
        return Observation(ego, vehicles, mask, None)

    def done(self) -> torch.Tensor:
        return self.sim.done

    def speeds(self, rows: torch.Tensor | Sequence[int]) -> torch.Tensor:
        return self.sim.state.speed[self._rows(rows), 0].double()

    def close(self) -> None:
        """Nothing to release."""
