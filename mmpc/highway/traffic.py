"""The other vehicles of a highway-env episode: IDM/MOBIL traffic kept around the ego, a
hand-built scene, or an NGSIM recording replayed.

A controller is created after ``env.reset`` (:func:`make_traffic`), arranges the vehicles in
:meth:`reset` and may move them after every frame (:meth:`after_step`). Randomness comes from
the environment's seeded ``np_random``, so a seed fixes the whole episode.
"""

from __future__ import annotations

from typing import Optional, Protocol

import numpy as np
from highway_env.envs.common.abstract import AbstractEnv
from highway_env.road.lane import AbstractLane
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import ControlledVehicle
from highway_env.vehicle.kinematics import Vehicle

from mmpc.highway.ngsim import Recording, Track, read_ngsim
from mmpc.scenario import ScenarioConfig
from mmpc.traffic_config import IDMTraffic, NGSIMTraffic, ScriptedTraffic

#: Smallest distance along the road to any vehicle in a lane where a vehicle is (re)placed [m].
PLACEMENT_GAP = 30.0
#: Placement attempts before giving up for this frame.
_PLACEMENT_TRIES = 30


class TrafficController(Protocol):
    def reset(self) -> None:
        """Arrange the other vehicles at the start of the episode (after ``env.reset``)."""
        ...

    def after_step(self) -> None:
        """Update the other vehicles after a simulation frame."""
        ...


def make_traffic(scenario: ScenarioConfig, env: AbstractEnv) -> TrafficController:
    """The controller of ``scenario.traffic`` for the (unwrapped) environment ``env``."""
    traffic = scenario.traffic
    if isinstance(traffic, IDMTraffic):
        return IDMTrafficController(traffic, env)
    if isinstance(traffic, ScriptedTraffic):
        return ScriptedTrafficController(traffic, env)
    if isinstance(traffic, NGSIMTraffic):
        return NGSIMReplay(traffic, env, scenario.duration)
    raise TypeError(f"unknown traffic config {type(traffic).__name__}")


class _Lanes:
    """Lane geometry of highway-env's straight road: lane k's (s, d) coordinates and placement."""

    def __init__(self, env: AbstractEnv) -> None:
        self.env = env
        self.road_id = env.vehicle.lane_index[:2]
        self.count = len(env.road.network.graph[self.road_id[0]][self.road_id[1]])

    def lane(self, index: int) -> AbstractLane:
        return self.env.road.network.get_lane((*self.road_id, index))

    def along(self, vehicle: Vehicle) -> float:
        """Distance along the road [m]."""
        return float(self.lane(0).local_coordinates(vehicle.position)[0])

    def lane_of(self, vehicle: Vehicle) -> int:
        return int(vehicle.lane_index[2])

    def is_free(self, index: int, s: float, gap: float, ignore: Optional[Vehicle] = None) -> bool:
        """No vehicle in or entering lane ``index`` within ``gap`` of position ``s`` along the road."""
        lane = self.lane(index)
        for other in self.env.road.vehicles:
            if other is ignore:
                continue
            s_other, d_other = lane.local_coordinates(other.position)
            if abs(d_other) < lane.width_at(s_other) and abs(s_other - s) < gap:
                return False
        return True

    def place(self, vehicle: Vehicle, index: int, s: float) -> None:
        """Put ``vehicle`` on lane ``index``'s centre at ``s``, heading along the lane."""
        lane = self.lane(index)
        vehicle.position = np.asarray(lane.position(s, 0.0), dtype=np.float64)
        vehicle.heading = lane.heading_at(s)
        vehicle.lane_index = (*self.road_id, index)
        vehicle.lane = lane
        if hasattr(vehicle, "target_lane_index"):
            vehicle.target_lane_index = vehicle.lane_index

    def relocate(self, vehicle: Vehicle, s_low: float, s_high: float, *, keep_lane: bool = False) -> bool:
        """Move ``vehicle`` to a free spot in [s_low, s_high] of a random lane (of its own lane
        with ``keep_lane``); False if none was found."""
        rng = self.env.np_random
        for _ in range(_PLACEMENT_TRIES):
            index = self.lane_of(vehicle) if keep_lane else int(rng.integers(self.count))
            s = float(rng.uniform(s_low, s_high))
            if self.is_free(index, s, PLACEMENT_GAP, ignore=vehicle):
                self.place(vehicle, index, s)
                return True
        return False


def resize(vehicle: Vehicle, length: float, width: float) -> None:
    """Give one highway-env vehicle another footprint [m] (collisions, drawing, and the bicycle
    model's wheelbase all read it)."""
    vehicle.LENGTH, vehicle.WIDTH = float(length), float(width)
    vehicle.diagonal = float(np.hypot(length, width))


