"""The world protocol: E environments of one scenario stepped together, as the episode runner
(:func:`mmpc.highway.run_lockstep`) and the safe RL environments (:class:`mmpc.rl.engine.SafeEnvs`)
drive them; :func:`make_world` makes the runner's world of a scenario.

Two worlds implement it: highway-env episodes one by one (the reference,
:class:`mmpc.highway.highway_env_world.HighwayEnvWorld`), or all of them at once on the batched
simulator (:class:`mmpc.highway.batched_world.BatchedWorld`); ``ScenarioConfig.sim`` chooses.
"""

from __future__ import annotations

from typing import Protocol, Sequence

import numpy as np
import torch

from mmpc.device import run_device
from mmpc.drivers import Observation
from mmpc.highway.batched_world import BatchedWorld
from mmpc.highway.ego_terms import EgoTerms
from mmpc.highway.highway_env_world import HighwayEnvWorld
from mmpc.scenario import ScenarioConfig
from mmpc.sim import SimEpisodes


class World(Protocol):
    """E environments of one scenario, stepped together.

    ``rows`` select environments: a (R,) long tensor or a sequence of ints, each in [0, E). The
    world's ``dtype`` is that of the states it observes; its ``device`` holds the batch it
    observes, :meth:`done` and :meth:`speeds` (single-environment observations are on the host).
    """

    dtype: torch.dtype
    device: torch.device
    episodes: Sequence  # one view per environment: scenario, seed, ego.crashed, ego.on_road, done, reward, observe()

    @property
    def num_envs(self) -> int:
        """E."""

    def observe(self, rows: torch.Tensor | Sequence[int]) -> tuple[Observation, Sequence[Observation]]:
        """The batch of the environments ``rows`` (one row each, ``env_ids`` = ``rows``; with
        highway-env's ``Kinematics`` rows where the world observes them) and each row alone (E = 1)."""

    def apply(self, rows: torch.Tensor | Sequence[int], acceleration: torch.Tensor, steering: torch.Tensor) -> None:
        """Apply one command per environment of ``rows``, (R,) each [m/s^2], [rad], and advance
        those environments one frame (the others stay as they are)."""

    def restart(self, rows: torch.Tensor, seeds: Sequence[int]) -> None:
        """Start a new episode in each environment of ``rows`` (R,) from its seed in ``seeds``."""

    def kinematics_rows(self, rows: torch.Tensor | Sequence[int], vehicles_count: int) -> np.ndarray:
        """(R, vehicles_count, 5) float32 highway-env ``Kinematics`` observations of the environments ``rows``."""

    def ego_terms(self, rows: torch.Tensor | Sequence[int]) -> EgoTerms:
        """What a task reward reads of the egos of ``rows`` (:class:`EgoTerms`)."""

    def observe_impact(self, index: int) -> Observation:
        """Environment ``index`` (E = 1) after the step in which its ego crashed, with that step's
        collision pushes taken back: the cars where they met (both worlds push colliding cars apart)."""

    def done(self) -> torch.Tensor:
        """(E,) bool on :attr:`device`: the environment's episode is over (its ego crashed or its time is up)."""

    def speeds(self, rows: torch.Tensor | Sequence[int]) -> torch.Tensor:
        """(R,) float64 on :attr:`device`: the egos' speeds [m/s]."""

    def close(self) -> None:
        """Release the environments."""


def make_world(scenario: ScenarioConfig, seeds: Sequence[int], *, render: bool = False, dtype: torch.dtype = torch.float32,
               kinematics: bool = True, device: torch.device | str | None = None) -> World:
    """The world of ``scenario.sim`` with one environment per seed.

    Args:
        render: highway-env draws frames (the batched simulator refuses).
        dtype: the dtype of the states observed.
        kinematics: observations carry highway-env's ``Kinematics`` rows.
        device: where the batched simulator runs and where highway-env's :meth:`World.done` and
            :meth:`World.speeds` are; default the run's (:func:`mmpc.device.run_device`; highway-env: the host).
    """
    if scenario.sim == "batched":
        if render:
            raise ValueError(f"scenario {scenario.name!r}: videos are drawn by highway-env; run it with --sim highway-env")
        sim = SimEpisodes(scenario, [int(seed) for seed in seeds], device=run_device() if device is None else device)
        return BatchedWorld(sim, dtype=dtype, kinematics=kinematics)
    return HighwayEnvWorld.start(scenario, seeds, render=render, dtype=dtype, kinematics=kinematics,
                                 device="cpu" if device is None else device)
