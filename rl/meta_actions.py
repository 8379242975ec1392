"""highway-env's ``DiscreteMetaAction`` executed as its ``MDPVehicle`` executes it, for E egos at once.

A meta-action moves the ego's targets; a lane and speed controller turns the targets into an
(acceleration, steering) command at every simulation frame. highway-env's laws (``ControlledVehicle``,
``MDPVehicle``, HighwayEnv 1.x):

- targets: a lane and an index into the target speeds (``env.meta_speeds``; highway-env's
  default (20, 25, 30) m/s). FASTER / SLOWER set the index to the one nearest the *current*
  speed, plus or minus one (clamped); LANE_LEFT / LANE_RIGHT move the *target* lane by one
  (clamped to the road) where the new lane is reachable (its centre within two lane widths of
  the ego); IDLE keeps both. An ego starts with the lane it is in and the speed of the set
  nearest its own;
- speed: ``acceleration = (v_target - v) / 0.6 s``;
- lane: lateral speed command ``-(y - y_lane) / 0.6 s``, heading reference ``asin(v_lat / v)``
  (within +-45 deg), heading rate ``(psi_ref - psi_body) / 0.2 s``, the bicycle's steering for
  that rate (within +-60 deg; L the scenario's vehicle length).

The command then goes through the world's command path like any driver's (the scenario's
+-5 m/s^2 and +-45 deg): a plain agent drives the car the safe agents drive. Road frame: lane k's
centre at ``y = k * lane_width``; lane 0 is highway-env's leftmost, so LANE_LEFT lowers y.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Sequence

import torch

from mmpc.problem import EGO_PSI, EGO_PSIDOT, EGO_V, EGO_Y
from mmpc.rl.config import check_meta_speeds
from mmpc.road import Road

#: highway-env's DiscreteMetaAction indices.
LANE_LEFT, IDLE, LANE_RIGHT, FASTER, SLOWER = range(5)
META_ACTIONS = ("LANE_LEFT", "IDLE", "LANE_RIGHT", "FASTER", "SLOWER")
#: MDPVehicle's default target speeds [m/s].
TARGET_SPEEDS = (20.0, 25.0, 30.0)
#: ControlledVehicle's time constants [s] and steering limit [rad].
TAU_ACCELERATION, TAU_HEADING, TAU_LATERAL = 0.6, 0.2, 0.6
MAX_STEERING = math.pi / 3
#: A lane change is refused where the new lane's centre is farther than this many lane widths.
REACH_LANE_WIDTHS = 2.0


class MetaTargets(NamedTuple):
    """The targets of E egos: ``lane`` (E,) int64 lane index, ``speed_index`` (E,) int64 into the target speeds."""

    lane: torch.Tensor
    speed_index: torch.Tensor

    def select(self, rows: torch.Tensor) -> "MetaTargets":
        """The targets of the egos ``rows`` (R,)."""
        return MetaTargets(self.lane[rows], self.speed_index[rows])


class MetaActions:
    """The meta-actions and the lane and speed controller of E egos on ``road``.

    Args:
        road: the road (lane k's centre at ``y = k * lane_width``).
        length: the vehicle's length [m] (the bicycle's wheelbase as highway-env takes it).
        speeds: the target speeds, ascending and evenly spaced as MDPVehicle assumes [m/s]
            (``env.meta_speeds``; highway-env's default :data:`TARGET_SPEEDS`).
    """

    def __init__(self, road: Road, length: float, speeds: Sequence[float] = TARGET_SPEEDS) -> None:
        speeds = tuple(speeds)
        check_meta_speeds(speeds)
        speeds = tuple(float(v) for v in speeds)
        self.road = road
        self.length = float(length)
        self.speeds = speeds

    def nearest_index(self, speed: torch.Tensor) -> torch.Tensor:
        """(E,) int64 index of the target speed nearest ``speed`` (E,) [m/s] (MDPVehicle's ``speed_to_index``)."""
        low, high, top = self.speeds[0], self.speeds[-1], len(self.speeds) - 1
        return torch.round((speed.to(torch.float64) - low) / (high - low) * top).clamp(0, top).to(torch.int64)

    def target_speeds(self, targets: MetaTargets) -> torch.Tensor:
        """(E,) float64 target speeds [m/s]."""
        return torch.tensor(self.speeds, dtype=torch.float64, device=targets.speed_index.device)[targets.speed_index]

    def start(self, ego: torch.Tensor) -> MetaTargets:
        """The targets of egos ``ego`` (E, 6) (road frame, :data:`mmpc.EGO_FIELDS`) as highway-env
        creates an MDPVehicle: its lane and the target speed nearest its speed."""
        return MetaTargets(self.road.lane_index(ego[:, EGO_Y]), self.nearest_index(ego[:, EGO_V]))

    def apply(self, targets: MetaTargets, actions: torch.Tensor, ego: torch.Tensor) -> MetaTargets:
        """The targets after meta-actions ``actions`` (E,) (indices of :data:`META_ACTIONS`) at states ``ego`` (E, 6).

        Raises:
            ValueError: an action outside [0, 4].
        """
        road = self.road
        actions = torch.as_tensor(actions, device=targets.lane.device).to(torch.int64).reshape(-1)
        if actions.numel() and (int(actions.min()) < 0 or int(actions.max()) >= len(META_ACTIONS)):
            raise ValueError(f"meta-actions are indices of {META_ACTIONS}; got {sorted(set(actions.tolist()))}")
        step = (actions == LANE_RIGHT).to(torch.int64) - (actions == LANE_LEFT).to(torch.int64)
        lane = (targets.lane + step).clamp(0, road.num_lanes - 1)
        reachable = (lane * road.lane_width - ego[:, EGO_Y].to(torch.float64)).abs() <= REACH_LANE_WIDTHS * road.lane_width
        lane = torch.where(reachable, lane, targets.lane)
        nearest = self.nearest_index(ego[:, EGO_V])
        top = len(self.speeds) - 1
        speed_index = torch.where(actions == FASTER, (nearest + 1).clamp(max=top), targets.speed_index)
        speed_index = torch.where(actions == SLOWER, (nearest - 1).clamp(min=0), speed_index)
        return MetaTargets(lane, speed_index)

    def command(self, targets: MetaTargets, ego: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The controller's command towards ``targets`` at states ``ego`` (E, 6): (E,) acceleration
        [m/s^2] and (E,) steering [rad], float64."""
        ego = ego.to(torch.float64)
        v = ego[:, EGO_V].clamp_min(1e-3)
        body_heading = ego[:, EGO_PSI] - bicycle_slip(ego[:, EGO_PSIDOT], v, self.length)  # psi: the direction of motion
        lateral_speed = -(ego[:, EGO_Y] - targets.lane.to(torch.float64) * self.road.lane_width) / TAU_LATERAL
        heading_ref = torch.asin((lateral_speed / v).clamp(-1.0, 1.0)).clamp(-math.pi / 4, math.pi / 4)
        rate = (heading_ref - body_heading) / TAU_HEADING
        steering = bicycle_steering(rate, v, self.length).clamp(-MAX_STEERING, MAX_STEERING)
        acceleration = (self.target_speeds(targets) - ego[:, EGO_V]) / TAU_ACCELERATION
        return acceleration, steering


def bicycle_slip(rate: torch.Tensor, speed: torch.Tensor, length: float) -> torch.Tensor:
    """The slip angle beta [rad] at which highway-env's kinematic bicycle (turn rate
    ``v sin(beta) / (L / 2)``) turns at ``rate`` [rad/s] at ``speed`` [m/s] with length ``length``
    [m]; rates beyond the model's reach saturate at +-90 deg. Shapes: rate and speed broadcast;
    the result has their shape."""
    return torch.asin((length / 2 / speed * rate).clamp(-1.0, 1.0))


def bicycle_steering(rate: torch.Tensor, speed: torch.Tensor, length: float) -> torch.Tensor:
    """The steering angle [rad] (``beta = atan(tan(delta) / 2)``) of :func:`bicycle_slip`'s slip."""
    return torch.atan(2 * torch.tan(bicycle_slip(rate, speed, length)))
