"""Fail-safe manoeuvres: from any ego state, brake to rest while steering to a lane centre.

A fail-safe is a feedback law, (target lane, deceleration): every frame the ego brakes at the
deceleration (highway-env's command path: no braking through rest) and steers to the lane's
centre with the lane-change controller the traffic uses (:func:`mmpc.sim.idm.steering_to_lane`,
within the ego's steering range). The set tried from a state is the nearest lane and its
neighbours (brake in lane, abort back, complete the change), each at every deceleration of
:class:`FailSafes`. Driving the law from the state it was verified from retraces the verified
path, so a stored fail-safe stays valid while the world moves as the ego's model says.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch

from mmpc.config import require, require_field_types
from mmpc.problem import EGO_PSI, EGO_PSIDOT, EGO_V, EGO_X, EGO_Y
from mmpc.road import Road
from mmpc.sim.config import SimConfig
from mmpc.sim.ego import ego_action
from mmpc.sim.idm import steering_to_lane
from mmpc.sim.kinematics import bicycle_frame


@dataclass(frozen=True)
class FailSafes:
    """The fail-safe manoeuvres tried from each state.

    Attributes:
        decelerations: braking levels [m/s^2], strongest first (the ego's range ends at 5; a
            milder second level verified no more steps and doubled the check's time).
        lanes: lanes either side of the nearest one steered to (1: abort and complete).
    """

    decelerations: tuple[float, ...] = (5.0,)
    lanes: int = 1

    def __post_init__(self) -> None:
        require_field_types(self)
        require(len(self.decelerations) > 0 and all(d > 0 for d in self.decelerations),
                f"FailSafes: `decelerations` must be positive [m/s^2]; got {self.decelerations}")
        require(self.lanes >= 0, f"FailSafes: `lanes` must be >= 0; got {self.lanes}")


class Body(NamedTuple):
    """Ego bodies, every field of one shape (...): x, y [m], heading (of the body) [rad], speed [m/s]."""

    x: torch.Tensor
    y: torch.Tensor
    heading: torch.Tensor
    speed: torch.Tensor

    def expand(self, *shape: int) -> "Body":
        return Body(*(field.expand(*shape) for field in self))


def ego_body(ego: torch.Tensor, length: float) -> Body:
    """The (E,) bodies of (E, 6) ego states: their ``psi`` is the direction of motion, the body
    heading plus the slip angle that ``psidot = v sin(beta) / (length / 2)`` gives."""
    speed = ego[:, EGO_V]
    sin_slip = (ego[:, EGO_PSIDOT] * 0.5 * length / speed.clamp_min(1e-3)).clamp(-1.0, 1.0)
    slip = torch.where(speed > 1e-3, torch.asin(sin_slip), torch.zeros_like(speed))
    return Body(ego[:, EGO_X], ego[:, EGO_Y], ego[:, EGO_PSI] - slip, speed)


def drive(body: Body, acceleration: torch.Tensor, steering: torch.Tensor, length: float, sim: SimConfig) -> Body:
    """``body`` after one command held ``sim.frames_per_command`` frames, as the worlds apply it."""
    acceleration, steering = ego_action(acceleration, steering, body.speed, sim)
    x, y, heading, speed = body
    for _ in range(sim.frames_per_command):
        x, y, heading, speed = bicycle_frame(x, y, heading, speed, length, acceleration, steering, sim.dt)
    return Body(x, y, heading, speed.clamp_min(0.0))


def failsafe_command(body: Body, lane: torch.Tensor, deceleration: torch.Tensor, length: float, road: Road,
                     sim: SimConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """The fail-safe law's (acceleration [m/s^2], steering [rad]) at ``body``, to ``lane`` (long)
    at ``deceleration`` [m/s^2], all of one shape."""
    target = lane.to(body.y.dtype) * road.lane_width
    steering = steering_to_lane(body.y, body.heading, body.speed, length, target, sim, max_steering=sim.steering_range[1])
    return -deceleration.expand_as(body.speed), steering


def failsafe_table(body: Body, road: Road, failsafes: FailSafes) -> tuple[torch.Tensor, torch.Tensor]:
    """The fail-safes tried from ``body`` (...), in order of preference (the nearest lane, then
    the neighbours; each lane at every deceleration): target lanes (..., F) long and
    decelerations (..., F) [m/s^2]."""
    nearest = road.lane_index(body.y)
    sides = [offset for step in range(1, failsafes.lanes + 1) for offset in (-step, step)]
    offsets = torch.tensor([0, *sides], device=nearest.device)  # braking in lane first
    lanes = (nearest[..., None] + offsets).clamp(0, road.num_lanes - 1)  # an edge lane repeats: harmless
    decelerations = torch.tensor(failsafes.decelerations, dtype=body.x.dtype, device=body.x.device)
    count = len(failsafes.decelerations)
    lanes = lanes.repeat_interleave(count, dim=-1)
    return lanes, decelerations.repeat(offsets.numel()).expand(lanes.shape)


def rollout(body: Body, lane: torch.Tensor, deceleration: torch.Tensor, frames: int, length: float, road: Road,
            sim: SimConfig) -> Body:
    """The fail-safe (``lane``, ``deceleration``) from ``body``, every field (...): poses at the
    end of each command, every field (..., frames)."""
    poses = []
    for _ in range(frames):
        acceleration, steering = failsafe_command(body, lane, deceleration, length, road, sim)
        body = drive(body, acceleration, steering, length, sim)
        poses.append(body)
    return Body(*(torch.stack(field, dim=-1) for field in zip(*poses)))
