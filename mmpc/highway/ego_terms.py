"""What a task reward reads of the egos of a :class:`mmpc.highway.worlds.World`."""

from __future__ import annotations

from typing import NamedTuple

import torch


class EgoTerms(NamedTuple):
    """What a task reward reads of R egos: (R,) float64 each, on the world's device.

    Fields:
        speed: [m/s]; forward_speed: ``speed cos(heading)`` [m/s]; y: lateral position [m];
        lane: the lane's index (0 leftmost); crashed, on_road: 0 or 1.
    """

    speed: torch.Tensor
    forward_speed: torch.Tensor
    y: torch.Tensor
    lane: torch.Tensor
    crashed: torch.Tensor
    on_road: torch.Tensor
