"""Which other cars may change lanes next: MOBIL's incentive as the ego can estimate it.

highway-env's traffic (and :mod:`mmpc.sim`'s) changes lanes by MOBIL: a car moves one lane over
when its IDM acceleration there beats the one behind its current leader by a threshold, and its
new follower need not brake too hard. The ego sees positions and velocities, not the cars'
target speeds, so the estimate takes each car's target speed as its current speed (the IDM's
free-road term then cancels out of the gain) and reads the gap terms from the observed cars.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from mmpc.config import require_field_types, require_non_negative, require_positive
from mmpc.road import Road


@dataclass(frozen=True)
class DriverModel:
    """The other drivers' IDM and MOBIL as the ego assumes them (highway-env's ``IDMVehicle``).

    Attributes:
        comfort_acc_max: IDM's acceleration scale of the gap term [m/s^2].
        comfort_acc_min: IDM's comfortable deceleration [m/s^2] (negative).
        distance_wanted: IDM's jam distance, centre to centre [m].
        time_wanted: IDM's desired time headway [s].
        min_gain: MOBIL changes lanes for an acceleration gain of at least this [m/s^2] (a
            lower or negative value also flags the cars that are approaching the threshold).
        max_braking_imposed: MOBIL refuses a change that makes the new follower brake harder
            than this [m/s^2] (positive).
        lane_margin: a car counts on a lane within half a lane width and this of its centre
            (one astride a lane line counts on both) [m].
    """

    comfort_acc_max: float = 3.0
    comfort_acc_min: float = -5.0
    distance_wanted: float = 10.0
    time_wanted: float = 1.5
    min_gain: float = 0.2
    max_braking_imposed: float = 2.0
    lane_margin: float = 1.0

    def __post_init__(self) -> None:
        require_field_types(self)
        require_positive("DriverModel", comfort_acc_max=self.comfort_acc_max, distance_wanted=self.distance_wanted,
                         time_wanted=self.time_wanted, max_braking_imposed=self.max_braking_imposed,
                         comfort_deceleration=-self.comfort_acc_min)
        require_non_negative("DriverModel", lane_margin=self.lane_margin)

    def gap_term(self, speed: torch.Tensor, leader_speed: torch.Tensor, gap: torch.Tensor) -> torch.Tensor:
        """IDM's interaction term [m/s^2] (>= 0, subtracted from the free-road term) of a car at
        ``speed`` a centre-to-centre ``gap`` [m] behind a leader at ``leader_speed`` [m/s]."""
        ab = -self.comfort_acc_max * self.comfort_acc_min
        desired = self.distance_wanted + speed * self.time_wanted + speed * (speed - leader_speed) / (2 * ab ** 0.5)
        return self.comfort_acc_max * (desired / gap.clamp_min(1e-2)) ** 2


def mobil_lane_changes(
    cars: torch.Tensor,
    traffic: torch.Tensor,
    traffic_mask: torch.Tensor,
    ego: torch.Tensor,
    road: Road,
    model: DriverModel = DriverModel(),
) -> torch.Tensor:
    """(E, M) int64: the lane change MOBIL (politeness 0) picks for each car now: -1 one lane to
    the left (lower index), +1 to the right, 0 none; asked both, MOBIL's right wins.

    Each car's lane is the one whose centre is nearest; its leaders and its new follower are the
    nearest cars ahead and behind on those lanes, of ``traffic`` and the ego (a car counts on a
    lane within :attr:`DriverModel.lane_margin` of it; a car of ``cars`` found in ``traffic``
    at the same position is itself). The traffic's target speeds, unseen, cancel out of the
    gain, and a new follower is taken at its target speed; the ego, which has none, is a
    follower no car cuts in ahead of (highway-env reads its target speed as 0). A car slower
    than 1 m/s does not change lanes.

    Args:
        cars: (E, M, 4) the cars asked about (x [m], y [m], vx [m/s], vy [m/s]), road frame.
        traffic: (E, V, 4) every car seen (the ego excluded), the same frame.
        traffic_mask: (E, V) bool, False for empty rows.
        ego: (E, 3) the ego's x [m], y [m] and speed along the road [m/s].
        road: the lanes.
        model: the drivers' IDM and MOBIL.

    Example:
        >>> import torch
        >>> from mmpc.road import Road
        >>> traffic = torch.tensor([[[0.0, 8.0, 10.0, 0.0], [20.0, 8.0, 8.0, 0.0]]])  # lane 2, slower leader
        >>> seen = torch.ones(1, 2, dtype=torch.bool)
        >>> mobil_lane_changes(traffic[:, :1], traffic, seen, torch.tensor([[-200.0, 8.0, 20.0]]), Road()).tolist()
        [[1]]
        >>> mobil_lane_changes(traffic[:, :1], traffic, seen, torch.tensor([[-5.0, 12.0, 20.0]]), Road()).tolist()
        [[-1]]
    """
    environments = cars.shape[0] if cars.dim() == 3 else -1
    shapes_fit = (cars.dim() == 3 and cars.shape[-1] == 4 and traffic.dim() == 3 and traffic.shape[-1] == 4
                  and traffic.shape[0] == environments and tuple(traffic_mask.shape) == tuple(traffic.shape[:2])
                  and traffic_mask.dtype == torch.bool and ego.dim() == 2 and ego.shape[0] == environments
                  and ego.shape[1] >= 3)
    if not shapes_fit:
        raise ValueError(
            "expected cars (E, M, 4), traffic (E, V, 4), traffic_mask (E, V) bool and ego (E, 3); got "
            f"{tuple(cars.shape)}, {tuple(traffic.shape)}, {tuple(traffic_mask.shape)} {traffic_mask.dtype}, {tuple(ego.shape)}")
    width = road.lane_width
    ego_row = torch.cat([ego[:, :3], torch.zeros_like(ego[:, :1])], dim=-1)[:, None]  # (E, 1, 4)
    everyone = torch.cat([ego_row, traffic.to(cars.dtype)], dim=1)  # (E, 1 + V, 4), the ego first
    present = torch.cat([traffic_mask.new_ones(traffic_mask.shape[0], 1), traffic_mask], dim=1)[:, None, :]
    lane = torch.round(cars[..., 1] / width)  # (E, M)
    ahead = everyone[:, None, :, 0] - cars[..., 0, None]  # (E, M, 1 + V)
    itself = (ahead.abs() < 1e-3) & ((everyone[:, None, :, 1] - cars[..., 1, None]).abs() < 1e-3)
    present = present & ~itself
    speed = cars[..., 2]
    other_speed = everyone[:, None, :, 2].expand_as(ahead)

    def nearest(on_lane: torch.Tensor, front: bool):
        """(found, gap [m], speed [m/s], is the ego) of the nearest car ahead (or behind) on ``on_lane`` (E, M)."""
        side = ahead >= 0 if front else ahead < 0
        on = (everyone[:, None, :, 1] - on_lane[..., None] * width).abs() <= 0.5 * width + model.lane_margin
        gap = torch.where(present & side & on, ahead.abs(), torch.full_like(ahead, float("inf")))
        gap, index = gap.min(dim=-1)
        found = torch.isfinite(gap)
        found_speed = torch.gather(other_speed, -1, index[..., None])[..., 0]
        return found, torch.where(found, gap, torch.ones_like(gap)), found_speed, found & (index == 0)  # the ego is row 0

    def behind(found, gap, leader_speed):  # IDM's gap term behind the leader found, 0 without one
        return torch.where(found, model.gap_term(speed, leader_speed, gap), torch.zeros_like(speed))

    stay = behind(*nearest(lane, front=True)[:3])

    def accepts(side: int) -> torch.Tensor:
        target = lane + side
        gain = stay - behind(*nearest(target, front=True)[:3])
        follower, follower_gap, follower_speed, follower_is_ego = nearest(target, front=False)
        imposed = torch.where(follower, model.gap_term(follower_speed, speed, follower_gap), torch.zeros_like(speed))
        safe = ~follower_is_ego & (imposed <= model.max_braking_imposed)
        on_road = (target >= 0) & (target <= road.num_lanes - 1)
        return on_road & safe & (gain >= model.min_gain)

    moving = speed.abs() >= 1.0
    right, left = accepts(+1) & moving, accepts(-1) & moving
    return torch.where(right, 1, torch.where(left, -1, 0)).to(torch.int64)
