"""The other vehicles' driving: highway-env's ``IDMVehicle`` on straight lanes, batched
(longitudinal IDM behind the nearest vehicle ahead, lateral ``ControlledVehicle.steering_control``).

IDM (``IDMVehicle.acceleration``), for a vehicle of speed v behind one at gap d (centre to
centre, along the road) closing at dv (the velocity difference projected on its heading)::

    a = a_max [1 - (max(v, 0) / v0)^delta] - a_max (d* / d)^2,   d* = d0 + v T + v dv / (2 sqrt(a_max b))

with v0 the target speed clipped to [0, speed_limit]; without a vehicle ahead the second term
is dropped. A vehicle off its target lane takes the smaller of the two lanes' accelerations;
the result is clipped to +-acc_max. Divisors near zero become +-0.01 as highway-env's ``not_zero``.
"""

from __future__ import annotations

from typing import Optional

import torch

from mmpc.compaction import capacity, compact
from mmpc.sim.config import SimConfig
from mmpc.sim.state import VehicleState

#: The lane changers' buffer per environment on average (traffic holds ~1.7), at least one per vehicle.
CHANGES_PER_ENV = 4.0
#: highway-env's ``utils.not_zero`` threshold.
NOT_ZERO = 1e-2


def not_zero(value: torch.Tensor) -> torch.Tensor:
    """``value`` with |value| <= 0.01 replaced by 0.01 carrying its sign (+0.01 for 0)."""
    small = value.abs() <= NOT_ZERO
    return torch.where(small, torch.where(value >= 0, NOT_ZERO, -NOT_ZERO).to(value.dtype), value)


def wrap_to_pi(angle: torch.Tensor) -> torch.Tensor:
    """Angles [rad] wrapped to [-pi, pi)."""
    return torch.remainder(angle + torch.pi, 2 * torch.pi) - torch.pi