def _others(env: AbstractEnv) -> list[Vehicle]:
    return [v for v in env.road.vehicles if v is not env.vehicle]


class IDMTrafficController:
    """highway-env's IDM/MOBIL vehicles with the scenario's speeds, kept inside a window around
    the ego (see :class:`mmpc.traffic_config.IDMTraffic`)."""

    def __init__(self, config: IDMTraffic, env: AbstractEnv) -> None:
        self.config = config
        self.env = env
        self.lanes = _Lanes(env)

    def reset(self) -> None:
        rng = self.env.np_random
        ego = self.env.vehicle
        for vehicle in _others(self.env):
            vehicle.enable_lane_change = self.config.lane_changes
            if self.config.target_speeds is not None:
                vehicle.speed = vehicle.target_speed = float(rng.uniform(*self.config.target_speeds))
        s_ego, lane_ego = self.lanes.along(ego), self.lanes.lane_of(ego)
        clearance = self.config.initial_clearance
        far = max([self.lanes.along(v) for v in _others(self.env)], default=s_ego) + PLACEMENT_GAP
        for vehicle in _others(self.env):
            ds = self.lanes.along(vehicle) - s_ego
            if self.lanes.lane_of(vehicle) == lane_ego and -0.5 * clearance < ds < clearance:
                placed = self.lanes.relocate(vehicle, s_ego + clearance, far)
                if not placed:  # nowhere free nearby: behind everything else, ahead
                    self.lanes.relocate(vehicle, far, far + 10 * PLACEMENT_GAP)

    def after_step(self) -> None:
        if self.config.window is not None:
            _keep_in_window(self.env, self.lanes, self.config.window, keep_lane=False)


def _keep_in_window(env: AbstractEnv, lanes: _Lanes, window: tuple[float, float], *, keep_lane: bool) -> None:
    """Move every other vehicle farther than ``window = (behind, ahead)`` [m] from the ego
    along the road to the window's other end (its last quarter), into a free gap of a random
    lane or, with ``keep_lane``, of its own."""
    behind, ahead = window
    s_ego = lanes.along(env.vehicle)
    for vehicle in _others(env):
        ds = lanes.along(vehicle) - s_ego
        if ds < -behind:
            lanes.relocate(vehicle, s_ego + 0.75 * ahead, s_ego + ahead, keep_lane=keep_lane)
        elif ds > ahead:
            lanes.relocate(vehicle, s_ego - behind, s_ego - 0.75 * behind, keep_lane=keep_lane)


class ScriptedTrafficController:
    """A hand-built scene: the scenario's vehicles, placed relative to the ego, keep their
    speed (IDM, or constant) and, unless allowed, their lane; with a window they are recycled
    in their lane around the ego."""

    def __init__(self, config: ScriptedTraffic, env: AbstractEnv) -> None:
        self.config = config
        self.env = env
        self.lanes = _Lanes(env)

    def reset(self) -> None:
        road = self.env.road
        road.vehicles = [self.env.vehicle]
        s_ego = self.lanes.along(self.env.vehicle)
        for spec in self.config.vehicles:
            lane = self.lanes.lane(spec.lane)
            s = s_ego + spec.x
            if spec.scripted:
                vehicle = ManoeuvreVehicle(road, lane.position(s, 0.0), lane.heading_at(s), spec.speed,
                                           target_lane_index=(*self.lanes.road_id, spec.lane))
                vehicle.script(
                    None if spec.cut_in_lane is None else (*self.lanes.road_id, spec.cut_in_lane),
                    spec.cut_in_at, spec.brake_at, spec.brake_deceleration,
                )
            elif spec.constant_speed:
                vehicle = Vehicle(road, lane.position(s, 0.0), lane.heading_at(s), spec.speed)
            else:
                vehicle = IDMVehicle(
                    road, lane.position(s, 0.0), lane.heading_at(s), spec.speed,
                    target_lane_index=(*self.lanes.road_id, spec.lane), target_speed=spec.speed,
                    enable_lane_change=spec.lane_change,
                )
            road.vehicles.append(vehicle)

    def after_step(self) -> None:
        if self.config.window is not None:
            _keep_in_window(self.env, self.lanes, self.config.window, keep_lane=True)


