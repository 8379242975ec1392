"""Occupancy sets: the road space each other car may cover under :class:`TrafficAssumptions`.

On the straight road a set is an axis-aligned box per car and time interval, bounding the car's
whole footprint (not its centre). Along the road: braking at ``max_deceleration`` to rest (less
what turning across the road takes from the path's progress) and speeding up at
``max_acceleration`` to ``max(v, speed_limit)``. Across: the footprint's edges swing out by a
turn to ``max_heading``, then move at most ``lateral_speed``, and stay within ``lane_overreach``
of the outermost lane centres the car may reach; the lane-change rule cuts that band where the
ego holds a lane:

- a car ahead of the moving ego, with no car between them on a lane the ego counts on for the
  whole manoeuvre checked, stays out of that lane unless it is changing into it already, under
  MOBIL's safety criterion (``TrafficAssumptions.cut_in``). The rule binds while the ego is behind
  the car: one the ego overtakes may enter behind it, where the fault rule below takes over. With
  the ego read as an IDM follower (``"follower"``) a car that may have decided already is not held;
  one that may decide later is held in this band and :attr:`Occupancy.enters`: the verifier adds,
  per path, where it could enter (:func:`mmpc.verify.cut_ins.entry_floor`);
- a car behind the ego answers for its own distance (the evaluation's fault rule). One wholly
  behind on a lane the ego counts on is a follower: it brakes at ``max_deceleration`` at most
  ``follower_reaction`` after the ego does, so its set along the road ends where that braking takes
  its front (:func:`follower_reach`). A path that stays ahead of it is never struck, whatever the
  ego's turn or braking along the road; a path that brakes or swerves into it is refused (the ego
  does not cut in close in front of it, nor brake harder than it can). A car alongside on a lane
  the ego counts on keeps its whole set. A car behind (its centre behind the ego's) elsewhere is
  not counted entering the ego's lanes (it would enter behind or into the side of the ego), even
  where it is changing towards them already.

The ego's lanes are those it counts on now (at most two, halfway between); each set comes in the
four variants of which of them the manoeuvre holds (:data:`HELD_VARIANTS`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from mmpc.problem import EGO_V, EGO_X, EGO_Y
from mmpc.road import Road
from mmpc.verify.assumptions import TrafficAssumptions
from mmpc.verify.cut_ins import may_have_decided

#: Variants of the lateral bounds: bit 0 set where the manoeuvre holds the ego's nearest lane,
#: bit 1 where it holds the other lane it counts on (none: the variants repeat).
HELD_VARIANTS = 4


class Occupancy(NamedTuple):
    """Footprint boxes of M cars over T intervals ``[times[k], times[k + 1]]`` [m].

    Fields:
        x_low, x_high: (E, M, T) along the road.
        y_low, y_high: (E, H, M, T) across, per variant of :data:`HELD_VARIANTS`.
        ego_lanes: (E, 2) long, the ego's nearest lane and the other lane it counts on (-1: none).
        enters: (E, M) bool, cars the lane-change rule holds out of a lane the ego holds that may
            still decide to enter it ahead of the ego (``cut_in="follower"``); the band of variant 0
            (no lane held) is theirs past :func:`mmpc.verify.cut_ins.entry_floor`.
    """

    x_low: torch.Tensor
    x_high: torch.Tensor
    y_low: torch.Tensor
    y_high: torch.Tensor
    ego_lanes: torch.Tensor
    enters: torch.Tensor


def counted_lanes(y: torch.Tensor, road: Road, margin: float) -> torch.Tensor:
    """(..., 2) long: the nearest lane of lateral positions ``y`` (...) [m] and the other lane
    whose centre lies within ``lane_width / 2 + margin`` (-1 where none): the lanes MOBIL counts
    a vehicle on."""
    nearest = road.lane_index(y)
    offset = y - nearest.to(y.dtype) * road.lane_width
    side = torch.where(offset >= 0, 1, -1)
    other = nearest + side
    counts = (offset.abs() >= road.lane_width / 2 - margin) & (other >= 0) & (other < road.num_lanes)
    return torch.stack([nearest, torch.where(counts, other, -1)], dim=-1)


def held_variant(ego_lanes: torch.Tensor, path_y: torch.Tensor, road: Road, margin: float) -> torch.Tensor:
    """Which of the ego's lanes a manoeuvre holds, as a :data:`HELD_VARIANTS` index: bit j set where
    the ego, at every lateral position of ``path_y`` (E, ..., P) [m], counts on ``ego_lanes[:, j]``
    ((E, 2), -1: none; :func:`counted_lanes` with ``margin``). Returns (E, ...) long."""
    counted = counted_lanes(path_y, road, margin)  # (E, ..., P, 2)
    lanes = ego_lanes.view(ego_lanes.shape[0], *[1] * (path_y.dim() - 1), 2)  # (E, 1, ..., 1, 2)
    held = ((counted[..., :, None] == lanes[..., None, :]).any(dim=-2) & (lanes >= 0)).all(dim=-2)  # (E, ..., 2)
    return held[..., 0].long() + 2 * held[..., 1].long()


def body_reach(vx: torch.Tensor, vy: torch.Tensor, assumptions: TrafficAssumptions) -> tuple[torch.Tensor, torch.Tensor]:
    """Half extents (along, across the road) [m] of bodies of the assumed size heading along their
    velocity (vx, vy) [m/s], any shape."""
    heading = torch.atan2(vy, vx)
    cos, sin = torch.cos(heading).abs(), torch.sin(heading).abs()
    half_length, half_width = 0.5 * assumptions.length, 0.5 * assumptions.width
    return half_length * cos + half_width * sin, half_length * sin + half_width * cos


def follower_reach(vehicles: torch.Tensor, times: torch.Tensor, assumptions: TrafficAssumptions) -> torch.Tensor:
    """(E, M, T): how far along the road each car's front reaches by the end of each interval of
    ``times`` (T + 1,) [s] as a follower: at its speed until ``follower_reaction``, then braking at
    ``max_deceleration`` to rest [m] (bodies of :attr:`TrafficAssumptions.half_length`). Left sums
    (each interval at its starting speed): the speed never rises, so they bound the continuous and
    the frame-stepped car alike.

    Example: a car at 10 m/s, frames of 0.5 s: 5.0 m in the first, then 4.4 (braking from 0.3 s),
    2.9 and 1.4 to rest:

        >>> import torch
        >>> cars = torch.tensor([[[0.0, 0.0, 10.0, 0.0]]])
        >>> reach = follower_reach(cars, torch.arange(6) * 0.5, TrafficAssumptions())
        >>> [round(v - TrafficAssumptions().half_length, 1) for v in reach[0, 0].tolist()]
        [5.0, 9.4, 12.3, 13.7, 13.7]
    """
    a = assumptions
    speed = torch.hypot(vehicles[..., 2], vehicles[..., 3])  # (E, M)
    starts, steps = times[:-1].to(vehicles.dtype), (times[1:] - times[:-1]).to(vehicles.dtype)
    braked = a.max_deceleration * (starts - a.follower_reaction).clamp_min(0.0)  # (T,)
    slow = (speed[..., None] - braked).clamp_min(0.0)  # (E, M, T) at each interval's start
    return vehicles[..., 0, None] + a.half_length + torch.cumsum(slow * steps, dim=-1)


def occupancy(ego: torch.Tensor, vehicles: torch.Tensor, mask: torch.Tensor, road: Road, times: torch.Tensor,
              assumptions: TrafficAssumptions, *, fault_rule: bool = True, decided_within: float = 0.0) -> Occupancy:
    """The occupancy sets of E environments' cars over the intervals of ``times``.

    Args:
        ego: (E, 6) ego states now (:data:`mmpc.EGO_FIELDS`).
        vehicles: (E, M, 4) other cars' x, y [m], vx, vy [m/s] now.
        mask: (E, M) bool, present cars.
        road: the road.
        times: (T + 1,) increasing times from now, ``times[0] = 0`` [s].
        assumptions: what the cars may do.
        fault_rule: bound the followers by their braking, and keep the cars behind the ego out of
            its lanes (what the verification may do); ``False``: the sets of the traffic's rules
            alone (what the monitor checks).
        decided_within: under ``cut_in="follower"``, a car that may decide to enter a lane the ego
            holds up to this long from now [s] is not held out of it (0 for the verifier, which
            bounds later decisions per path; the monitor's period for the monitor).

    Returns:
        The :class:`Occupancy` (T intervals).
    """
    a = assumptions
    dtype = vehicles.dtype
    x, y, vx, vy = vehicles.unbind(dim=-1)  # (E, M)
    speed = torch.hypot(vx, vy)
    ends = times[1:].to(dtype)  # (T,)
    width = road.lane_width

    # Along the road: speed bounds at the end of each interval, integrated by right sums (the
    # lower bound falls, the upper rises, so both sums bound the motion of the continuous and the
    # frame-stepped car alike); a turned car covers its path less tan(heading / 2) x its lateral travel.
    steps = (times[1:] - times[:-1]).to(dtype)
    slow = (speed[..., None] - a.max_deceleration * ends).clamp_min(0.0)
    fast = torch.minimum(speed[..., None] + a.max_acceleration * ends, speed.clamp_min(a.speed_limit)[..., None])
    crossing = math.tan(0.5 * a.max_heading) * (a.lateral_speed * ends).clamp_max(a.lateral_travel)
    x_low = x[..., None] - a.half_length - crossing + torch.cumsum(slow * steps, dim=-1) - slow * steps
    x_high = x[..., None] + a.half_length + torch.cumsum(fast * steps, dim=-1)

    # Across: the footprint's edges now (heading from the velocity; at rest any heading), swung
    # out at once by a turn to ``max_heading`` (the body turns within a frame or two), then moved
    # at ``lateral_speed``.
    turned = 0.5 * a.length * math.sin(a.max_heading) + 0.5 * a.width * math.cos(a.max_heading)
    reach = torch.where(speed > 1e-3, body_reach(vx, vy, a)[1], torch.full_like(speed, a.half_length))
    swing = (turned - reach).clamp_min(0.0)
    edge_low, edge_high = y - reach, y + reach
    spread = swing[..., None] + a.lateral_speed * ends  # (E, M, T)

    lane = road.lane_index(y)  # (E, M)
    offset = y - lane.to(dtype) * width
    toward = torch.where(vy.abs() > a.change_speed, vy.sign(), torch.where(offset.abs() >= a.change_offset,
                                                                           offset.sign(), torch.zeros_like(vy)))
    # a car changing lane is bound for the next lane on its way (the nearest, once past halfway)
    target = torch.where((toward != 0) & (offset * toward >= 0), lane + toward.long(), lane)
    ego_lanes = counted_lanes(ego[:, EGO_Y], road, a.lane_margin)  # (E, 2)
    car_lanes = counted_lanes(y, road, a.lane_margin)  # (E, M, 2)
    on_ego_lane = ((car_lanes[..., :, None] == ego_lanes[:, None, None, :]) & (ego_lanes[:, None, None, :] >= 0))  # (E, M, 2, 2)
    on_ego_lane = on_ego_lane.any(dim=2)  # (E, M, 2): counted on the ego's lane j
    ego_x = ego[:, EGO_X, None]
    behind = (x < ego_x) & fault_rule
    wholly_behind = (ego_x - x > a.length) & fault_rule  # bodies of the assumed length
    follower = wholly_behind & on_ego_lane.any(dim=-1)  # (E, M): its set ends where its braking takes it
    x_high = torch.where(follower[..., None], torch.minimum(x_high, follower_reach(vehicles, times, a)), x_high)

    # Per lane j of the ego: the cars the rule keeps out of it where the manoeuvre holds it (ahead
    # of the ego with nobody between, not bound there already, and not free to decide by MOBIL's
    # criterion) and those the fault rule always does.
    if a.cut_in == "follower":
        held_by_rule = ~may_have_decided(ego, vehicles, a, after=decided_within)
    else:
        held_by_rule = torch.full_like(mask, a.cut_in == "highway-env")
    cuts = []
    for j in range(2):
        blocked_lane = ego_lanes[:, j, None].expand_as(lane)  # (E, M)
        eligible = (blocked_lane >= 0) & mask & ~on_ego_lane[..., j]
        bound_there = (toward != 0) & (target == blocked_lane)  # decided before now: the rule no longer holds it
        by_rule = (eligible & (x >= ego_x) & ~_cars_between(x, car_lanes, mask, ego_x, blocked_lane) & ~bound_there
                   & held_by_rule)
        cuts.append((blocked_lane, blocked_lane > lane, by_rule, eligible & behind))  # above: on the car's +y side

    # Lane bands: the whole road, cut on the car's side of each lane it may not enter.
    low_lane = torch.zeros_like(lane)
    high_lane = torch.full_like(lane, road.num_lanes - 1)
    y_low, y_high = [], []
    for variant in range(HELD_VARIANTS):
        low_cut, high_cut = low_lane, high_lane
        for j, (blocked_lane, above, by_rule, by_fault) in enumerate(cuts):
            keeps_out = (by_rule | by_fault) if variant >> j & 1 else by_fault
            high_cut = torch.where(keeps_out & above, torch.minimum(high_cut, blocked_lane - 1), high_cut)
            low_cut = torch.where(keeps_out & ~above, torch.maximum(low_cut, blocked_lane + 1), low_cut)
        band_low = torch.minimum(low_cut.to(dtype) * width - a.lane_overreach, edge_low)
        band_high = torch.maximum(high_cut.to(dtype) * width + a.lane_overreach, edge_high)
        y_low.append(torch.maximum(band_low[..., None], edge_low[..., None] - spread))
        y_high.append(torch.minimum(band_high[..., None], edge_high[..., None] + spread))
    enters = (cuts[0][2] | cuts[1][2]) & (a.cut_in == "follower")
    return Occupancy(x_low, x_high, torch.stack(y_low, dim=1), torch.stack(y_high, dim=1), ego_lanes, enters)


def _cars_between(x: torch.Tensor, car_lanes: torch.Tensor, mask: torch.Tensor, ego_x: torch.Tensor,
                  lane: torch.Tensor) -> torch.Tensor:
    """(E, M) bool: another present car counts on ``lane`` (E, M) with its x between the ego's and car m's."""
    on_lane = ((car_lanes[:, None, :, :] == lane[..., None, None]).any(dim=-1)) & mask[:, None, :]  # (E, M, M'): m' on m's lane
    inside = (x[:, None, :] > ego_x[..., None]) & (x[:, None, :] < x[:, :, None])
    return (on_lane & inside).any(dim=-1)
