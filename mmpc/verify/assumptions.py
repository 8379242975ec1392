"""What the other cars may do: the assumptions every occupancy set rests on, written once.

Each names the rule of the worlds it comes from (highway-env 1.12's ``IDMVehicle`` and
``ControlledVehicle``, and :mod:`mmpc.sim`, which implements them batched), and
``tests/test_verify.py`` checks that the batched simulator's cars keep them. A car that breaks
one (a crashed car brakes at ``-v`` per second; a collision push moves it sideways; IDM can
reverse a car stopped too close to its leader) is reported by :class:`mmpc.verify.AssumptionMonitor`:
no verification holds for it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from mmpc.config import require, require_field_types, require_non_negative, require_positive
from mmpc.sim.traffic import sim_config

if TYPE_CHECKING:
    from mmpc.scenario import ScenarioConfig


#: The lane-change rules :attr:`TrafficAssumptions.cut_in` names.
CUT_IN_RULES = ("follower", "highway-env", "any")


@dataclass(frozen=True)
class TrafficAssumptions:
    """Bounds on every other car's motion and the lane-change rule the traffic obeys.

    Attributes:
        max_deceleration: braking at most this [m/s^2]: IDM's command is clipped to
            ``+-ACC_MAX`` = 6 (``SimConfig.acc_max``); speed never below 0 (no reversing).
        max_acceleration: speeding up at most this [m/s^2]: IDM's free-road term
            ``COMFORT_ACC_MAX (1 - (v / v0)^delta)`` <= 3 (``SimConfig.comfort_acc_max``).
        speed_limit: IDM target speeds are at most this [m/s] (``SimConfig.speed_limit``), so a
            car speeds up to at most ``max(v, speed_limit)``.
        lateral_speed: a car's centre moves across the road at most this fast [m/s]: the
            lane-change controller asks for ``kp_lateral * offset`` (6.7 m/s at one lane width);
            the slip angle of a sudden steer adds to it at the start of a change.
        max_heading: a car's body heading stays within this of the road's [rad] (the lane-change
            controller's reference is clipped to 45 deg; the bound covers its overshoot). The
            body may turn that far within a frame, so its footprint's edges swing out at once;
            along the road it covers at least its path less ``tan(max_heading / 2)`` times its
            lateral travel.
        lateral_travel: a car travels at most this far across the road over a check [m] (two
            lane changes: MOBIL decides at most once a second, a change takes about three).
        lane_overreach: a footprint edge lies at most this far beyond the centre of the
            outermost lane the car is on or bound for [m] (half a body width, the turned body's
            corner and the controller's overshoot).
        length, width: the other cars' bodies [m] (highway-env's 5 x 2).
        lane_margin: a car counts on a lane within ``lane_width / 2 + lane_margin`` of its
            centre [m] (highway-env's ``on_lane(margin=1)``, what MOBIL's neighbour search reads).
        change_speed, change_offset: a car moving across the road faster than ``change_speed``
            [m/s], or ``change_offset`` [m] or more off its nearest lane centre, is changing lane
            towards that side: it decided before now, so the lane-change rule no longer holds it.
        follower_reaction: a car behind the ego brakes, as hard as it needs up to ``max_deceleration``,
            at most this long after the ego does [s] (IDM reacts at the next frame; its braking
            grows with the square of the closing gap). Such a car's set ends where that braking
            takes it (:func:`mmpc.verify.occupancy.follower_reach`).
        cut_in: where a car ahead of the ego, with nobody between, may decide to enter a lane the
            ego holds (MOBIL's safety criterion, :mod:`mmpc.verify.cut_ins`). ``"follower"``: MOBIL
            reads the ego as an IDM follower holding its present speed, so a car enters only where
            the ego behind it would brake at most ``max_braking_imposed`` (far enough ahead for its
            speeds); it covers both worlds' readings. ``"highway-env"``: no car decides to enter
            directly ahead of the moving ego, as highway-env reads a continuous-action ego (no target
            speed, so MOBIL predicts it braking beyond any bound): an artefact, for claims about that
            simulator's traffic only. ``"any"``: no rule, any car may enter any lane.
        distance_wanted, time_wanted: IDM's jam distance between centres [m] and time headway [s]
            (``SimConfig``), read by the follower rule; IDM's acceleration a is ``max_acceleration``.
        comfort_deceleration: IDM's comfortable deceleration b [m/s^2] (``-SimConfig.comfort_acc_min``).
        max_braking_imposed: MOBIL's bound on the new follower's braking [m/s^2]
            (``SimConfig.lane_change_max_braking_imposed``).
        decision_lag: a lane-change decision shows (``change_speed``, ``change_offset``) at most this
            long after MOBIL took it [s]; the follower rule counts decisions that recent as possible.
        ego_acceleration: the ego's acceleration commands lie within +- this [m/s^2]
            (``SimConfig.acceleration_range``): it bounds where the ego was when a car decided.
    """

    max_deceleration: float = 6.0
    max_acceleration: float = 3.0
    speed_limit: float = 30.0
    lateral_speed: float = 8.0
    max_heading: float = 0.9
    lateral_travel: float = 8.0
    lane_overreach: float = 1.6
    length: float = 5.0
    width: float = 2.0
    lane_margin: float = 1.0
    change_speed: float = 0.5
    change_offset: float = 0.5
    follower_reaction: float = 0.3
    cut_in: str = "follower"
    distance_wanted: float = 10.0
    time_wanted: float = 1.5
    comfort_deceleration: float = 5.0
    max_braking_imposed: float = 2.0
    decision_lag: float = 0.5
    ego_acceleration: float = 5.0

    def __post_init__(self) -> None:
        require_field_types(self)
        require_positive("TrafficAssumptions", max_deceleration=self.max_deceleration, lateral_speed=self.lateral_speed,
                         length=self.length, width=self.width, max_heading=self.max_heading,
                         lateral_travel=self.lateral_travel, change_speed=self.change_speed,
                         change_offset=self.change_offset, comfort_deceleration=self.comfort_deceleration,
                         ego_acceleration=self.ego_acceleration)
        require_non_negative("TrafficAssumptions", max_acceleration=self.max_acceleration, speed_limit=self.speed_limit,
                             lane_overreach=self.lane_overreach, lane_margin=self.lane_margin,
                             follower_reaction=self.follower_reaction, distance_wanted=self.distance_wanted,
                             time_wanted=self.time_wanted, max_braking_imposed=self.max_braking_imposed,
                             decision_lag=self.decision_lag)
        require(self.cut_in in CUT_IN_RULES, f"TrafficAssumptions: `cut_in` must be one of {list(CUT_IN_RULES)}; "
                                             f"got {self.cut_in!r}")

    @classmethod
    def for_scenario(cls, scenario: "ScenarioConfig", cut_in: str = "follower") -> "TrafficAssumptions":
        """The assumptions for a scenario's cars: their size (a footprint wider than 2 m reaches
        beyond a lane centre by half the extra width more), its worlds' IDM and MOBIL constants and
        the ego's command range, under the lane-change rule ``cut_in``."""
        sim = sim_config(scenario)
        length, width = scenario.vehicle
        default = cls()
        return cls(length=length, width=width, lane_overreach=default.lane_overreach + 0.5 * (width - default.width),
                   cut_in=cut_in, distance_wanted=sim.distance_wanted, time_wanted=sim.time_wanted,
                   comfort_deceleration=-sim.comfort_acc_min, max_acceleration=sim.comfort_acc_max,
                   max_braking_imposed=sim.lane_change_max_braking_imposed,
                   ego_acceleration=max(abs(bound) for bound in sim.acceleration_range))

    @property
    def half_length(self) -> float:
        """The largest half extent of a car's body along the road, whatever its heading [m]."""
        return 0.5 * (self.length ** 2 + self.width ** 2) ** 0.5
