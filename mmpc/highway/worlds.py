"""The world protocol: E environments of one scenario stepped together, as the episode runner
(:func:`mmpc.highway.run_lockstep`) and the safe RL agent step (:func:`mmpc.rl.agent_step.run_agent_step`)
drive them; :func:`make_world` makes the runner's world of a scenario.

Two worlds implement it: highway-env episodes one by one (the reference,
:class:`mmpc.highway.highway_env_world.HighwayEnvWorld`), or all of them at once on the batched
simulator (:class:`mmpc.highway.batched_world.BatchedWorld`); ``ScenarioConfig.sim`` chooses.
"""

from __future__ import annotations

from typing import Protocol, Sequence

import torch

from mmpc.device import run_device
from mmpc.drivers import Observation
from mmpc.highway.batched_world import BatchedWorld
from mmpc.highway.highway_env_world import HighwayEnvWorld
from mmpc.scenario import ScenarioConfig


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
        """The batch of the environments ``rows`` (one row each, ``env_ids`` their ids: ``rows``
        unless the world was given stable ids of its own; with
        highway-env's ``Kinematics`` rows where the world observes them) and each row alone (E = 1)."""

    def apply(self, rows: torch.Tensor | Sequence[int], acceleration: torch.Tensor, steering: torch.Tensor) -> None:
        """Apply one command per environment of ``rows``, (R,) each [m/s^2], [rad], and advance
        those environments one frame (the others stay as they are)."""

    def observe_impact(self, index: int) -> Observation:
        """Environment ``index`` (E = 1) after the step in which its ego crashed, with that step's
        collision pushes taken back: the cars where they met (both worlds push colliding cars apart)."""

    def done(self) -> torch.Tensor:
        """(E,) bool on :attr:`device`: the environment's episode is over (its ego crashed or its time is up)."""

    def speeds(self, rows: torch.Tensor | Sequence[int]) -> torch.Tensor:
        """(R,) float64 on :attr:`device`: the egos' speeds [m/s]."""

    def close(self) -> None:
        """Release the environments."""


def make_world(scenario: ScenarioConfig, seeds: Sequence[int], *, render: bool = False) -> World:
    """The world of ``scenario.sim`` with one environment per seed (``render``: highway-env only);
    the batched simulator runs on the run's device (:func:`mmpc.device.run_device`)."""
    if scenario.sim == "batched":
        if render:
            raise ValueError(f"scenario {scenario.name!r}: videos are drawn by highway-env; run it with --sim highway-env")
        return BatchedWorld.start(scenario, seeds, device=run_device())
    return HighwayEnvWorld.start(scenario, seeds, render=render)
