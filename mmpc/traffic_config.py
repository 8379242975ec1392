"""The traffic sections of a scenario (``traffic:`` in its YAML, picked by ``type``): IDM/MOBIL
cars (:class:`IDMTraffic`, with :class:`Threats` on the batched simulator), scripted vehicles
(:class:`ScriptedTraffic`), or a replayed NGSIM recording (:class:`NGSIMTraffic`). Validated
settings only: :mod:`mmpc.sim` and :mod:`mmpc.highway` build the traffic from them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, Optional, Union

from mmpc.config import require, require_field_types, require_int, require_positive


#: The lowest frequency of a scenario with threatening traffic [Hz]: 1 / ``SimConfig.kp_heading``
#: is the longest frame after which the lane-keeping controller does not overshoot; with longer
#: frames the cars leave the headings and lateral speeds :class:`mmpc.verify.TrafficAssumptions`
#: holds them to, and a falsification tool must keep its cars within them.
THREATS_MIN_FREQUENCY = 5.0


@dataclass(frozen=True)
class Threats:
    """Traffic that threatens the ego as much as the rules allow (the batched simulator only).

    Every car near the ego keeps IDM, MOBIL and the lane-change controller, except that, within
    ``reach`` of the ego along the road (:mod:`mmpc.sim.threats`):

    - a car ahead brakes as hard as IDM may (``SimConfig.acc_max``, to rest) in a random share of
      time windows;
    - a car ahead that MOBIL keeps on its lane at a decision (once a second) moves instead into a
      lane the ego holds or is moving into wherever MOBIL's safety criterion allows it, gain or not:
      two such cars can enter the ego's target lane from both sides; with the ego as the new follower
      the criterion refuses, so the latest legal moment is just before the ego counts on the lane;
    - a car behind in a lane beside the ego's speeds up as fast as IDM may, to pass and cut in.

    Attributes:
        reach: cars within this distance of the ego along the road threaten it [m].
        brake_window: braking comes in windows of this length [s].
        brake_share: share of a car's windows in which it brakes [-].
        cut_in: probability that a car free to cut in at a MOBIL decision does [-].
        overtake: whether cars behind speed up beside the ego.
    """

    reach: float = 60.0
    brake_window: float = 2.0
    brake_share: float = 0.3
    cut_in: float = 1.0
    overtake: bool = True

    def __post_init__(self) -> None:
        require_field_types(self)
        require_positive("traffic threats", reach=self.reach, brake_window=self.brake_window)
        for name in ("brake_share", "cut_in"):
            value = getattr(self, name)
            require(0.0 <= value <= 1.0, f"traffic threats: `{name}` must lie in [0, 1]; got {value!r}")


@dataclass(frozen=True)
class IDMTraffic:
    """highway-env's IDM/MOBIL traffic, optionally slowed down and kept around the ego.

    Attributes:
        vehicles_count: other vehicles on the road.
        vehicles_density: highway-env's density factor (spacing at creation is 1/density).
        target_speeds: (low, high) range the vehicles' desired and initial speeds are drawn
            from [m/s]; ``None`` keeps highway-env's defaults (21-24 m/s).
        window: (behind, ahead) [m]: a vehicle farther behind the ego than ``behind`` is moved
            ahead near ``ahead`` and one farther ahead than ``ahead`` is moved behind, into a
            free gap of a random lane, so that traffic stays around the ego; ``None`` disables it.
        initial_clearance: at the start, vehicles within this distance ahead of the ego in its
            lane (or half of it behind) are moved away [m].
        lane_changes: whether the vehicles change lanes (MOBIL); without, each keeps its lane
            (IDM only).
        threats: the cars near the ego threaten it within the rules (:class:`Threats`; the
            batched simulator only); ``None``: naturalistic traffic.
        ego_as_follower: MOBIL reads the ego as an IDM follower at its present speed, so a car
            may cut in directly ahead of it where that follower would brake at most
            ``lane_change_max_braking_imposed`` (highway-env: the ego carries its speed as
            ``target_speed``). ``False``: highway-env's own reading of a continuous-action ego, which
            has no target speed: MOBIL predicts it braking enormously and no car cuts in ahead of it.
    """

    kind: ClassVar[str] = "idm"
    vehicles_count: int = 18
    vehicles_density: float = 1.5
    target_speeds: Optional[tuple[float, float]] = (7.0, 12.0)
    window: Optional[tuple[float, float]] = (60.0, 200.0)
    initial_clearance: float = 25.0
    lane_changes: bool = True
    threats: Optional[Threats] = None
    ego_as_follower: bool = False

    def __post_init__(self) -> None:
        require_field_types(self)
        where = "traffic idm"
        require_int(where, low=0, vehicles_count=self.vehicles_count)
        require_positive(where, vehicles_density=self.vehicles_density, initial_clearance=self.initial_clearance)
        if self.target_speeds is not None:
            require(0 < self.target_speeds[0] <= self.target_speeds[1],
                     f"{where}: `target_speeds` must be [low, high] with 0 < low <= high m/s; got {self.target_speeds!r}")
        _check_window(where, self.window)


def _check_window(where: str, window: Optional[tuple[float, float]]) -> None:
    if window is not None:
        require_positive(where, window_behind=window[0], window_ahead=window[1])


@dataclass(frozen=True)
class ScriptedVehicle:
    """One vehicle of a hand-built scene, placed relative to the ego at the start.

    Attributes:
        lane: lane index (0 = leftmost).
        x: longitudinal offset from the ego [m] (negative: behind).
        speed: initial and desired speed [m/s].
        lane_change: whether MOBIL may change its lane.
        constant_speed: drive straight at ``speed`` without reacting to anything (a plain
            kinematic vehicle instead of IDM/MOBIL).
        cut_in_lane: with ``cut_in_at``, a scripted manoeuvre instead of IDM: the vehicle keeps
            ``speed``, steers into this lane at ``cut_in_at`` and brakes from ``brake_at``.
        cut_in_at: when the lane change starts [s].
        brake_at: when the scripted vehicle starts braking to a stop [s]; ``None``: never.
        brake_deceleration: its braking [m/s^2].
    """

    lane: int
    x: float
    speed: float
    lane_change: bool = False
    constant_speed: bool = False
    cut_in_lane: Optional[int] = None
    cut_in_at: float = 0.0
    brake_at: Optional[float] = None
    brake_deceleration: float = 6.0

    def __post_init__(self) -> None:
        require_field_types(self)
        require_int("scripted vehicle", low=0, lane=self.lane)
        require(math.isfinite(self.x), f"scripted vehicle: `x` must be finite; got {self.x!r}")
        require(self.speed >= 0, f"scripted vehicle: `speed` must be >= 0; got {self.speed!r}")
        require(self.cut_in_lane is None or self.cut_in_lane >= 0,
                f"scripted vehicle: `cut_in_lane` must be null or an int >= 0; got {self.cut_in_lane!r}")
        require(self.cut_in_at >= 0 and (self.brake_at is None or self.brake_at >= 0),
                f"scripted vehicle: `cut_in_at` and `brake_at` must be >= 0 s; got {self.cut_in_at!r}, {self.brake_at!r}")
        require_positive("scripted vehicle", brake_deceleration=self.brake_deceleration)
        require(not (self.scripted and (self.constant_speed or self.lane_change)),
                "scripted vehicle: a cut-in or braking manoeuvre excludes `constant_speed` and `lane_change`")

    @property
    def scripted(self) -> bool:
        """Whether the vehicle follows a scripted manoeuvre (cut-in and/or braking)."""
        return self.cut_in_lane is not None or self.brake_at is not None


@dataclass(frozen=True)
class ScriptedTraffic:
    """A hand-built scene: vehicles at given places that keep their speed and lane (IDM unless
    ``constant_speed``).

    Attributes:
        vehicles: the vehicles (YAML: a list of mappings with the :class:`ScriptedVehicle` fields).
        window: (behind, ahead) [m]: a vehicle farther behind the ego than ``behind`` is moved
            ahead near ``ahead`` and one farther ahead than ``ahead`` is moved behind, each into
            a free gap of its own lane (the scene repeats around the ego); ``None``: the
            vehicles stay where they drive.
    """

    kind: ClassVar[str] = "scripted"
    vehicles: tuple[ScriptedVehicle, ...] = ()
    window: Optional[tuple[float, float]] = None

    def __post_init__(self) -> None:
        require_field_types(self)
        _check_window("traffic scripted", self.window)


@dataclass(frozen=True)
class NGSIMTraffic:
    """Recorded vehicles from an NGSIM trajectory CSV replayed around the ego (not reactive).

    Attributes:
        path: the CSV (US-101 / I-80 format, feet); relative paths are taken from the working
            directory.
        location: keep only rows whose ``Location`` column equals this (the combined data.gov
            file holds several sites); ``None`` keeps all.
        start_time: replay start, seconds after the recording's first frame [s].
        ego_position: where the ego starts along the section (``Local_Y``) [m].
        lane_width_ft: NGSIM lane width; lateral positions are scaled so that NGSIM lane k
            (1 = leftmost) lies on highway-env lane k - 1 [ft].
        initial_clearance: recorded vehicles within this distance of the ego's start in its
            lane are left out [m].
    """

    kind: ClassVar[str] = "ngsim"
    path: str = ""
    location: Optional[str] = None
    start_time: float = 0.0
    ego_position: float = 100.0
    lane_width_ft: float = 12.0
    initial_clearance: float = 15.0

    def __post_init__(self) -> None:
        require_field_types(self)
        require(self.path != "", "traffic ngsim: `path` must name the NGSIM CSV file")
        require(self.start_time >= 0, f"traffic ngsim: `start_time` must be >= 0 s; got {self.start_time!r}")
        require_positive("traffic ngsim", lane_width_ft=self.lane_width_ft, initial_clearance=self.initial_clearance)
        require(math.isfinite(self.ego_position), f"traffic ngsim: `ego_position` must be finite; got {self.ego_position!r}")


Traffic = Union[IDMTraffic, ScriptedTraffic, NGSIMTraffic]
