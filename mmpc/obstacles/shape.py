"""The obstacle shape: ellipses that cover two rectangular vehicles, the distance to them, and
the obstacles a plan is made around.

The optimizer keeps the ego's centre outside an ellipse around each obstacle's centre,
``(dx / a)^2 + (dy / b)^2 >= 1`` in the road frame. A simulator that checks collisions between
rectangles (highway-env: 5 m x 2 m) reports a crash when the ego's centre enters the Minkowski
sum of the two rectangles, so the ellipse is safe when it contains that sum. The sum of two
convex polygons has its vertices among the sums of their vertices, and the ellipse is convex, so
checking the 16 corner sums is exact.

A car that turns (changing lanes, 5-30 deg off the road) sticks out of an ellipse sized for cars
along the road: :func:`covering_semi_axes` widens each obstacle's ellipse across the road for its
heading, keeping the margin the configured one has beyond what it must cover
(:func:`obstacle_semi_axes`, by :data:`OBSTACLE_SHAPES` name). Widening keeps the ellipse
aligned with the road, so the optimizer's iterations keep their cost (a turned ellipse would
rotate every offset and push).

Every reader of the shape measures with this module: :func:`ellipse_distance_squared` (tensors)
and :func:`offset_distance_squared` / :func:`offset_distance` (one offset in Python floats) are
the normalised distance, :func:`squared_obstacle_distance` the distance of candidate
trajectories to predicted obstacles, :func:`smallest_distance` the clearance (the smallest
distance over obstacles and samples), and :func:`nearest_obstacles` the vehicles a plan is made
around. The optimizer's iterations keep their own copy of the distance (:mod:`mmpc.solver.iterations`).
"""

from __future__ import annotations

import itertools
import math
from typing import Optional, Union

import torch

from mmpc.problem import EGO_PSI, EGO_V, EGO_X, EGO_Y
from mmpc.result import Trajectories

#: highway-env's vehicle footprint, length x width [m].
HIGHWAY_VEHICLE = (5.0, 2.0)


def _corners(length: float, width: float, heading_deg: float) -> list[tuple[float, float]]:
    """The 4 corners of a length x width rectangle centred at the origin, turned by ``heading_deg``."""
    c, s = math.cos(math.radians(heading_deg)), math.sin(math.radians(heading_deg))
    return [(u * length / 2 * c - v * width / 2 * s, u * length / 2 * s + v * width / 2 * c)
            for u in (-1, 1) for v in (-1, 1)]


def ellipse_coverage(
    semi_axes: tuple[float, float],
    ego_heading_deg: float,
    other_heading_deg: float = 0.0,
    vehicle: tuple[float, float] = HIGHWAY_VEHICLE,
) -> float:
    """Largest ``(dx / a)^2 + (dy / b)^2`` over the Minkowski sum of two vehicle rectangles.

    Args:
        semi_axes: the obstacle ellipse (a along the road, b across) [m].
        ego_heading_deg: the ego's heading relative to the road [deg].
        other_heading_deg: the other vehicle's heading relative to the road [deg].
        vehicle: both vehicles' (length, width) [m].

    Returns:
        At most 1 when the ellipse covers every relative position at which the rectangles touch;
        above 1 when some such position lies outside it (a collision the optimizer cannot see).

    Example:
        >>> round(ellipse_coverage((8.0, 3.3), 13.0, 3.0), 2)
        0.99
    """
    a, b = semi_axes
    if not (a > 0 and b > 0):
        raise ValueError(f"`semi_axes` must be two lengths > 0 m; got {semi_axes}")
    length, width = vehicle
    return max(offset_distance_squared(x1 + x2, y1 + y2, semi_axes)
               for (x1, y1), (x2, y2) in itertools.product(_corners(length, width, ego_heading_deg),
                                                           _corners(length, width, other_heading_deg)))


