"""The obstacle shape: ellipses that cover two rectangular vehicles, and the distance to them.

The optimizer keeps the ego's centre outside an ellipse around each obstacle's centre,
``(dx / a)^2 + (dy / b)^2 >= 1`` in the road frame. A simulator that checks collisions between
rectangles (highway-env: 5 m x 2 m) reports a crash when the ego's centre enters the Minkowski
sum of the two rectangles, so the ellipse is safe when it contains that sum. The sum of two
convex polygons has its vertices among the sums of their vertices, and the ellipse is convex, so
checking the 16 corner sums is exact.

A car that turns (changing lanes, 5-30 deg off the road) sticks out of an ellipse sized for cars
along the road: :func:`covering_semi_axes` widens each obstacle's ellipse across the road for its
heading, keeping the margin the configured one has beyond what it must cover. Widening keeps
the ellipse aligned with the road, so the optimizer's iterations keep their cost (a turned
ellipse would rotate every offset and push); :func:`ellipse_distance_squared` is the one
normalised distance every reader of the shape uses.
"""

from __future__ import annotations

import itertools
import math
from typing import Union

import torch

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
    return max(((x1 + x2) / a) ** 2 + ((y1 + y2) / b) ** 2
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
