"""Scripted stopped-traffic scenes: the fail-safe grid of the tests and ``scripts/bench_stopped_traffic.py``.

Every scene starts the ego at speed ``v`` behind stopped traffic (or a car that cuts in and
brakes hard) at a bumper-to-bumper gap of ``ratio`` times the braking distance ``v^2 / (2 a_max)``
at the optimizer's acceleration bound. A driver passes a scene without a collision and, where
the traffic blocks every lane (:attr:`StoppedTrafficScene.blocked`), ending at rest.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

from mmpc.scenario import EgoConfig, ScenarioConfig
from mmpc.traffic_config import ScriptedTraffic, ScriptedVehicle

#: Layouts of :func:`stopped_traffic_scene`.
LAYOUTS = ("wall", "single", "cut_in")
#: Below this speed the ego counts as stopped [m/s].
STOPPED_SPEED = 0.5


class StoppedTrafficScene(NamedTuple):
    """One scene of the grid.

    Fields:
        layout: ``"wall"`` (a stopped car in every lane of a 3-lane road, the ego in the middle),
            ``"single"`` (one stopped car on a 1-lane road) or ``"cut_in"`` (3 lanes: a car
            alongside at the ego's speed, ``ratio`` braking distances ahead, cuts into the ego's
            lane at 1 s and brakes at 6 m/s^2 to a stop from 2 s).
        speed: the ego's initial speed [m/s].
        ratio: initial bumper-to-bumper gap over the braking distance [-].
        gap: that gap [m].
        scenario: the scenario to drive (seeds, duration and MPC settings from the base).
    """

    layout: str
    speed: float
    ratio: float
    gap: float
    scenario: ScenarioConfig

    @property
    def name(self) -> str:
        return f"{self.layout}_v{self.speed:g}_x{self.ratio:g}"

    @property
    def blocked(self) -> bool:
        """Whether every lane ends blocked, so the ego must come to rest (a cut-in leaves the
        other lanes open)."""
        return self.layout != "cut_in"

    def passed(self, collisions: int, final_speed: float) -> bool:
        """No collision, and at rest at the end where every lane is blocked."""
        return collisions == 0 and (final_speed < STOPPED_SPEED or not self.blocked)


def stopped_traffic_scene(base: ScenarioConfig, layout: str, speed: float, ratio: float) -> StoppedTrafficScene:
    """The scene ``layout`` at ego speed ``speed`` [m/s] and gap ``ratio`` braking distances,
    driven with ``base``'s objective, optimizer and MPC (``v_max`` raised to ``speed`` if needed).

    The duration covers the approach at half the initial speed, the stop and 5 s at rest.
    """
    if layout not in LAYOUTS:
        raise ValueError(f"`layout` must be one of {LAYOUTS}; got {layout!r}")
    if not speed > 0 or not ratio > 0:
        raise ValueError(f"`speed` and `ratio` must be > 0; got {speed!r}, {ratio!r}")
    length = base.vehicle[0]
    gap = ratio * speed**2 / (2.0 * base.optimizer.a_max)
    ahead = gap + length  # centre to centre
    if layout == "wall":
        lanes, ego_lane = 3, 1
        vehicles = tuple(ScriptedVehicle(lane=k, x=ahead, speed=0.0, constant_speed=True) for k in range(lanes))
    elif layout == "single":
        lanes, ego_lane = 1, 0
        vehicles = (ScriptedVehicle(lane=0, x=ahead, speed=0.0, constant_speed=True),)
    else:
        lanes, ego_lane = 3, 1
        vehicles = (ScriptedVehicle(lane=2, x=ahead, speed=speed, cut_in_lane=1, cut_in_at=1.0, brake_at=2.0),)
    duration = math.ceil(ahead / (0.5 * speed) + speed / base.optimizer.a_max + 5.0)
    scenario = base.replace(
        name=f"{base.name}_{layout}_v{speed:g}_x{ratio:g}",
        lanes=lanes,
        duration=float(duration),
        ego=EgoConfig(speed=float(speed), lane=ego_lane),
        traffic=ScriptedTraffic(vehicles=vehicles),
        optimizer=dataclasses.replace(base.optimizer, v_max=max(base.optimizer.v_max, float(speed))),
    )
    return StoppedTrafficScene(layout, float(speed), float(ratio), gap, scenario)


def stopped_traffic_grid(
    base: ScenarioConfig,
    speeds: tuple[float, ...] = (10.0, 20.0, 30.0),
    ratios: tuple[float, ...] = (1.3, 2.0, 5.0),
) -> list[StoppedTrafficScene]:
    """Every wall and single-car scene over ``speeds`` x ``ratios``, and a cut-in per speed at
    the smallest ratio."""
    scenes = [stopped_traffic_scene(base, layout, v, r) for layout in ("wall", "single") for v in speeds for r in ratios]
    scenes += [stopped_traffic_scene(base, "cut_in", v, min(ratios)) for v in speeds]
    return scenes
