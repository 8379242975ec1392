"""Stopping for traffic ahead: stop goals for the goal set and the deceleration a fallback needs.

Every other goal lies a speed times the horizon ahead, so close behind stopped traffic none of
them is reachable. The stop goals below come to rest behind the nearest vehicle ahead in each
lane around the ego (or, with the lane clear, where a constant deceleration to rest over the
horizon ends), and :func:`conflict_deceleration` is the braking a fallback needs so that it never
drives into a vehicle ahead in its lane.
"""

from __future__ import annotations

import torch

from mmpc.problem import EGO_V, EGO_X, EGO_Y
from mmpc.road import Road

#: Closest a stop goal comes to the ego along the road [m] (a goal must lie ahead of the ego).
MIN_ADVANCE = 0.1


def first_conflict_x(
    corridor_y: torch.Tensor, start_x: torch.Tensor, obstacles: torch.Tensor, mask: torch.Tensor, half_width: float
) -> torch.Tensor:
    """Where each corridor first meets an obstacle ahead: the smallest predicted x of an obstacle
    sample that lies ahead of ``start_x`` and within ``half_width`` of the corridor laterally.

    Args:
        corridor_y: (E, C, N) lateral position of C corridors over the horizon [m] (a lane
            centre, or a planned path).
        start_x: (E,) the ego's x [m]; obstacles that start behind it are left out.
        obstacles: (E, M, N, 2) predicted obstacle centres [m].
        mask: (E, M) bool, present obstacles.
        half_width: lateral reach of an obstacle, the ellipse's semi-axis across the road [m].

    Returns:
        (E, C) x of the first conflict [m]; +inf where a corridor meets none.
    """
    x = obstacles[..., 0][:, None]  # (E, 1, M, N)
    y = obstacles[..., 1][:, None]
    ahead = (obstacles[:, :, 0, 0] > start_x[:, None]) & mask  # (E, M)
    in_corridor = (y - corridor_y[:, :, None, :]).abs() < half_width  # (E, C, M, N)
    hit = in_corridor & ahead[:, None, :, None]
    inf = torch.full((), float("inf"), dtype=x.dtype, device=x.device)
    conflicts = torch.where(hit, x, inf).flatten(2)  # (E, C, M N)
    none = inf.expand(*conflicts.shape[:2], 1)  # M = 0 (no obstacle slots): no conflict
    return torch.cat([conflicts, none], dim=2).amin(dim=2)


def stop_goals(
    ego: torch.Tensor,
    obstacles: torch.Tensor,
    mask: torch.Tensor,
    road: Road,
    *,
    horizon: float,
    ellipse: tuple[float, float],
    lanes: int,
    gap: float,
) -> torch.Tensor:
    """Goals that come to rest on the lane centres around the ego.

    In each lane of :meth:`mmpc.Road.lanes_around` the goal lies ``ellipse[0] + gap`` behind the
    first conflict with an obstacle ahead (:func:`first_conflict_x` along the lane centre), but
    no farther than ``v0 horizon / 2`` (where braking at a constant rate to rest over the
    horizon ends) and at least :data:`MIN_ADVANCE` ahead. The end speed is free, so a goal short
    of the stopping distance yields a plan that stops early; the optimizer's bounds decide
    whether that is feasible.

    Args:
        ego: (E, 6) ego states.
        obstacles: (E, M, N, 2) predicted obstacle centres [m].
        mask: (E, M) bool, present obstacles.
        road: the road.
        horizon: planning horizon t_f [s].
        ellipse: (a, b) obstacle ellipse semi-axes [m]; a may be an (E, 1) tensor, one per problem.
        lanes: lanes either side of the ego's lane that get a stop goal.
        gap: distance kept to the ellipse of the obstacle ahead [m].

    Returns:
        (E, L, 2) goals, L = min(2 lanes + 1, lane count).
    """
    lane_y = road.lanes_around(ego[:, EGO_Y], lanes).to(ego.dtype) * road.lane_width  # (E, L)
    steps = obstacles.shape[2]
    corridor = lane_y[..., None].expand(-1, -1, steps)
    conflict = first_conflict_x(corridor, ego[:, EGO_X], obstacles, mask, ellipse[1])
    advance = torch.minimum(conflict - ego[:, EGO_X, None] - ellipse[0] - gap, 0.5 * horizon * ego[:, EGO_V, None])
    x = ego[:, EGO_X, None] + advance.clamp_min(MIN_ADVANCE)
    return torch.stack([x, lane_y], dim=-1)


def conflict_deceleration(
    ego: torch.Tensor,
    obstacles: torch.Tensor,
    mask: torch.Tensor,
    times: torch.Tensor,
    *,
    half_width: float,
    standoff: float,
    max_deceleration: float,
) -> torch.Tensor:
    """(E,) the constant acceleration [m/s^2] (<= 0) that brings the ego down to the speed of
    every vehicle ahead in its lane before it comes within ``standoff`` of it (centre to centre).

    A vehicle counts when its predicted centre comes within ``half_width`` of the ego's lateral
    position at any sample: it is in, or enters, the ego's lane; its speed is its predicted one
    over the first sample. Already within ``standoff`` while still closing: ``-max_deceleration``.
    The room is measured to contact, not to the planner's ellipse, so a leader a little inside
    the ellipse and closing slowly asks for a little braking, not full braking.

    Args:
        ego: (E, 6) ego states.
        obstacles: (E, M, N, 2) predicted obstacle centres at ``times`` [m].
        mask: (E, M) bool, present obstacles.
        times: (N,) sample times [s].
        half_width: lateral reach of an obstacle [m] (e.g. half a lane width).
        standoff: centre distance along the road kept to the vehicle ahead [m] (a vehicle length
            plus a gap).
        max_deceleration: the strongest braking asked for [m/s^2].
    """
    x0, y0, v0 = ego[:, EGO_X, None], ego[:, EGO_Y, None], ego[:, EGO_V, None]
    dt = (times[1] - times[0]).to(obstacles.dtype)
    speed = (obstacles[:, :, 1, 0] - obstacles[:, :, 0, 0]) / dt  # (E, M)
    in_lane = ((obstacles[..., 1] - y0[..., None]).abs() < half_width).any(dim=-1)  # (E, M)
    relevant = mask & in_lane & (obstacles[:, :, 0, 0] > x0)
    closing = (v0 - speed).clamp_min(0.0)
    room = obstacles[:, :, 0, 0] - x0 - standoff
    needed = closing**2 / (2.0 * room.clamp_min(1e-3))
    needed = torch.where(room > 0, needed, torch.where(closing > 0, max_deceleration, 0.0))
    needed = torch.where(relevant, needed, torch.zeros_like(needed))
    needed = torch.cat([needed, torch.zeros_like(v0)], dim=1)  # no obstacle: no braking
    return -needed.amax(dim=1).clamp(max=max_deceleration)
