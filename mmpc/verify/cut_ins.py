"""Cut-ins under MOBIL's safety criterion with the ego read as an IDM follower.

A car decides to enter the ego's lane ahead of it only where the ego, as its new follower, would
brake at most ``max_braking_imposed``: IDM's acceleration of a follower holding its present speed
(target speed = speed, so no free-road term above rest) behind a leader ``d`` ahead (centres) is
``-a (d* / d)^2`` with ``d* = d0 + v T + v (v - w) / (2 sqrt(a b))`` (``v`` the ego's speed, ``w``
the car's along the ego's heading), so it decides only with ``d >= sqrt(a / b_imposed) |d*|``.
That bounds where an entering car can be, not only when it may enter:

- :func:`may_have_decided`: a decision taken before now (up to ``decision_lag``, not yet visible
  as a lane change) or within a short window after, bounded over every state the ego and the car
  may have been or be in then;
- :func:`entry_floor`: on one path of the ego, the lowest point along the road of an entering
  car's footprint at each pose: a car that decides at pose j sits at least ``sqrt(a / b) |d*|``
  ahead of the ego's pose j and no further back than its speed at that moment lets it be (slower
  cars have larger ``d*``), and moves on at least as the slowest car does.

The ``highway-env`` reading of a continuous-action ego (no target speed, so MOBIL predicts it
braking beyond any bound and no car ever decides to enter directly ahead of the moving ego) is
:attr:`TrafficAssumptions.cut_in` ``"highway-env"``; claims that rest on it hold for that
simulator's traffic only.
"""

from __future__ import annotations

import math
from typing import Optional

import torch

from mmpc.problem import EGO_V, EGO_X
from mmpc.verify.assumptions import TrafficAssumptions

#: highway-env's ``utils.not_zero``: IDM's divisors are kept this far from zero [m], [m/s].
NOT_ZERO = 1e-2

#: Braking profiles (speed falling at ``max_deceleration`` from a start) :func:`entry_floor` rounds
#: an entering car's least motion down to (more: tighter, dearer).
PROFILES = 12

#: Car speeds between a set's bounds at which :func:`entry_floor` evaluates the criterion (the
#: bound is sound for any count; more points make it tighter where a car's speed range is wide).
SPEED_POINTS = 5


def desired_gap(assumptions: TrafficAssumptions, ego_speed: torch.Tensor, car_speed: torch.Tensor) -> torch.Tensor:
    """IDM's desired gap ``d*`` [m] of an ego at ``ego_speed`` behind a car at ``car_speed`` [m/s]."""
    a = assumptions
    root = 2 * math.sqrt(a.max_acceleration * a.comfort_deceleration)
    return a.distance_wanted + ego_speed * a.time_wanted + ego_speed * (ego_speed - car_speed) / root


def safe_distance(assumptions: TrafficAssumptions, smallest_gap: torch.Tensor, ego_slowest: torch.Tensor) -> torch.Tensor:
    """The shortest distance between centres [m] at which a car may decide to enter ahead of the
    ego, given the smallest ``|d*|`` [m]; an ego that may be at rest has IDM's free-road term
    (``a``) on its side, as highway-env's ``not_zero`` target speed gives it."""
    a = assumptions
    free = torch.where(ego_slowest <= NOT_ZERO, a.max_acceleration, 0.0)
    return smallest_gap * torch.sqrt(a.max_acceleration / (a.max_braking_imposed + free))


def may_have_decided(ego: torch.Tensor, vehicles: torch.Tensor, assumptions: TrafficAssumptions, after: float = 0.0
                     ) -> torch.Tensor:
    """(E, M) bool: each car, ahead of the ego, may have decided to enter its lane at some time in
    ``[-decision_lag, after]`` [s]: the largest distance and the smallest ``|d*|`` that the ego's
    (``ego_acceleration``) and the car's (``max_deceleration``, ``max_acceleration``) bounds allow
    over that window satisfy the criterion.

    Args:
        ego: (E, 6) ego states now; vehicles: (E, M, 4) the cars' x, y, vx, vy now.
        after: how far past now decisions count [s] (0 for the verifier, whose paths bound the
            future themselves through :func:`entry_floor`; a period for the monitor).
    """
    a = assumptions
    lag = a.decision_lag
    window = max(lag, after)
    gap = vehicles[..., 0] - ego[:, EGO_X, None]  # (E, M) between centres
    car = torch.hypot(vehicles[..., 2], vehicles[..., 3])
    ego_speed = ego[:, EGO_V, None].clamp_min(0.0)
    # Farthest apart: back then the ego as far back and the car as far ahead as they may have been,
    # or later the car as far ahead and the ego as close to where it is as they may get.
    before = gap + ego_speed * lag + 0.5 * a.ego_acceleration * lag ** 2 - (car * lag - 0.5 * a.max_acceleration * lag ** 2).clamp_min(0.0)
    later = gap + car * after + 0.5 * a.max_acceleration * after ** 2 - _least_progress(ego_speed, a.ego_acceleration, after)
    widest = torch.maximum(before, later)
    ego_low = (ego_speed - a.ego_acceleration * window).clamp_min(0.0)
    ego_high = ego_speed + a.ego_acceleration * window
    car_high = car + max(a.max_deceleration, a.max_acceleration) * window
    # d* is convex in the ego's speed and falls as the car's rises: its least over the ranges
    root = 2 * math.sqrt(a.max_acceleration * a.comfort_deceleration)
    lowest_at = torch.minimum(torch.maximum(0.5 * (car_high - a.time_wanted * root), ego_low), ego_high)
    smallest = desired_gap(a, lowest_at, car_high).clamp_min(0.0)
    return (widest > 0) & (widest >= safe_distance(a, smallest, ego_low))


