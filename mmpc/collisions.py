"""Which part of the ego a collision struck, and so whose fault it was.

The evaluation splits collisions into the ego's fault (its front or side struck another car)
and others' fault (a car behind ran into it). The struck part is read off the state right
after the collision: the collider is the other vehicle nearest to the ego in units of the
footprint (``max(|along| / length, |across| / width)`` in the ego's frame), and the part is the
face of the ego's rectangle its centre lies beyond: the rear when it is behind the ego and more
behind than beside it, measured in those units, the front likewise ahead, else a side.

Pure Python over floats; no simulator import.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence

#: The parts of the ego a collision can strike.
PARTS = ("front", "side", "rear")
#: Parts whose collisions are the ego's fault.
EGO_FAULT_PARTS = frozenset({"front", "side"})


def struck_part(
    ego: tuple[float, float, float],
    others: Sequence[tuple[float, float]],
    vehicle: tuple[float, float],
) -> Optional[str]:
    """The part of the ego that the nearest other vehicle touches.

    Args:
        ego: the ego's (x, y, heading psi) [m, m, rad] right after the collision.
        others: the other vehicles' centres (x, y) [m].
        vehicle: every vehicle's (length, width) [m].

    Returns:
        ``"front"``, ``"side"`` or ``"rear"`` (see the module); ``None`` without other vehicles.

    Example:
        >>> struck_part((0.0, 0.0, 0.0), [(-4.8, 0.3), (30.0, 4.0)], (5.0, 2.0))
        'rear'
    """
    length, width = vehicle
    if not (length > 0 and width > 0):
        raise ValueError(f"`vehicle` must be (length, width) > 0 m; got {vehicle}")
    x, y, psi = ego
    cos, sin = math.cos(psi), math.sin(psi)
    nearest: Optional[tuple[float, float, float]] = None  # (footprint distance, along, across)
    for other_x, other_y in others:
        dx, dy = other_x - x, other_y - y
        along, across = cos * dx + sin * dy, -sin * dx + cos * dy
        distance = max(abs(along) / length, abs(across) / width)
        if nearest is None or distance < nearest[0]:
            nearest = (distance, along, across)
    if nearest is None:
        return None
    _, along, across = nearest
    if abs(along) / length <= abs(across) / width:
        return "side"
    return "front" if along > 0 else "rear"


def is_ego_fault(part: Optional[str]) -> bool:
    """A collision that struck ``part`` of the ego is the ego's fault (front or side)."""
    if part not in PARTS:
        raise ValueError(f"`part` must be one of {list(PARTS)}; got {part!r}")
    return part in EGO_FAULT_PARTS