def smallest_covering_axis(
    semi_axis: float,
    given: str,
    ego_headings_deg: tuple[float, ...],
    vehicle: tuple[float, float] = HIGHWAY_VEHICLE,
) -> float:
    """The smallest other semi-axis that makes the ellipse cover two vehicles at every heading.

    With ``given="a"``, the smallest b such that ``ellipse_coverage((a, b), h, 0, vehicle) <= 1``
    for every ego heading ``h`` in ``ego_headings_deg`` (the other vehicle along the road); with
    ``given="b"``, the smallest a for the given b. Per corner (x, y) of the Minkowski sum,
    ``(x / a)^2 + (y / b)^2 <= 1`` gives ``b >= |y| / sqrt(1 - (x / a)^2)``.

    Args:
        semi_axis: the given semi-axis [m].
        given: ``"a"`` (along the road) or ``"b"`` (across).
        ego_headings_deg: the ego's headings relative to the road [deg].
        vehicle: both vehicles' (length, width) [m].

    Returns:
        The other semi-axis [m]; ``inf`` when none covers (the given one is too short).

    Example:
        >>> round(smallest_covering_axis(8.0, "a", (-13.0, 13.0)), 2)
        3.14
    """
    if given not in ("a", "b"):
        raise ValueError(f"`given` must be 'a' or 'b'; got {given!r}")
    if not semi_axis > 0:
        raise ValueError(f"`semi_axis` must be a length > 0 m; got {semi_axis}")
    length, width = vehicle
    needed = 0.0
    for heading in ego_headings_deg:
        for (x1, y1), (x2, y2) in itertools.product(_corners(length, width, heading), _corners(length, width, 0.0)):
            along, across = abs(x1 + x2), abs(y1 + y2)
            known, other = (along, across) if given == "a" else (across, along)
            if known >= semi_axis:
                return math.inf
            needed = max(needed, other / math.sqrt(1.0 - (known / semi_axis) ** 2))
    return needed


def covering_semi_axes(
    headings: torch.Tensor,
    semi_axes: tuple[float, float],
    ego_band_deg: float,
    vehicle: tuple[float, float] = HIGHWAY_VEHICLE,
) -> torch.Tensor:
    """Per-obstacle ellipse semi-axes that cover each car at its heading.

    The across-road semi-axis of each obstacle is ``semi_axes[1]`` plus what covering the
    Minkowski sum of the two rectangles (the ego at any heading within ``ego_band_deg``, the
    obstacle at its heading) needs beyond what it needs for an obstacle along the road
    (:func:`smallest_covering_axis`); the along-road semi-axis stays ``semi_axes[0]``. At
    heading 0 the result is ``semi_axes`` exactly.

    Args:
        headings: (...,) obstacles' directions of motion relative to the road [rad]; their
            magnitude is capped at 45 deg.
        semi_axes: the configured ellipse (a, b) [m].
        ego_band_deg: the ego's largest heading relative to the road [deg] (the optimizer's
            heading band).
        vehicle: both vehicles' (length, width) [m].

    Returns:
        (..., 2) semi-axes (a, b) [m], in ``headings``' dtype and device.

    Example:
        >>> import torch
        >>> covering_semi_axes(torch.tensor([0.0, 0.26]), (8.0, 3.3), 13.0).round(decimals=2)
        tensor([[8.0000, 3.3000],
                [8.0000, 3.9200]])
    """
    a, b = semi_axes
    if not (a > 0 and b > 0):
        raise ValueError(f"`semi_axes` must be two lengths > 0 m; got {semi_axes}")
    length, width = vehicle
    ego = [corner for heading in (-ego_band_deg, ego_band_deg) for corner in _corners(length, width, heading)]
    ego_x = headings.new_tensor([x for x, _ in ego])  # (8,)
    ego_y = headings.new_tensor([y for _, y in ego])
    theta = headings.clamp(-math.pi / 4, math.pi / 4)[..., None]  # (..., 1)
    u = headings.new_tensor([-1.0, -1.0, 1.0, 1.0]) * (length / 2)  # the obstacle's 4 corners in its frame
    v = headings.new_tensor([-1.0, 1.0, -1.0, 1.0]) * (width / 2)
    cos, sin = torch.cos(theta), torch.sin(theta)
    other_x, other_y = u * cos - v * sin, u * sin + v * cos  # (..., 4)
    sum_x = (other_x[..., :, None] + ego_x).flatten(-2)  # (..., 32)
    sum_y = (other_y[..., :, None] + ego_y).flatten(-2)
    needed = (sum_y.abs() / (1.0 - (sum_x / a) ** 2).clamp_min(1e-4).sqrt()).amax(dim=-1)
    along_road = smallest_covering_axis(a, "a", (-ego_band_deg, ego_band_deg), vehicle)
    across = b + (needed - along_road).clamp_min(0.0)
    return torch.stack([torch.full_like(across, a), across], dim=-1)


#: Obstacle shapes by :attr:`mmpc.MPCConfig.obstacle_shape` name: ``"fixed"`` (the optimizer's
#: ellipse for every car) or ``"heading"`` (:func:`covering_semi_axes` at each car's direction of motion).
OBSTACLE_SHAPES = ("fixed", "heading")


