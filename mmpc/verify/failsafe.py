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

import functools
from dataclasses import dataclass
from typing import Callable, NamedTuple

import torch

from mmpc.config import require, require_field_types
from mmpc.problem import EGO_PSI, EGO_PSIDOT, EGO_V, EGO_X, EGO_Y
from mmpc.road import Road
from mmpc.sim.config import SimConfig
from mmpc.sim.ego import ego_action
from mmpc.sim.idm import steering_to_lane
from mmpc.sim.kinematics import bicycle_frame
from mmpc.solver import execution
from mmpc.verify.compiling import CheckCompiling

#: Frames of the fail-safe law per compiled call: eager, the law is ~50 small tensor operations a
#: frame, launch-bound at one environment's few rollouts; compiled, a call costs ~0.2 ms whatever
#: its frames, and compiling grows with them (8: ~60 s on one core the first time, ~8 s from
#: inductor's on-disk cache; longer chunks were no faster).
ROLLOUT_CHUNK = 8


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


class FailSafeRollout:
    """:func:`rollout`, eager or compiled: the fail-safes of a road, command path and ego length.

    Compiled, the law runs :data:`ROLLOUT_CHUNK` frames per call of one graph over a flat batch of
    any size; the last chunk's frames past ``frames`` are dropped, so both paths give the same
    poses to the rounding of fused arithmetic.

    Args:
        length: the ego's length [m].
        road: the road.
        sim: the worlds' constants (the ego's command path).
        compiling: when to run compiled (shared with the check's other parts).
    """

    def __init__(self, length: float, road: Road, sim: SimConfig, compiling: CheckCompiling) -> None:
        self.length, self.road, self.sim, self.compiling = float(length), road, sim, compiling

    def __call__(self, body: Body, lane: torch.Tensor, deceleration: torch.Tensor, frames: int) -> Body:
        """The fail-safe (``lane``, ``deceleration``) from ``body``, every field (...): poses at the
        end of each command, every field (..., frames)."""
        if torch.compiler.is_compiling():  # inside a caller's graph
            return rollout(body, lane, deceleration, frames, self.length, self.road, self.sim)
        if self.compiling.compiled and body.x.numel() and body.x.device.type == "cpu":
            path = self.compiling.attempt(lambda: self._compiled(body, lane, deceleration, frames))
            if path is not None:
                return path
        return self.compiling.eager(rollout, body, lane, deceleration, frames, self.length, self.road, self.sim)

    def _compiled(self, body: Body, lane: torch.Tensor, deceleration: torch.Tensor, frames: int) -> Body:
        shape = body.x.shape
        chunk = _compiled_chunk(self.length, self.road, self.sim)
        state = [field.reshape(-1) for field in body]
        lane, deceleration = lane.expand(shape).reshape(-1), deceleration.expand(shape).reshape(-1)
        poses = []
        for _ in range(execution.ceil_div(frames, ROLLOUT_CHUNK)):
            poses.append(chunk(*state, lane, deceleration))  # (4, ROLLOUT_CHUNK, N)
            state = list(poses[-1][:, -1].unbind(0))  # contiguous, as the first call's: no recompile
        path = torch.cat(poses, dim=1)[:, :frames].movedim(1, -1)  # (4, N, frames)
        return Body(*(field.reshape(*shape, frames) for field in path.unbind(0)))


@functools.lru_cache(maxsize=None)
def _compiled_chunk(length: float, road: Road, sim: SimConfig) -> Callable[..., torch.Tensor]:
    """:data:`ROLLOUT_CHUNK` frames of the law over flat (N,) x, y, heading, speed, lane (long) and
    deceleration, compiled for any N (one per distinct road, command path and length in a
    process): the poses (4, ROLLOUT_CHUNK, N)."""

    def frames(x: torch.Tensor, y: torch.Tensor, heading: torch.Tensor, speed: torch.Tensor, lane: torch.Tensor,
               deceleration: torch.Tensor) -> torch.Tensor:
        body, poses = Body(x, y, heading, speed), []
        for _ in range(ROLLOUT_CHUNK):
            acceleration, steering = failsafe_command(body, lane, deceleration, length, road, sim)
            body = drive(body, acceleration, steering, length, sim)
            poses.append(torch.stack(tuple(body)))
        return torch.stack(poses, dim=1)

    return torch.compile(frames, dynamic=True, fullgraph=True)  # a C++ wrapper compiled longer and ran no faster
