"""Whether oriented rectangles (the ego's footprint) meet axis-aligned boxes (occupancy sets)."""

from __future__ import annotations

import torch


def rectangle_meets_box(x: torch.Tensor, y: torch.Tensor, heading: torch.Tensor, half_length: torch.Tensor | float,
                        half_width: torch.Tensor | float,
                        x_low: torch.Tensor, x_high: torch.Tensor, y_low: torch.Tensor, y_high: torch.Tensor) -> torch.Tensor:
    """Bool, broadcast over every argument: the rectangle centred at (``x``, ``y``) [m], turned
    by ``heading`` [rad], of half sides ``half_length`` x ``half_width`` [m], overlaps the box
    ``[x_low, x_high] x [y_low, y_high]`` [m]. Separating axes: the box's two and the rectangle's
    two; touching counts as meeting."""
    cos, sin = torch.cos(heading), torch.sin(heading)
    abs_cos, abs_sin = cos.abs(), sin.abs()
    box_x, box_y = 0.5 * (x_low + x_high), 0.5 * (y_low + y_high)
    box_hx, box_hy = 0.5 * (x_high - x_low), 0.5 * (y_high - y_low)
    dx, dy = x - box_x, y - box_y
    apart = dx.abs() > box_hx + half_length * abs_cos + half_width * abs_sin
    apart |= dy.abs() > box_hy + half_length * abs_sin + half_width * abs_cos
    apart |= (dx * cos + dy * sin).abs() > half_length + box_hx * abs_cos + box_hy * abs_sin
    apart |= (dy * cos - dx * sin).abs() > half_width + box_hx * abs_sin + box_hy * abs_cos
    return ~apart