def obstacle_semi_axes(
    states: torch.Tensor,
    shape: str,
    semi_axes: tuple[float, float],
    ego_band_deg: float,
    vehicle: tuple[float, float] = HIGHWAY_VEHICLE,
) -> Optional[torch.Tensor]:
    """Each obstacle's ellipse by :data:`OBSTACLE_SHAPES` name.

    Args:
        states: (E, M, 4) obstacles (x, y, vx, vy) [m, m/s].
        shape: ``"fixed"`` or ``"heading"``.
        semi_axes: the configured ellipse (a, b) [m].
        ego_band_deg: the ego's largest heading relative to the road [deg].
        vehicle: both vehicles' (length, width) [m].

    Returns:
        (E, M, 2) semi-axes [m] (:func:`covering_semi_axes` at each car's direction of motion,
        heading 0 below 1 m/s); ``None`` for ``"fixed"`` (every obstacle has ``semi_axes``).
    """
    if shape not in OBSTACLE_SHAPES:
        raise ValueError(f"`shape` must be one of {list(OBSTACLE_SHAPES)}; got {shape!r}")
    if shape == "fixed":
        return None
    # Below 1 m/s the direction of motion says little about where the car points.
    moving = torch.hypot(states[..., 2], states[..., 3]) >= 1.0
    heading = torch.where(moving, torch.atan2(states[..., 3], states[..., 2]), torch.zeros_like(states[..., 2]))
    return covering_semi_axes(heading, semi_axes, ego_band_deg, vehicle)


def longest_semi_axes(
    axes: Optional[torch.Tensor], mask: torch.Tensor, semi_axes: tuple[float, float]
) -> tuple[float, float] | tuple[torch.Tensor, float]:
    """The ellipse a stop goal rests behind: ``semi_axes`` with ``a`` the longest of the present
    obstacles' (at least ``semi_axes[0]``).

    Args:
        axes: (E, M, 2) per-obstacle semi-axes (:func:`obstacle_semi_axes`) or ``None`` (all ``semi_axes``).
        mask: (E, M) bool, present obstacles.
        semi_axes: the configured ellipse (a, b) [m].

    Returns:
        ``semi_axes`` itself, or (a (E, 1) [m], b [m]) where per-obstacle axes are given.
    """
    if axes is None or axes.shape[1] == 0:
        return semi_axes
    longest = torch.where(mask, axes[..., 0], torch.full_like(axes[..., 0], semi_axes[0]))
    return longest.amax(dim=1, keepdim=True).clamp_min(semi_axes[0]), semi_axes[1]


def offset_distance_squared(dx: float, dy: float, semi_axes: tuple[float, float]) -> float:
    """``(dx / a)^2 + (dy / b)^2`` of one offset (dx, dy) [m] from an ellipse's centre, in
    Python floats (< 1: inside the ellipse; :func:`ellipse_distance_squared` on tensors).

    Example:
        >>> offset_distance_squared(4.0, 3.0, (8.0, 3.0))
        1.25
    """
    a, b = semi_axes
    return (dx / a) ** 2 + (dy / b) ** 2


def offset_distance(dx: float, dy: float, semi_axes: tuple[float, float]) -> float:
    """``hypot(dx / a, dy / b)``, the normalised distance of one offset (dx, dy) [m] from an
    ellipse's centre, in Python floats (< 1: inside the ellipse).

    Example:
        >>> offset_distance(0.0, 6.0, (8.0, 3.0))
        2.0
    """
    a, b = semi_axes
    return math.hypot(dx / a, dy / b)


def ellipse_distance_squared(
    points: torch.Tensor, centres: torch.Tensor, semi_axes: Union[tuple[float, float], torch.Tensor]
) -> torch.Tensor:
    """``(dx / a)^2 + (dy / b)^2`` of points to ellipse centres (< 1: inside the ellipse).

    Args:
        points: (..., 2) positions (x, y) [m].
        centres: (..., 2) ellipse centres [m], broadcast against ``points``.
        semi_axes: (a, b) [m], or a (..., 2) tensor of them broadcast against both.

    Returns:
        (...) the squared normalised distances.

    Example:
        >>> import torch
        >>> float(ellipse_distance_squared(torch.tensor([4.0, 3.0]), torch.zeros(2), (8.0, 3.0)))
        1.25
    """
    scale = semi_axes if isinstance(semi_axes, torch.Tensor) else points.new_tensor(semi_axes)
    offset = (points - centres) / scale
    return (offset * offset).sum(dim=-1)


def squared_obstacle_distance(
    trajectories: Trajectories, obstacles: torch.Tensor, semi_axes: Union[tuple[float, float], torch.Tensor]
) -> torch.Tensor:
    """(E, C, M, N) squared normalised distance ``(dx / a)^2 + (dy / b)^2`` of every
    candidate's samples to every obstacle slot (< 1: inside its ellipse; :func:`ellipse_distance_squared`).

    Args:
        trajectories: the candidates, fields (E, C, N).
        obstacles: (E, M, N, 2) predicted centres at the same instants [m].
        semi_axes: (a, b) [m], or (E, M, 2) per obstacle (:attr:`mmpc.ProblemBatch.obstacle_axes`).
    """
    points = torch.stack([trajectories.x, trajectories.y], dim=-1)[:, :, None]  # (E, C, 1, N, 2)
    if isinstance(semi_axes, torch.Tensor):
        semi_axes = semi_axes[:, None, :, None, :]  # (E, 1, M, 1, 2)
    return ellipse_distance_squared(points, obstacles[:, None], semi_axes)


