"""highway-env adapter: build the environment of a scenario, read its true state in the road
frame, turn an MPC command into highway-env's continuous action.

This module and :mod:`mmpc.highway.traffic` are the only ones in :mod:`mmpc` that import highway-env.

Frames. highway-env's straight road has lane k's centre at ``y = 4 k`` along +x; the road frame
used by the optimizer is lane 0's frame (x along the lane from its start, y to the right-hand
lanes), which coincides with the world frame for highway-env's straight road but is computed
from the lane, not assumed.

Vehicle model. highway-env's kinematic bicycle moves along ``heading + beta`` with
``beta = atan(tan(delta) / 2)`` and turns at ``v sin(beta) / (L / 2)`` (L its length: 5 m
unless ``ScenarioConfig.vehicle_size`` says otherwise): the optimizer's heading psi (the
direction of the velocity) is ``heading + beta`` and its heading rate that turn rate; the
command's steering ``atan(L psidot / v)`` inverts it to first order.
"""

from __future__ import annotations

import math
from typing import Mapping, NamedTuple, Optional

import gymnasium as gym
import highway_env  # noqa: F401  (registers the highway-v0 family)
import numpy as np
import torch
from highway_env.envs.common.abstract import AbstractEnv
from highway_env.road.lane import StraightLane
from highway_env.vehicle.kinematics import Vehicle

from mmpc.drivers import Decision, Driver, Observation
from mmpc.scenario import ScenarioConfig
from mmpc.traffic_config import IDMTraffic
from mmpc.highway.kinematics import DeferredKinematics
from mmpc.highway.traffic import TrafficController, make_traffic, resize

#: Acceleration [m/s^2] and steering [rad] ranges that highway-env's [-1, 1] action maps onto.
ACCELERATION_RANGE = (-5.0, 5.0)
STEERING_RANGE = (-math.pi / 4, math.pi / 4)
#: Rendered frame size [px] (multiples of 16 for video codecs) and scale [px/m].
SCREEN = (960, 192)
SCALING = 4.0


def env_config(scenario: ScenarioConfig) -> dict:
    """highway-env configuration of a scenario (continuous control at the MPC rate)."""
    traffic = scenario.traffic
    idm = isinstance(traffic, IDMTraffic)  # the other sources place their own vehicles
    return {
        "action": {
            "type": "ContinuousAction",
            "acceleration_range": ACCELERATION_RANGE,
            "steering_range": STEERING_RANGE,
        },
        "observation": {"type": "Kinematics"},
        "simulation_frequency": scenario.frequency,
        "policy_frequency": scenario.frequency,
        "lanes_count": scenario.lanes,
        "vehicles_count": traffic.vehicles_count if idm else 0,
        "vehicles_density": traffic.vehicles_density if idm else 1.0,
        "initial_lane_id": scenario.ego.lane,
        "duration": scenario.duration,
        "offroad_terminal": False,
        "screen_width": SCREEN[0],
        "screen_height": SCREEN[1],
        "scaling": SCALING,
        "centering_position": [0.25, 0.5],
    }


class RoadFrame(NamedTuple):
    """Lane 0's frame: ``origin`` (2,) [m], unit ``along`` and ``across`` (2,), ``heading`` [rad]."""

    origin: np.ndarray
    along: np.ndarray
    across: np.ndarray
    heading: float

    @classmethod
    def of(cls, env: AbstractEnv) -> "RoadFrame":
        lane = env.road.network.get_lane((*env.vehicle.lane_index[:2], 0))
        if not isinstance(lane, StraightLane):
            raise TypeError(f"the road frame needs a straight road; lane 0 is a {type(lane).__name__}")
        return cls(np.asarray(lane.start, dtype=np.float64), lane.direction, lane.direction_lateral, float(lane.heading))

    def to_road(self, points: np.ndarray) -> np.ndarray:
        """World positions (..., 2) -> road frame (..., 2) [m]."""
        relative = points - self.origin
        return np.stack([relative @ self.along, relative @ self.across], axis=-1)

    def vector_to_road(self, vectors: np.ndarray) -> np.ndarray:
        """World vectors (..., 2) (e.g. velocities) -> road frame (..., 2)."""
        return np.stack([vectors @ self.along, vectors @ self.across], axis=-1)

    def to_world(self, points: np.ndarray) -> np.ndarray:
        """Road-frame positions (..., 2) -> world (..., 2) [m]."""
        return self.origin + points[..., :1] * self.along + points[..., 1:2] * self.across


