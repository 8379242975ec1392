"""Which part of the ego a collision struck, whose fault it was, and the scene around it.

The evaluation splits collisions into the ego's fault (its front or side struck another car)
and others' fault (a car behind ran into it): a car that drives into the ego's rear is to blame,
as on a real road; a car cutting in ahead or beside is not, because the ego decides how close
it passes a car that may turn (defensive driving). The struck part is read off the state at the
impact (the worlds' collision push taken back: :meth:`mmpc.highway.worlds.World.observe_impact`): the collider is the other vehicle nearest to the ego in units of the
footprint (``max(|along| / length, |across| / width)`` in the ego's frame), and the part is the
face of the ego's rectangle its centre lies beyond: the rear when it is behind the ego and more
behind than beside it, measured in those units, the front likewise ahead, else a side.

Pure Python over floats; no simulator import.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Optional, Sequence

#: The parts of the ego a collision can strike.
PARTS = ("front", "side", "rear")
#: Parts whose collisions are the ego's fault.
EGO_FAULT_PARTS = frozenset({"front", "side"})
#: An episode's crash scene (:func:`crash_scene` and the records before it), ``None`` without a collision:
#: ``crash_time`` [s]; the collider's ``crash_along`` / ``crash_across`` position in the ego's
#: frame [m], ``crash_other_heading_deg`` to the road, ``crash_other_speed`` and the ego's
#: ``crash_closing_speed`` on it [m/s]; the ego's ``crash_ego_offset`` from its lane centre [m] and
#: ``crash_ego_speed`` [m/s]; ``crash_fallback_steps``: the steps of the last second a fallback drove.
CRASH_COLUMNS = ("crash_time", "crash_along", "crash_across", "crash_other_heading_deg", "crash_other_speed",
                 "crash_closing_speed", "crash_ego_offset", "crash_ego_speed", "crash_fallback_steps")


def struck_part(
    ego: tuple[float, float, float],
    others: Sequence[tuple[float, float]],
    vehicle: tuple[float, float],
) -> Optional[str]:
    """The part of the ego that the nearest other vehicle touches.

    Args:
        ego: the ego's (x, y, heading psi) [m, m, rad] at the impact.
        others: the other vehicles' centres (x, y) [m].
        vehicle: every vehicle's (length, width) [m].

    Returns:
        ``"front"``, ``"side"`` or ``"rear"`` (see the module); ``None`` without other vehicles.

    Example:
        >>> struck_part((0.0, 0.0, 0.0), [(-4.8, 0.3), (30.0, 4.0)], (5.0, 2.0))
        'rear'
    """
    nearest = _nearest(ego, [(x, y, 0.0, 0.0) for x, y in others], vehicle)
    return None if nearest is None else _part(nearest[1], nearest[2], vehicle)


class Crash(NamedTuple):
    """The scene of a collision, read at the impact (:func:`crash_scene`).

    Fields:
        part: what the collider struck of the ego (``"front"``, ``"side"``, ``"rear"``).
        along, across: the collider's centre in the ego's frame: ahead, and toward +y (in
            highway-env's frame, where lane k's centre is at y = 4 k, to the right) [m].
        other_heading_deg: the collider's direction of motion relative to the road [deg]
            (+: toward +y); a car changing lanes is turned by 5-30 deg.
        other_speed: the collider's speed [m/s].
        closing_speed: how fast the ego was gaining on the collider along the road
            (ego vx - collider vx) [m/s].
        ego_offset: the ego's distance from its nearest lane centre, toward +y [m]; beyond 1 m
            it rides near a lane line.
        ego_speed: the ego's speed [m/s].
    """

    part: str
    along: float
    across: float
    other_heading_deg: float
    other_speed: float
    closing_speed: float
    ego_offset: float
    ego_speed: float


def crash_scene(
    ego: tuple[float, float, float, float],
    others: Sequence[tuple[float, float, float, float]],
    vehicle: tuple[float, float],
    lane_width: float,
) -> Optional[Crash]:
    """The scene of a collision: the collider (the other vehicle nearest in footprint units, as
    :func:`struck_part`), where it is and how it moves relative to the ego.

    Args:
        ego: the ego's (x, y, heading psi, speed v) [m, m, rad, m/s] at the impact.
        others: the other vehicles' (x, y, vx, vy) [m, m/s], road frame (lane k's centre at
            ``y = k * lane_width``).
        vehicle: every vehicle's (length, width) [m].
        lane_width: [m].

    Returns:
        A :class:`Crash`; ``None`` without other vehicles.

    Example:
        >>> crash = crash_scene((0.0, 5.2, 0.0, 20.0), [(4.0, 7.0, 8.0, 2.0)], (5.0, 2.0), 4.0)
        >>> crash.part, round(crash.other_heading_deg, 1), crash.closing_speed, round(crash.ego_offset, 1)
        ('side', 14.0, 12.0, 1.2)
    """
    if not lane_width > 0:
        raise ValueError(f"`lane_width` must be > 0 m; got {lane_width}")
    nearest = _nearest(ego[:3], others, vehicle)
    if nearest is None:
        return None
    index, along, across = nearest
    _, _, vx, vy = others[index]
    x, y, psi, v = ego
    return Crash(
        part=_part(along, across, vehicle),
        along=along,
        across=across,
        other_heading_deg=math.degrees(math.atan2(vy, vx)),
        other_speed=math.hypot(vx, vy),
        closing_speed=v * math.cos(psi) - vx,
        ego_offset=y - round(y / lane_width) * lane_width,
        ego_speed=v,
    )


def collider_index(ego: tuple[float, float, float], others: Sequence[Sequence[float]], vehicle: tuple[float, float]) -> Optional[int]:
    """Which of ``others`` (x, y, ...) :func:`crash_scene` takes for the collider of the ego at
    (x, y, psi): the nearest in footprint units; ``None`` without others."""
    nearest = _nearest(ego, others, vehicle)
    return None if nearest is None else nearest[0]


def _nearest(
    ego: tuple[float, float, float], others: Sequence[Sequence[float]], vehicle: tuple[float, float]
) -> Optional[tuple[int, float, float]]:
    """(index, along, across) of the other vehicle nearest to the ego in footprint units
    ``max(|along| / length, |across| / width)`` (ego frame); ``None`` without any."""
    length, width = vehicle
    if not (length > 0 and width > 0):
        raise ValueError(f"`vehicle` must be (length, width) > 0 m; got {vehicle}")
    x, y, psi = ego
    cos, sin = math.cos(psi), math.sin(psi)
    nearest: Optional[tuple[float, int, float, float]] = None  # (footprint distance, index, along, across)
    for index, other in enumerate(others):
        dx, dy = other[0] - x, other[1] - y
        along, across = cos * dx + sin * dy, -sin * dx + cos * dy
        distance = max(abs(along) / length, abs(across) / width)
        if nearest is None or distance < nearest[0]:
            nearest = (distance, index, along, across)
    return None if nearest is None else nearest[1:]


def _part(along: float, across: float, vehicle: tuple[float, float]) -> str:
    """The face of the ego's rectangle beyond which a centre at (along, across) lies (module docstring)."""
    length, width = vehicle
    if abs(along) / length <= abs(across) / width:
        return "side"
    return "front" if along > 0 else "rear"


def is_ego_fault(part: Optional[str]) -> bool:
    """A collision that struck ``part`` of the ego is the ego's fault (front or side)."""
    if part not in PARTS:
        raise ValueError(f"`part` must be one of {list(PARTS)}; got {part!r}")
    return part in EGO_FAULT_PARTS