def smallest_distance(
    squared: torch.Tensor, present: Optional[torch.Tensor], dim: int | tuple[int, ...]
) -> torch.Tensor:
    """The clearance: the smallest normalised distance ``sqrt((dx / a)^2 + (dy / b)^2)`` over
    the dimensions ``dim`` of ``squared`` (obstacles, samples), counting only ``present`` entries.

    Args:
        squared: (...) squared normalised distances (:func:`ellipse_distance_squared`).
        present: bool, broadcast against ``squared``: the entries that count; ``None``: all.
        dim: the dimension(s) reduced.

    Returns:
        ``squared`` without the dimensions ``dim``: the smallest distance, +inf where no entry
        counts (or ``dim`` is empty).

    Example:
        >>> import torch
        >>> squared = torch.tensor([[4.0, 0.25], [9.0, 1.0]])
        >>> smallest_distance(squared, torch.tensor([[True, False], [True, True]]), 1)
        tensor([2., 1.])
    """
    dims = {d % squared.ndim for d in ((dim,) if isinstance(dim, int) else dim)}
    if present is not None:
        squared = squared.masked_fill(~present, float("inf"))
    if any(squared.shape[d] == 0 for d in dims):
        return squared.new_full([size for d, size in enumerate(squared.shape) if d not in dims], float("inf"))
    return squared.amin(dim=tuple(sorted(dims))).sqrt()


def nearest_obstacles(
    ego: torch.Tensor,
    vehicles: torch.Tensor,
    vehicle_mask: Optional[torch.Tensor],
    count: int,
    ellipse: tuple[float, float],
    ignore_behind: float,
    lookahead: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``count`` vehicles that come nearest to the ego within ``lookahead`` seconds, in
    ellipse-normalised distance, both moving at their current velocity.

    With ``lookahead`` 0 this is the distance now, which ranks a car 45 m ahead in the ego's
    lane (5.6 at a = 8 m) behind one alongside two lanes over (2.7 at b = 3 m) however fast
    the ego closes on it; the closest approach within a few seconds ranks it first.

    Args:
        ego: (E, 6) ego states.
        vehicles: (E, V, 4) other vehicles (x, y, vx, vy) [m, m/s].
        vehicle_mask: (E, V) bool, True for real vehicles; ``None`` = all real.
        count: M slots to fill.
        ellipse: (a, b) semi-axes [m] defining the distance.
        ignore_behind: vehicles with x < ego x - ignore_behind are left out [m].
        lookahead: window of the closest approach [s], >= 0.

    Returns:
        states (E, M, 4) and mask (E, M), nearest first; unused slots have mask False.
    """
    num_problems, num_vehicles = vehicles.shape[:2]
    if vehicle_mask is None:
        vehicle_mask = torch.ones(num_problems, num_vehicles, dtype=torch.bool, device=vehicles.device)
    scale = vehicles.new_tensor(ellipse)
    offset = (vehicles[..., :2] - ego[:, None, EGO_X:EGO_Y + 1]) / scale  # (E, V, 2)
    ego_velocity = ego[:, EGO_V, None] * torch.stack([torch.cos(ego[:, EGO_PSI]), torch.sin(ego[:, EGO_PSI])], dim=-1)
    closing = (vehicles[..., 2:4] - ego_velocity[:, None]) / scale  # (E, V, 2) normalised relative velocity
    # closest approach of offset + t closing over t in [0, lookahead]
    speed_sq = (closing * closing).sum(dim=-1).clamp_min(1e-12)
    when = (-(offset * closing).sum(dim=-1) / speed_sq).clamp(0.0, lookahead)
    distance = torch.linalg.vector_norm(offset + when[..., None] * closing, dim=-1)
    eligible = vehicle_mask & (vehicles[..., 0] >= ego[:, None, EGO_X] - ignore_behind)
    distance = torch.where(eligible, distance, torch.full_like(distance, float("inf")))
    k = min(count, num_vehicles)
    order = distance.argsort(dim=1)[:, :k]
    states = torch.gather(vehicles, 1, order[..., None].expand(-1, -1, 4))
    mask = torch.gather(eligible, 1, order)
    if k < count:
        pad = count - k
        states = torch.cat([states, states.new_zeros(num_problems, pad, 4)], dim=1)
        mask = torch.cat([mask, mask.new_zeros(num_problems, pad)], dim=1)
    return states, mask