class RoadState(NamedTuple):
    """True state of one environment in the road frame, as the MPC takes it.

    Shapes:
        ego: (1, 6) as :data:`mmpc.EGO_FIELDS`: x, y [m], psi (direction of motion) [rad],
            v [m/s], a (the acceleration being applied) [m/s^2], psidot (the turn rate of the
            steering being applied) [rad/s].
        vehicles: (1, V, 4) every other vehicle's x, y [m], vx, vy [m/s].
    """

    ego: torch.Tensor
    vehicles: torch.Tensor


def vehicle_motion(vehicle: Vehicle) -> tuple[float, float]:
    """Slip angle beta [rad] and turn rate [rad/s] of a kinematic-bicycle vehicle's current steering."""
    beta = math.atan(0.5 * math.tan(float(vehicle.action["steering"])))
    return beta, vehicle.speed * math.sin(beta) / (vehicle.LENGTH / 2)


def road_state(env: AbstractEnv, frame: RoadFrame, *, dtype: torch.dtype = torch.float32,
               displaced: Mapping[int, np.ndarray] = {}) -> RoadState:
    """Read the ego and every other vehicle from ``env`` (its ``unwrapped`` highway-env).

    ``displaced``: world displacements (2,) [m] to take back from the positions read, by the
    ``id`` of the vehicle they moved (:attr:`HighwayEpisode.pushes`: the scene at a collision's impact).
    """
    def position(vehicle: Vehicle) -> np.ndarray:
        return np.asarray(vehicle.position) - displaced.get(id(vehicle), 0.0)

    ego = env.vehicle
    beta, turn_rate = vehicle_motion(ego)
    x, y = frame.to_road(position(ego))
    ego_row = [x, y, ego.heading + beta - frame.heading, ego.speed, float(ego.action["acceleration"]), turn_rate]
    others = [v for v in env.road.vehicles if v is not ego]
    if others:
        positions = frame.to_road(np.array([position(v) for v in others]))
        velocities = frame.vector_to_road(np.array([v.velocity for v in others]))
        rows = np.concatenate([positions, velocities], axis=1)
    else:
        rows = np.zeros((0, 4))
    return RoadState(
        torch.tensor([ego_row], dtype=dtype),
        torch.as_tensor(rows, dtype=dtype).reshape(1, -1, 4),
    )


def command_to_action(acceleration: float, steering: float) -> np.ndarray:
    """Acceleration [m/s^2] and steering [rad] -> highway-env's ContinuousAction in [-1, 1]^2 (clipped)."""
    a = 2.0 * (acceleration - ACCELERATION_RANGE[0]) / (ACCELERATION_RANGE[1] - ACCELERATION_RANGE[0]) - 1.0
    s = 2.0 * (steering - STEERING_RANGE[0]) / (STEERING_RANGE[1] - STEERING_RANGE[0]) - 1.0
    return np.clip(np.array([a, s], dtype=np.float32), -1.0, 1.0)


