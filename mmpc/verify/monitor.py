"""The assumption monitor: did each car's actual motion stay inside the set predicted for it?

Every step it predicts, from the present observation, the set each car may cover until the next
step (:func:`mmpc.verify.occupancy`) and, at the next observation, checks each car's actual
footprint against it and its speed against the acceleration bounds. A car outside its set broke :class:`TrafficAssumptions`: no verification
holds against it, and a collision with it is not a defect of the verification.
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import torch

from mmpc.problem import EGO_X, EGO_Y
from mmpc.road import Road
from mmpc.verify.assumptions import TrafficAssumptions
from mmpc.verify.occupancy import Occupancy, body_reach, held_variant, occupancy


class Footprints(NamedTuple):
    """Axis-aligned bounds of the cars' actual footprints, (E, M) each [m] (heading from the velocity)."""

    x_low: torch.Tensor
    x_high: torch.Tensor
    y_low: torch.Tensor
    y_high: torch.Tensor


def footprints(vehicles: torch.Tensor, assumptions: TrafficAssumptions) -> Footprints:
    """The footprint bounds of (E, M, 4) cars (x, y [m], vx, vy [m/s]), bodies of the assumed size."""
    x, y, vx, vy = vehicles.unbind(dim=-1)
    along, across = body_reach(vx, vy, assumptions)
    return Footprints(x - along, x + along, y - across, y + across)


def outside(sets: Occupancy, interval: int, later: torch.Tensor, held: torch.Tensor, assumptions: TrafficAssumptions,
            tolerance: float = 1e-4) -> torch.Tensor:
    """(E, M) bool: a car's footprint in ``later`` (E, M, 4), at the end of interval ``interval``
    of ``sets``, is not inside that interval's box of the variant ``held`` (E,) long (which of
    the ego's lanes it held, :data:`mmpc.verify.occupancy.HELD_VARIANTS`)."""
    actual = footprints(later, assumptions)
    rows = torch.arange(held.shape[0], device=held.device)
    y_low, y_high = sets.y_low[rows, held, :, interval], sets.y_high[rows, held, :, interval]
    return ((actual.x_low < sets.x_low[..., interval] - tolerance) | (actual.x_high > sets.x_high[..., interval] + tolerance)
            | (actual.y_low < y_low - tolerance) | (actual.y_high > y_high + tolerance))


class AssumptionMonitor:
    """Finds, every step, the cars that left the set predicted for them one step before.

    Args:
        road: the road.
        period: time between two observations [s].
        assumptions: the assumptions checked.
        reach: only cars within this distance of the ego along the road, at both observations,
            are checked [m] (the batched world moves cars that drift out of its window to its
            other end: a new car in an old slot).

    Use: :meth:`observe` every step with the environments' ids and observation; it returns
    which cars broke the assumptions since the last observation of their environment.
    """

    def __init__(self, road: Road, period: float, assumptions: TrafficAssumptions = TrafficAssumptions(),
                 reach: float = 100.0) -> None:
        if not (period > 0 and reach > 0):
            raise ValueError(f"AssumptionMonitor: `period` and `reach` must be > 0; got {period!r}, {reach!r}")
        self.road, self.period, self.assumptions, self.reach = road, period, assumptions, reach
        self._last: Optional[tuple[torch.Tensor, Occupancy, torch.Tensor, torch.Tensor]] = None  # ids, sets, mask, speed

    def reset(self) -> None:
        self._last = None

    @torch.no_grad()
    def observe(self, ids: torch.Tensor, ego: torch.Tensor, vehicles: torch.Tensor, mask: Optional[torch.Tensor]) -> torch.Tensor:
        """(E, M) bool: the cars outside their set (footprint or speed) since the last observation
        of their environment (False at its first, or where its number of slots changed).

        Args:
            ids: (E,) long environment ids, stable over an episode (slots of ``vehicles`` name the same car).
            ego: (E, 6) ego states; vehicles (E, M, 4); mask (E, M) bool (``None``: all present).
        """
        mask = torch.ones(vehicles.shape[:2], dtype=torch.bool) if mask is None else mask
        mask = mask & ((vehicles[..., 0] - ego[:, None, EGO_X]).abs() <= self.reach)
        times = torch.tensor([0.0, self.period], dtype=vehicles.dtype)
        sets = occupancy(ego, vehicles, mask, self.road, times, self.assumptions, fault_rule=False,
                         decided_within=self.period)
        speed = torch.hypot(vehicles[..., 2], vehicles[..., 3])
        broke = torch.zeros_like(mask)
        last, self._last = self._last, (ids.clone(), sets, mask, speed)
        if last is None or last[1].x_low.shape[1] != vehicles.shape[1]:
            return broke
        last_ids, previous, previous_mask, previous_speed = last
        match = ids[:, None] == last_ids[None, :]
        seen = match.any(dim=1)
        rows = match.int().argmax(dim=1)
        previous = Occupancy(*(field[rows] for field in previous))
        a, tolerance = self.assumptions, 1e-3
        held = held_variant(previous.ego_lanes, ego[:, EGO_Y, None], self.road, a.lane_margin)
        previous_speed = previous_speed[rows]
        broke = outside(previous, 0, vehicles, held, a)
        broke |= speed < previous_speed - a.max_deceleration * self.period - tolerance
        broke |= speed > torch.minimum(previous_speed + a.max_acceleration * self.period,
                                       previous_speed.clamp_min(a.speed_limit)) + tolerance
        return broke & previous_mask[rows] & mask & seen[:, None]
