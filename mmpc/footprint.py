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