class ManoeuvreVehicle(ControlledVehicle):
    """A scripted vehicle: it holds its speed, changes lane at a given time (highway-env's
    lateral controller) and brakes to a stop at a given time (a cut-in that brakes hard)."""

    def script(self, lane_index: Optional[tuple], change_at: float, brake_at: Optional[float], deceleration: float) -> None:
        self.cut_in_lane_index = lane_index
        self.change_at = change_at
        self.brake_at = brake_at
        self.deceleration = deceleration
        self.elapsed = 0.0

    def act(self, action=None) -> None:
        if self.cut_in_lane_index is not None and self.elapsed >= self.change_at:
            self.target_lane_index = self.cut_in_lane_index
        braking = self.brake_at is not None and self.elapsed >= self.brake_at and self.speed > 0
        steering = np.clip(self.steering_control(self.target_lane_index), -self.MAX_STEERING_ANGLE, self.MAX_STEERING_ANGLE)
        Vehicle.act(self, {"steering": steering, "acceleration": -self.deceleration if braking else 0.0})

    def step(self, dt: float) -> None:
        super().step(dt)
        self.elapsed += dt
        self.speed = max(self.speed, 0.0)


class ReplayVehicle(Vehicle):
    """A vehicle that follows a recorded :class:`mmpc.highway.ngsim.Track` (it does not react).

    Args:
        road: the highway-env road.
        track: the recording, in the road frame.
        reference: the lane whose frame the track's (x, y) are in (highway-env's lane 0).
        shift: added to the track's x to place it on ``road`` [m].
        time: recording time of the vehicle's first state [s].
    """

    def __init__(self, road, track: Track, reference: AbstractLane, shift: float, time: float) -> None:
        self.track = track
        self.reference = reference
        self.shift = shift
        self.clock = time
        position, heading, speed = self._recorded(time)
        super().__init__(road, position, heading, speed)
        resize(self, track.length, track.width)
        # Recorded vehicles may overlap each other after the lateral rescaling; only collisions
        # with the ego (which checks its own) matter.
        self.check_collisions = False

    def _recorded(self, t: float) -> tuple[np.ndarray, float, float]:
        x, y, vx, vy = self.track.state_at(t)
        speed = float(np.hypot(vx, vy))
        heading = float(np.arctan2(vy, vx)) if speed > 0.5 else 0.0
        position = np.asarray(self.reference.position(x + self.shift, y), dtype=np.float64)
        return position, heading + self.reference.heading_at(x + self.shift), speed

    @property
    def finished(self) -> bool:
        return self.clock > self.track.end

    def act(self, action=None) -> None:
        """Replayed: no decision."""

    def step(self, dt: float) -> None:
        self.clock += dt
        self.position, self.heading, self.speed = self._recorded(self.clock)
        self.on_state_update()


class NGSIMReplay:
    """NGSIM vehicles replayed as the traffic around the ego (see :class:`mmpc.traffic_config.NGSIMTraffic`).

    The ego starts at ``ego_position`` along the recorded section, in the scenario's lane;
    recorded vehicles too close to that start are left out; vehicles enter when their
    recording starts and leave when it ends.
    """

    def __init__(self, config: NGSIMTraffic, env: AbstractEnv, duration: float) -> None:
        self.config = config
        self.env = env
        self.lanes = _Lanes(env)
        self.recording: Recording = read_ngsim(
            config.path, location=config.location, lane_width_ft=config.lane_width_ft,
            road_lane_width=self.lanes.lane(0).width_at(0.0),
        )
        if config.start_time + duration > self.recording.duration:
            raise ValueError(
                f"traffic ngsim: start_time {config.start_time} s + duration {duration} s exceeds the "
                f"recording's {self.recording.duration:.1f} s ({config.path})"
            )
        self.time = config.start_time
        self._next = 0  # index of the first track not yet on the road (tracks sorted by start)
        self.shift = 0.0  # road position of the recording's x = 0 [m]

    def reset(self) -> None:
        ego = self.env.vehicle
        self.shift = self.lanes.along(ego) - self.config.ego_position
        self.env.road.vehicles = [ego]
        ego_y = float(self.lanes.lane(0).local_coordinates(ego.position)[1])
        half_lane = 0.5 * self.lanes.lane(0).width_at(0.0)
        self._next = 0
        for track in self.recording.tracks:
            if track.start > self.time:
                break
            self._next += 1
            if track.end < self.time:
                continue
            x, y, _, _ = track.state_at(self.time)
            if abs(x - self.config.ego_position) < self.config.initial_clearance and abs(y - ego_y) < 1.5 * half_lane:
                continue
            self.env.road.vehicles.append(ReplayVehicle(self.env.road, track, self.lanes.lane(0), self.shift, self.time))

    def after_step(self) -> None:
        self.time += 1.0 / self.env.config["simulation_frequency"]
        road = self.env.road
        road.vehicles = [v for v in road.vehicles if not (isinstance(v, ReplayVehicle) and v.finished)]
        tracks = self.recording.tracks
        while self._next < len(tracks) and tracks[self._next].start <= self.time:
            road.vehicles.append(ReplayVehicle(road, tracks[self._next], self.lanes.lane(0), self.shift, self.time))
            self._next += 1