def entry_floor(path_x: torch.Tensor, path_speed: torch.Tensor, cars: torch.Tensor, times: torch.Tensor,
                assumptions: TrafficAssumptions, moving: bool = True, frame: Optional[float] = None) -> torch.Tensor:
    """The lowest x [m] of each car's footprint over each interval if it decides, on the ego's path,
    to enter the ego's lane ahead of it at any pose up to that interval (module docstring).

    Args:
        path_x, path_speed: (R, ..., P) the ego's x [m] and speed [m/s] at the poses ``times[:P]``.
        cars: (R, 4) each row's car now: x, y, vx, vy.
        times: (P + 1,) the intervals' bounds from now [s], ``times[0] = 0``, one frame apart (the
            frame-stepped car may lag the continuous least distance by ``a dt / 2`` per second).
        moving: count the car's progress after it decided (``False``: only that it never moves
            back, a lower floor at a twelfth of the work, enough for most paths).
        frame: the frame [s] (``times``' spacing); ``None``: read from ``times`` on the host.

    Returns:
        (R, ..., P): at interval i, the least ``x_low`` of the entering car's footprint.
    """
    a = assumptions
    middle = [1] * (path_x.dim() - 2)

    def per_car(t: torch.Tensor) -> torch.Tensor:  # (R, P, ...) -> (R, 1, ..., 1, P, ...)
        return t.reshape(t.shape[0], *middle, *t.shape[1:])

    dtype = path_x.dtype
    starts, ends = times[:-1].to(dtype), times[1:].to(dtype)  # (P,)
    steps = ends - starts
    frame = float(steps[0]) if frame is None else frame
    x, speed = cars[:, 0, None], torch.hypot(cars[:, 2], cars[:, 3])[:, None]  # (R, 1)
    # The car's speed w at pose j lies in [slow, fast]. On each slice [w_k, w_k+1] of that range its
    # centre is at least the least distance that ends at w_k from where it is now, and at least the
    # criterion's distance at w_k+1 ahead of the ego (d* falls as w rises).
    slow = (speed - a.max_deceleration * starts).clamp_min(0.0)
    fast = torch.minimum(speed + a.max_acceleration * starts, speed.clamp_min(a.speed_limit))
    w = slow[..., None] + (fast - slow)[..., None] * torch.linspace(0.0, 1.0, SPEED_POINTS, dtype=dtype)  # (R, P, S)
    # (less the frame-stepped car's lag and what turning across the road took from its progress)
    slope = math.tan(0.5 * a.max_heading) * a.lateral_speed  # [m/s] of progress a turn may take
    cap = math.tan(0.5 * a.max_heading) * a.lateral_travel
    stepping = 0.5 * a.max_acceleration * frame * starts[:, None] + (slope * starts).clamp_max(cap)[:, None]
    reached = x[..., None] + _least_distance_to(speed[..., None], w[..., :-1], starts[:, None], a) - stepping
    ego_speed = path_speed.clamp_min(0.0)[..., None]  # (R, ..., P, 1)
    ahead = path_x[..., None] + safe_distance(a, desired_gap(a, ego_speed, per_car(w[..., 1:])).clamp_min(0.0), ego_speed)
    centre = torch.maximum(ahead, per_car(reached))  # (R, ..., P, S - 1): deciding at pose j at speed >= w_k
    never_back = running_min(centre.amin(dim=-1), dim=-1)
    if not moving:
        return never_back - a.half_length
    # From then on it never moves back and brakes no harder than max_deceleration from w_k: at time t
    # at least max(w_k + b t_j - b t, 0), a profile fixed by w_k + b t_j. Rounded down to a grid of
    # such profiles, each grid profile's progress is a difference of one table (right sums), so the
    # least over the deciding poses is a running minimum.
    profile = w[..., :-1] + a.max_deceleration * starts[:, None]  # (R, P, S - 1)
    # Each car's own grid, spanning the profiles of the poses up to the ego's rest on every path (a
    # decision after that needs no progress: the ego stands), so that a check's verdict does not depend
    # on how many frames past that it runs (the frames are the batch's).
    ego_moves = path_speed.reshape(path_speed.shape[0], -1, path_speed.shape[-1]).gt(0).any(dim=1)  # (R, P)
    ego_moves[:, 0] = True
    spanned = profile.masked_fill(~ego_moves[..., None], torch.nan).flatten(1)
    low = spanned.nan_to_num(torch.inf).amin(dim=1)[:, None, None]  # (R, 1, 1)
    span = (spanned.nan_to_num(-torch.inf).amax(dim=1)[:, None, None] - low).clamp_min(1e-6)
    grid = low + span * torch.linspace(0.0, 1.0, PROFILES, dtype=dtype)[:, None]  # (R, G, 1)
    profile_speed = (grid - a.max_deceleration * ends).clamp_min(0.0)
    travel = profile_speed * steps
    table = torch.cumsum(travel, dim=-1) - travel  # (R, G, P): each profile's progress to each pose
    # Turning takes from the progress at most tan(max_heading / 2) x lateral_speed (slope) and
    # (1 - cos(max_heading)) of the speed per second: what is left at least
    kept = torch.maximum(profile_speed - slope, math.cos(a.max_heading) * profile_speed) * steps
    kept = torch.cumsum(kept, dim=-1) - kept  # (R, G, P)
    rounded = ((profile - low) / span * (PROFILES - 1)).floor().clamp(0, PROFILES - 1).long()  # grid value <= profile
    best = centre.new_full((*centre.shape[:-1], PROFILES), torch.inf)  # (R, ..., P, G): per profile, the least centre
    best.scatter_reduce_(-1, per_car(rounded).expand(centre.shape), centre, reduce="amin")
    # Within a turn's time (lateral_travel / lateral_speed) of deciding, the rate above bounds what
    # turning took; later the whole turn's loss (cap) or that rate, whichever leaves more. Per decision
    # the tighter, so the floor settles a turn's time after the cars and the ego stand (Verifier.frames
    # checks that far).
    progress, turned = per_car(table.transpose(1, 2)), per_car(kept.transpose(1, 2))  # (R, 1.., P, G)
    window = turn_frames(a, frame)
    turning = _window_min(best - turned, window, dim=-2).add_(turned)
    kept_older = running_min(best - turned, dim=-2).roll(window + 1, dims=-2).add_(turned)
    older = running_min(best.sub_(progress), dim=-2).roll(window + 1, dims=-2)
    capped = torch.maximum(older.add_(progress - cap), kept_older)  # both hold for every older decision
    capped[..., :window + 1, :] = torch.inf
    return torch.maximum(torch.minimum(turning, capped).amin(dim=-1), never_back) - a.half_length


