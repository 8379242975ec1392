"""Straight multi-lane road geometry in the road-aligned frame (highway-env's convention)."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class Road:
    """Straight road with parallel lanes; lane k's centre is at ``y = k * lane_width``.

    Lane 0 is the leftmost; the *right* lane has the highest index (highway-env's layout).

    Attributes:
        num_lanes: number of lanes.
        lane_width: lane width [m].
    """

    num_lanes: int = 6
    lane_width: float = 4.0

    def __post_init__(self) -> None:
        if not isinstance(self.num_lanes, int) or self.num_lanes < 1:
            raise ValueError(f"`num_lanes` must be a positive int; got {self.num_lanes!r}")
        if not self.lane_width > 0:
            raise ValueError(f"`lane_width` must be > 0 m; got {self.lane_width}")

    @property
    def right_lane_y(self) -> float:
        """Lateral position of the right lane's centre [m]."""
        return (self.num_lanes - 1) * self.lane_width

    @property
    def bounds(self) -> tuple[float, float]:
        """Lateral extent (left edge, right edge) of the road surface [m]."""
        return -0.5 * self.lane_width, self.right_lane_y + 0.5 * self.lane_width

    def lane_centers(self, *, dtype: torch.dtype = torch.float32, device=None) -> torch.Tensor:
        """(num_lanes,) lane-centre y positions [m]."""
        return torch.arange(self.num_lanes, dtype=dtype, device=device) * self.lane_width

    def lane_index(self, y: torch.Tensor) -> torch.Tensor:
        """Index of the nearest lane for lateral positions ``y`` [m] (same shape, int64)."""
        index = torch.round(y / self.lane_width).to(torch.int64)
        return index.clamp(0, self.num_lanes - 1)

    def lanes_around(self, y: torch.Tensor, count: int) -> torch.Tensor:
        """(E, min(2 count + 1, num_lanes)) lane indices around lateral positions ``y`` (E,) [m]:
        the nearest lane and ``count`` either side, the window shifted to stay on the road (on an
        edge lane: the edge lane and the next ``2 count`` inwards, so no lane repeats)."""
        width = min(2 * count + 1, self.num_lanes)
        first = (self.lane_index(y) - count).clamp(0, self.num_lanes - width)
        return first[:, None] + torch.arange(width, device=y.device)
