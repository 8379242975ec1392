"""The simulator's constants: highway-env's defaults, with units, validated."""

from __future__ import annotations

import math
from dataclasses import dataclass

from mmpc.config import require, require_field_types, require_int, require_non_negative, require_positive


@dataclass(frozen=True)
class SimConfig:
    """Road, vehicle-model, IDM and lane-keeping constants (highway-env's values by default).

    Attributes:
        simulation_frequency: simulation frames per second [Hz] (highway-env's own default is
            15; the project's scenarios run at 10).
        policy_frequency: ego commands per second [Hz]; each command is held for
            ``int(simulation_frequency // policy_frequency)`` frames, as highway-env does.
        lanes: number of straight lanes along +x; lane k's centre at ``y = k * lane_width``.
        lane_width: [m].
        lane_margin: a vehicle counts as on a lane, when looking for the vehicle ahead, within
            ``lane_width / 2 + lane_margin`` of its centre [m] (highway-env's ``on_lane(margin=1)``).
        speed_limit: the lanes' speed limit; IDM target speeds are clipped to ``[0, speed_limit]`` [m/s].
        min_speed, max_speed: beyond them the acceleration is limited to pull the speed back,
            ``a <= max_speed - v`` (resp. ``a >= min_speed - v``) [m/s]; the speed itself is not clipped.
        acceleration_range: the ego's acceleration command is clipped to it [m/s^2].
        steering_range: the ego's steering command is clipped to it [rad].
        acc_max: IDM acceleration bound, both signs [m/s^2].
        comfort_acc_max: IDM maximum acceleration a [m/s^2].
        comfort_acc_min: IDM comfortable deceleration -b [m/s^2] (negative).
        distance_wanted: IDM jam distance between centres, a 5 m vehicle length included [m].
        time_wanted: IDM time headway [s].
        kp_lateral: lane keeping, lateral position gain [1/s].
        kp_heading: lane keeping, heading gain [1/s].
        max_steering: IDM vehicles' steering bound [rad].
        politeness: MOBIL's weight of the followers' acceleration changes against the
            vehicle's own (highway-env's ``POLITENESS``, 0 selfish .. 1 altruistic) [-].
        lane_change_min_acc_gain: MOBIL changes lane only for a weighted acceleration gain of
            at least this [m/s^2].
        lane_change_max_braking_imposed: MOBIL refuses a change that makes the new follower
            brake harder than this [m/s^2] (positive).
        lane_change_delay: a vehicle on its target lane evaluates MOBIL once its timer
            exceeds this, then restarts the timer [s].
        ego_as_follower: MOBIL reads the ego (slot 0) as an IDM follower whose target speed is its
            present speed; ``False``: as highway-env reads a continuous-action ego, with none
            (:mod:`mmpc.sim.mobil`).
        fixed_shapes: a frame's shapes do not depend on the traffic and it reads nothing on the host
            (buffers of fixed size, :mod:`mmpc.compaction`; the window in fixed rounds): what one
            compiled graph or a GPU needs. ``False``: exact sizes read on the host, the CPU's fast eager path.
    """

    simulation_frequency: float = 10.0
    policy_frequency: float = 10.0
    lanes: int = 4
    lane_width: float = 4.0
    lane_margin: float = 1.0
    speed_limit: float = 30.0
    min_speed: float = -40.0
    max_speed: float = 40.0
    acceleration_range: tuple[float, float] = (-5.0, 5.0)
    steering_range: tuple[float, float] = (-math.pi / 4, math.pi / 4)
    acc_max: float = 6.0
    comfort_acc_max: float = 3.0
    comfort_acc_min: float = -5.0
    distance_wanted: float = 10.0
    time_wanted: float = 1.5
    kp_lateral: float = 1 / 0.6
    kp_heading: float = 1 / 0.2
    max_steering: float = math.pi / 3
    politeness: float = 0.0
    lane_change_min_acc_gain: float = 0.2
    lane_change_max_braking_imposed: float = 2.0
    lane_change_delay: float = 1.0
    ego_as_follower: bool = False
    fixed_shapes: bool = False

    def __post_init__(self) -> None:
        require_field_types(self)
        require_positive(
            "SimConfig", simulation_frequency=self.simulation_frequency, policy_frequency=self.policy_frequency,
            lane_width=self.lane_width, speed_limit=self.speed_limit, max_speed=self.max_speed, acc_max=self.acc_max,
            comfort_acc_max=self.comfort_acc_max, distance_wanted=self.distance_wanted, time_wanted=self.time_wanted,
            kp_lateral=self.kp_lateral, kp_heading=self.kp_heading, max_steering=self.max_steering,
            lane_change_max_braking_imposed=self.lane_change_max_braking_imposed, lane_change_delay=self.lane_change_delay,
        )
        require_non_negative("SimConfig", politeness=self.politeness, lane_change_min_acc_gain=self.lane_change_min_acc_gain)
        require_int("SimConfig", low=1, lanes=self.lanes)
        require(self.lane_margin >= 0, f"SimConfig: `lane_margin` must be >= 0 m; got {self.lane_margin}")
        require(self.min_speed < self.max_speed,
                f"SimConfig: `min_speed` must be < `max_speed`; got {self.min_speed} and {self.max_speed} m/s")
        require(self.comfort_acc_min < 0, f"SimConfig: `comfort_acc_min` must be < 0 m/s^2; got {self.comfort_acc_min}")
        for name in ("acceleration_range", "steering_range"):
            low, high = getattr(self, name)
            require(low < high, f"SimConfig: `{name}` must be (low, high) with low < high; got {(low, high)}")
        require(self.simulation_frequency >= self.policy_frequency,
                f"SimConfig: `simulation_frequency` ({self.simulation_frequency} Hz) must be >= "
                f"`policy_frequency` ({self.policy_frequency} Hz)")

    @property
    def dt(self) -> float:
        """Simulation time step [s]."""
        return 1.0 / self.simulation_frequency

    @property
    def frames_per_command(self) -> int:
        """Simulation frames each ego command is held for."""
        return int(self.simulation_frequency // self.policy_frequency)