#: Running minima of at most this many values take ``torch.cummin`` (:func:`running_min`; faster up
#: to ~8x10^4 values along the pose dimension on one CPU thread, slower above).
CUMMIN_MAX_VALUES = 32768


def turn_frames(assumptions: TrafficAssumptions, frame: float) -> int:
    """Frames of ``frame`` [s] a lane change's turn may take (``lateral_travel / lateral_speed``)."""
    return math.ceil(assumptions.lateral_travel / assumptions.lateral_speed / frame - 1e-9)


def _window_min(values: torch.Tensor, window: int, dim: int) -> torch.Tensor:
    """The minimum of ``values`` over each index and the ``window`` before it along ``dim``."""
    steps = values.movedim(dim, 0)
    least = steps.clone(memory_format=torch.contiguous_format)
    for shift in range(1, min(window, steps.shape[0] - 1) + 1):
        torch.minimum(least[shift:], steps[:-shift], out=least[shift:])
    return least.movedim(0, dim)


def running_min(values: torch.Tensor, dim: int) -> torch.Tensor:
    """The minimum of ``values`` up to each index along ``dim``: ``cummin`` for a small tensor (one
    call; a small check is bound by per-op overhead), else a loop of ``minimum`` along ``dim``
    (``cummin`` is many times slower along an inner dimension of a large one)."""
    if values.numel() <= CUMMIN_MAX_VALUES:
        return torch.cummin(values, dim).values
    steps = values.movedim(dim, 0).contiguous()
    for index in range(1, steps.shape[0]):
        torch.minimum(steps[index], steps[index - 1], out=steps[index])
    return steps.movedim(0, dim)


def _least_distance_to(speed: torch.Tensor, final: torch.Tensor, duration: torch.Tensor, a: TrafficAssumptions
                       ) -> torch.Tensor:
    """The least distance [m] a car at ``speed`` covers in ``duration`` [s] ending at ``final``
    [m/s] (reachable), braking at ``max_deceleration`` and speeding up at ``max_acceleration``:
    brake to ``u``, then speed up; to rest and wait where the time allows."""
    brake, accelerate = a.max_deceleration, a.max_acceleration
    turn = ((speed / brake + final / accelerate - duration) / (1 / brake + 1 / accelerate)).clamp_min(0.0)
    turn = torch.minimum(turn, torch.minimum(speed, final))
    return (speed ** 2 - turn ** 2) / (2 * brake) + (final ** 2 - turn ** 2) / (2 * accelerate)


def _least_progress(speed: torch.Tensor, slowing: float, duration: float) -> torch.Tensor:
    """Distance [m] covered over ``duration`` [s] from ``speed`` [m/s] slowing at ``slowing`` [m/s^2] to rest."""
    return torch.where(speed > slowing * duration, speed * duration - 0.5 * slowing * duration ** 2,
                       speed ** 2 / (2 * slowing))
