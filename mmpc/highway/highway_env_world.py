"""highway-env as a :class:`mmpc.highway.worlds.World`: one :class:`mmpc.highway.HighwayEpisode` per
environment, stepped one after another (the reference world)."""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np
import torch

from mmpc.drivers import Observation
from mmpc.highway.ego_terms import EgoTerms
from mmpc.highway.episode import HighwayEpisode
from mmpc.scenario import ScenarioConfig


class HighwayEnvWorld:
    """highway-env episodes as one world, stepped one after another from host copies of the commands.

    Args:
        episodes: one episode per environment (the world steps and closes them).
        dtype: the dtype of the states observed.
        kinematics: observations carry highway-env's ``Kinematics`` rows.
        device: where :meth:`done`, :meth:`speeds` and :meth:`ego_terms` are (observations are on the host).
        render: episodes it starts (:meth:`restart`) draw frames.
    """

    def __init__(self, episodes: Sequence[HighwayEpisode], *, dtype: torch.dtype = torch.float32, kinematics: bool = True,
                 device: torch.device | str = "cpu", render: bool = False) -> None:
        self.episodes = list(episodes)
        self.render = render
        self.dtype = dtype
        self.kinematics = kinematics
        self.device = torch.device(device)

    @classmethod
    def start(cls, scenario: ScenarioConfig, seeds: Sequence[int], *, render: bool = False, **settings) -> "HighwayEnvWorld":
        """A new episode of ``scenario`` per seed (``render``: drawn frames); ``settings``: the
        other arguments (by default observed with Kinematics rows)."""
        episodes: list[HighwayEpisode] = []
        try:
            for seed in seeds:
                episodes.append(HighwayEpisode(scenario, seed, render=render))
        except BaseException:
            for episode in episodes:
                episode.close()
            raise
        return cls(episodes, render=render, **settings)

    @property
    def num_envs(self) -> int:
        return len(self.episodes)

    def observe(self, rows: torch.Tensor | Sequence[int]) -> tuple[Observation, list[Observation]]:
        rows = _row_list(rows)
        singles = [self.episodes[i].observe(self.dtype, kinematics=self.kinematics) for i in rows]
        return stack_observations(singles, rows), singles

    def apply(self, rows: torch.Tensor | Sequence[int], acceleration: torch.Tensor, steering: torch.Tensor) -> None:
        for i, a, s in zip(_row_list(rows), acceleration.tolist(), steering.tolist()):
            self.episodes[i].apply(a, s)

    def restart(self, rows: torch.Tensor | Sequence[int], seeds: Sequence[int]) -> None:
        for row, seed in zip(_row_list(rows), seeds):
            scenario = self.episodes[row].scenario
            self.episodes[row].close()
            self.episodes[row] = HighwayEpisode(scenario, int(seed), render=self.render)

    def kinematics_rows(self, rows: torch.Tensor | Sequence[int], vehicles_count: int) -> np.ndarray:
        return np.stack([self.episodes[i].kinematics(vehicles_count) for i in _row_list(rows)])

    def ego_terms(self, rows: torch.Tensor | Sequence[int]) -> EgoTerms:
        return vehicle_terms([self.episodes[i].ego for i in _row_list(rows)], self.device)

    def observe_impact(self, index: int) -> Observation:
        return self.episodes[index].observe_impact()

    def done(self) -> torch.Tensor:
        return torch.tensor([episode.done for episode in self.episodes], device=self.device)

    def speeds(self, rows: torch.Tensor | Sequence[int]) -> torch.Tensor:
        return torch.tensor([float(self.episodes[i].ego.speed) for i in _row_list(rows)], dtype=torch.float64, device=self.device)

    def close(self) -> None:
        for episode in self.episodes:
            episode.close()


def vehicle_terms(vehicles: Sequence, device: torch.device | str = "cpu") -> EgoTerms:
    """What a task reward reads of highway-env vehicles (:class:`mmpc.highway.ego_terms.EgoTerms`):
    the lane is the one highway-env places the vehicle on (0 where it has none)."""
    values = torch.tensor([[v.speed, v.speed * np.cos(v.heading), v.position[1], v.lane_index[2] if v.lane_index is not None
                            else 0, v.crashed, v.on_road] for v in vehicles], dtype=torch.float64, device=device)
    return EgoTerms(*values.reshape(-1, 6).T)


def _row_list(rows: torch.Tensor | Sequence[int]) -> list[int]:
    """The environments ``rows`` (a long tensor or ints) as a list of ints."""
    return rows.tolist() if isinstance(rows, torch.Tensor) else list(rows)


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
