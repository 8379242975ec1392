"""Does an obstacle ellipse cover two rectangular vehicles? (choosing ``ellipse_a`` / ``ellipse_b``)

The optimizer keeps the ego's centre outside an ellipse around each obstacle's centre,
``(dx / a)^2 + (dy / b)^2 >= 1`` in the road frame. A simulator that checks collisions between
rectangles (highway-env: 5 m x 2 m) reports a crash when the ego's centre enters the Minkowski
sum of the two rectangles, so the ellipse is safe when it contains that sum. The sum of two
convex polygons has its vertices among the sums of their vertices, and the ellipse is convex, so
checking the 16 corner sums is exact.
"""

from __future__ import annotations

import itertools
import math

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