class HighwayEpisode:
    """One highway-env episode of a scenario, stepped one control period at a time by a driver.

    Args:
        scenario: the scenario.
        seed: seeds highway-env (ego lane, traffic) and the traffic controller.
        render: create the environment with ``render_mode="rgb_array"``.

    Example:
        >>> from mmpc.drivers import make_driver
        >>> scenario = ScenarioConfig(duration=1.0)
        >>> episode, driver = HighwayEpisode(scenario, seed=0), make_driver("mpc", scenario)
        >>> observation, decision = episode.step(driver)
        >>> observation.ego.shape, decision.acceleration.shape
        (torch.Size([1, 6]), torch.Size([1]))
    """

    def __init__(self, scenario: ScenarioConfig, seed: int, *, render: bool = False) -> None:
        self.scenario = scenario
        self.seed = seed
        self.env = gym.make(scenario.env_id, config=env_config(scenario), render_mode="rgb_array" if render else None)
        self.env.reset(seed=seed)
        self.unwrapped: AbstractEnv = self.env.unwrapped
        self.unwrapped.observation_type = DeferredKinematics(self.unwrapped, self.unwrapped.observation_type.vehicles_count)
        self.unwrapped.vehicle.speed = scenario.ego.speed
        self.traffic: TrafficController = make_traffic(scenario, self.unwrapped)
        self.traffic.reset()
        if scenario.vehicle_size is not None:
            for vehicle in self.unwrapped.road.vehicles:
                resize(vehicle, *scenario.vehicle_size)
        self.frame = RoadFrame.of(self.unwrapped)
        self.time = 0.0
        self.reward = 0.0
        #: The collision pushes the last frame applied: world displacement (2,) [m] by the ``id`` of the vehicle moved.
        self.pushes: dict[int, np.ndarray] = {}

    @property
    def ego(self) -> Vehicle:
        return self.unwrapped.vehicle

    @property
    def done(self) -> bool:
        """The ego crashed or the scenario's duration is over."""
        return bool(self.ego.crashed) or self.time >= self.scenario.duration - 1e-9

    def kinematics(self, vehicles_count: Optional[int] = None) -> np.ndarray:
        """highway-env's ``Kinematics`` observation of the current state, (rows, features) float32:
        ``vehicles_count`` rows (default: the count last asked for, first highway-env's 5); computed only when asked for
        (:class:`mmpc.highway.kinematics.DeferredKinematics`: highway-env's own observation at every frame is a placeholder)."""
        observer = self.unwrapped.observation_type
        if vehicles_count is not None and observer.vehicles_count != vehicles_count:
            observer = self.unwrapped.observation_type = DeferredKinematics(self.unwrapped, vehicles_count)
        return observer.compute()

    def observe(self, dtype: torch.dtype = torch.float32, *, kinematics: bool = True) -> Observation:
        """The current state for a driver (E = 1), with highway-env's ``Kinematics`` rows unless ``kinematics`` is off."""
        state = road_state(self.unwrapped, self.frame, dtype=dtype)
        return Observation(state.ego, state.vehicles, None, self.kinematics()[None] if kinematics else None)

    def observe_impact(self) -> Observation:
        """The current state with the last frame's collision pushes taken back (E = 1, no
        Kinematics rows): after the frame in which the ego crashed, the cars where they met.

        highway-env separates two cars predicted to collide by half the minimum translation each
        (``RoadObject.handle_collisions``), applied in the next frame, the one that marks them crashed.
        """
        state = road_state(self.unwrapped, self.frame, displaced=self.pushes)
        return Observation(state.ego, state.vehicles, None, None)

    def apply(self, acceleration: float, steering: float) -> None:
        """Send one command for one frame, then let the traffic controller move vehicles.

        Args:
            acceleration: [m/s^2], clipped to :data:`ACCELERATION_RANGE`; braking that would take
                the ego below rest within the frame stops it instead (the drivers plan forwards only).
            steering: [rad], clipped to :data:`STEERING_RANGE`.
        """
        speed = float(self.ego.speed)
        acceleration = max(acceleration, -max(speed, 0.0) * self.scenario.frequency)
        pending = {id(v): (v, v.impact) for v in self.unwrapped.road.vehicles if v.impact is not None}
        if getattr(self.scenario.traffic, "ego_as_follower", False):
            self.ego.target_speed = speed  # MOBIL reads the ego as an IDM follower holding its speed
        _, reward, _, _, _ = self.env.step(command_to_action(acceleration, steering))
        # A push was applied where the vehicle no longer holds it (a vehicle that does not step, e.g. a replay, keeps it).
        self.pushes = {key: np.array(impact) for key, (v, impact) in pending.items() if v.impact is not impact}
        if speed >= 0.0 and self.ego.speed < 0.0:  # rounding of the stopping command
            self.ego.speed = 0.0
        self.reward = float(reward)
        self.traffic.after_step()
        self.time += 1.0 / self.scenario.frequency

    def step(self, driver: Driver) -> tuple[Observation, Decision]:
        """Observe, decide, apply; returns the observation decided from and the decision."""
        observation = self.observe()
        decision = driver.decide(observation)
        self.apply(float(decision.acceleration[0]), float(decision.steering[0]))
        return observation, decision

    def close(self) -> None:
        self.env.close()