def _search(state: VehicleState, lane: torch.Tensor, query, config: SimConfig) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The searching vehicles' slots (E, Q), and (E, Q, V): [e, q, j] vehicle j is present, not
    the searcher, and within ``lane_width / 2 + lane_margin`` of the centre of lane ``lane[e, q]``."""
    slots = torch.arange(state.x.shape[1], device=state.x.device)
    query = slots.expand(state.x.shape) if query is None else query
    centre = lane.to(state.y.dtype) * config.lane_width
    on_lane = (state.y[:, None, :] - centre[:, :, None]).abs() <= config.lane_width / 2 + config.lane_margin
    return query, torch.gather(state.x, 1, query), on_lane & state.alive[:, None, :] & (slots != query[:, :, None])


def vehicle_ahead(
    state: VehicleState, lane: torch.Tensor, config: SimConfig, query: Optional[torch.Tensor] = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """For every vehicle (or the slots ``query``), the nearest other present vehicle ahead on lane ``lane``.

    A vehicle is on a lane within ``lane_width / 2 + lane_margin`` of its centre (so one
    between two lanes counts on both); ahead means ``x_other >= x`` (equal counts); on equal
    ``x`` the later slot wins, as in highway-env's ``Road.neighbour_vehicles``. The ego counts.

    Args:
        lane: (E, V) int64, or (E, Q) with ``query``: the lane searched for each vehicle.
        query: (E, Q) int64 slots of the searching vehicles; default: every slot (Q = V).

    Returns:
        index: (E, Q) int64 slot of the vehicle ahead (0 where there is none).
        found: (E, Q) bool.
    """
    query, x, candidate = _search(state, lane, query, config)
    candidate = candidate & (state.x[:, None, :] >= x[:, :, None])
    distance = torch.where(candidate, state.x[:, None, :], torch.full_like(candidate, torch.inf, dtype=state.x.dtype))
    nearest = distance.min(dim=2, keepdim=True).values
    slots = torch.arange(state.x.shape[1], device=state.x.device)
    index = torch.where(candidate & (distance == nearest), slots, -1).max(dim=2).values
    return index.clamp(min=0), index >= 0


def vehicle_behind(
    state: VehicleState, lane: torch.Tensor, config: SimConfig, query: Optional[torch.Tensor] = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """For every vehicle (or the slots ``query``), the nearest other present vehicle behind on
    lane ``lane``: on the lane as in :func:`vehicle_ahead`, behind meaning ``x_other < x``
    (strictly); on equal ``x`` the earlier slot wins, as in highway-env's
    ``Road.neighbour_vehicles``. The ego counts. Shapes as :func:`vehicle_ahead`.
    """
    num_vehicles = state.x.shape[1]
    query, x, candidate = _search(state, lane, query, config)
    candidate = candidate & (state.x[:, None, :] < x[:, :, None])
    position = torch.where(candidate, state.x[:, None, :], torch.full_like(candidate, -torch.inf, dtype=state.x.dtype))
    nearest = position.max(dim=2, keepdim=True).values
    slots = torch.arange(num_vehicles, device=state.x.device)
    index = torch.where(candidate & (position == nearest), slots, num_vehicles).min(dim=2).values
    return torch.where(index < num_vehicles, index, 0), index < num_vehicles


def desired_gap(speed: torch.Tensor, heading: torch.Tensor, front_speed: torch.Tensor, front_heading: torch.Tensor,
                config: SimConfig) -> torch.Tensor:
    """IDM desired gap ``d* = d0 + v T + v dv / (2 sqrt(a_max b))`` [m] of a vehicle of speed
    ``speed`` [m/s] and heading ``heading`` [rad] behind one of ``front_speed``, ``front_heading``;
    ``dv`` is the velocity difference projected on the follower's heading (as highway-env's
    ``IDMVehicle.desired_gap``). All four tensors broadcast together; the result has their shape."""
    cos, sin = torch.cos(heading), torch.sin(heading)
    closing = ((speed * cos - front_speed * torch.cos(front_heading)) * cos
               + (speed * sin - front_speed * torch.sin(front_heading)) * sin)
    ab = -config.comfort_acc_max * config.comfort_acc_min
    return config.distance_wanted + speed * config.time_wanted + speed * closing / (2 * ab ** 0.5)


def idm_between(
    state: VehicleState,
    follower: torch.Tensor,
    has_follower: torch.Tensor,
    front: torch.Tensor,
    has_front: torch.Tensor,
    delta: torch.Tensor,
    target_speed: torch.Tensor,
    config: SimConfig,
) -> torch.Tensor:
    """IDM acceleration [m/s^2] (unclipped) of slot ``follower`` behind slot ``front``, as
    highway-env's ``IDMVehicle.acceleration(ego_vehicle=follower, front_vehicle=front)``
    evaluated by a vehicle whose exponent is ``delta``: 0 without a follower, the free-road
    term alone without a front vehicle.

    Args:
        state: the vehicles.
        follower, front: (E, Q) int64 slots. has_follower, has_front: (E, Q) bool.
        delta: (E, Q) IDM exponent of the evaluating vehicle (not the follower's own).
        target_speed: (E, V) target speed [m/s] of every slot, read at ``follower``.

    Returns:
        (E, Q) acceleration [m/s^2].
    """
    speed, heading, x, target = (torch.gather(field, 1, follower) for field in
                                 (state.speed, state.heading, state.x, target_speed))
    target = target.clamp(0.0, config.speed_limit)
    free = config.comfort_acc_max * (1 - torch.pow(speed.clamp(min=0.0) / not_zero(target).abs(), delta))
    front_x, front_speed, front_heading = (torch.gather(field, 1, front) for field in (state.x, state.speed, state.heading))
    gap = desired_gap(speed, heading, front_speed, front_heading, config)
    interaction = config.comfort_acc_max * torch.pow(gap / not_zero(front_x - x), 2)
    acceleration = torch.where(has_front, free - interaction, free)
    return torch.where(has_follower, acceleration, torch.zeros_like(acceleration))


def idm_acceleration(state: VehicleState, lane: torch.Tensor, config: SimConfig,
                     query: Optional[torch.Tensor] = None) -> torch.Tensor:
    """(E, Q) IDM acceleration [m/s^2], unclipped, of every vehicle (or the slots ``query``, (E, Q)
    int64) behind its vehicle ahead on ``lane`` (E, Q)."""
    own = torch.arange(state.x.shape[1], device=state.x.device).expand(state.x.shape) if query is None else query
    index, found = vehicle_ahead(state, lane, config, own)
    delta = torch.gather(state.idm_delta, 1, own)
    return idm_between(state, own, torch.ones_like(found), index, found, delta, state.target_speed, config)


def lane_keeping_steering(state: VehicleState, config: SimConfig) -> torch.Tensor:
    """(E, V) steering [rad] of every vehicle to its target lane's centre (:func:`steering_to_lane`)."""
    return steering_to_lane(state.y, state.heading, state.speed, state.length,
                            state.target_lane.to(state.y.dtype) * config.lane_width, config)


def steering_to_lane(y: torch.Tensor, heading: torch.Tensor, speed: torch.Tensor, length: torch.Tensor | float,
                     target_y: torch.Tensor, config: SimConfig, max_steering: float | None = None) -> torch.Tensor:
    """Steering [rad] to the lane centre ``target_y`` [m] (``ControlledVehicle.steering_control``
    on a straight lane along +x), any shape (broadcast): a lateral speed ``-kp_lateral * offset``
    becomes a heading reference (within +-pi/4), a heading rate ``kp_heading * (reference -
    heading)`` a slip angle and that a steering angle, clipped to +-``max_steering`` (default:
    ``config.max_steering``, the IDM vehicles')."""
    offset = y - target_y
    speed = not_zero(speed)
    lateral_speed = -config.kp_lateral * offset
    heading_reference = torch.asin((lateral_speed / speed).clamp(-1, 1)).clamp(-torch.pi / 4, torch.pi / 4)
    heading_rate = config.kp_heading * wrap_to_pi(heading_reference - heading)
    sin_slip = (length / 2 / speed * heading_rate).clamp(-1, 1)
    # atan(2 tan(asin(s))) written with atan2: tan(asin(+-1)) in float32 can come out with the wrong sign
    steering = torch.atan2(2 * sin_slip, torch.sqrt(1 - sin_slip * sin_slip))
    bound = config.max_steering if max_steering is None else max_steering
    return steering.clamp(-bound, bound)


def traffic_command(state: VehicleState, config: SimConfig) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every vehicle's IDM command (``IDMVehicle.act`` after the lane-change decision of
    :func:`mmpc.sim.mobil.change_lanes`, towards ``target_lane``): (acceleration
    [m/s^2], steering [rad]), each (E, V). Slot 0 (the ego) is computed too; the caller replaces it.
    A vehicle changing lane takes the smaller of its two lanes' accelerations; those vehicles are
    asked, each with a copy of its environment (``config.fixed_shapes``: in a buffer of
    :data:`CHANGES_PER_ENV` per environment, :mod:`mmpc.compaction`); the third tensor, (E,)
    bool, marks the environments with changes past it (left on their current lane's acceleration:
    never seen in traffic)."""
    acceleration = idm_acceleration(state, state.lane, config)
    num_envs, num_vehicles = state.x.shape
    changing = state.lane != state.target_lane
    changing[:, 0] = False
    buffer = capacity(config.fixed_shapes, num_envs, CHANGES_PER_ENV, num_vehicles, num_envs * num_vehicles)
    found = compact(changing, buffer)
    env, slot = found.index  # the padding points at (0, 0), the ego, whose command the caller replaces
    if buffer is not None or env.numel():  # exact sizes: nothing to do without changers (a frame in most)
        copies = VehicleState(*(field[env] for field in state))
        on_target = idm_acceleration(copies, state.target_lane[env, slot][:, None], config, slot[:, None])[:, 0]
        current = acceleration[env, slot]
        acceleration[env, slot] = torch.where(found.valid, torch.minimum(current, on_target), current)
    return (acceleration.clamp(-config.acc_max, config.acc_max), lane_keeping_steering(state, config),
            found.dropped.any(dim=1))
