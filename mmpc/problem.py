"""Problem batches: ego states, obstacle predictions and goals, in the road-aligned frame.

Frame: x along the road [m], y across it [m] (highway-env's convention: lane k's centre at
y = 4 k, so +y points to the right-hand lanes), heading psi [rad] from the +x axis.

A batch holds E problems (one per environment or scene), each with G goals and M obstacle
slots; the optimizer solves all E x G (problem, goal) elements at once.
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import torch

#: Layout of the last axis of an ego-state tensor.
EGO_FIELDS = ("x", "y", "psi", "v", "a", "psidot")
EGO_X, EGO_Y, EGO_PSI, EGO_V, EGO_A, EGO_PSIDOT = range(len(EGO_FIELDS))


class ProblemBatch(NamedTuple):
    """Inputs of one batch solve.

    Shapes:
        ego: (E, 6) as :data:`EGO_FIELDS`: position x, y [m], heading psi [rad], speed v [m/s],
            longitudinal acceleration a [m/s^2], heading rate psidot [rad/s].
        goals: (E, G, 2) goal positions (x, y) at the end of the horizon [m].
        obstacles: (E, M, N, 2) predicted obstacle centres (x, y) at the N horizon samples [m].
        obstacle_mask: (E, M) bool, True where the slot holds a real obstacle; absent slots may
            hold any value, NaN included. ``None`` means every slot is present.
        obstacle_axes: (E, M, 2) each obstacle's ellipse semi-axes (a along x, b along y) [m],
            e.g. widened for a car that turns (:func:`mmpc.obstacles.shape.covering_semi_axes`);
            absent slots may hold any value. ``None``: every obstacle has the optimizer's
            ``ellipse_a``, ``ellipse_b``.
    """

    ego: torch.Tensor
    goals: torch.Tensor
    obstacles: torch.Tensor
    obstacle_mask: Optional[torch.Tensor] = None
    obstacle_axes: Optional[torch.Tensor] = None

    @property
    def num_problems(self) -> int:
        return int(self.ego.shape[0])

    @property
    def num_goals(self) -> int:
        return int(self.goals.shape[1])


def ego_state(
    x: torch.Tensor | float,
    y: torch.Tensor | float,
    psi: torch.Tensor | float,
    v: torch.Tensor | float,
    a: torch.Tensor | float = 0.0,
    psidot: torch.Tensor | float = 0.0,
    *,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Stack ego fields into an (E, 6) tensor; scalars become a batch of one.

    Example:
        >>> ego_state(0.0, 8.0, 0.0, 14.0).shape
        torch.Size([1, 6])
    """
    fields = [torch.as_tensor(f, dtype=dtype, device=device) for f in (x, y, psi, v, a, psidot)]
    fields = torch.broadcast_tensors(*fields)
    stacked = torch.stack(fields, dim=-1)
    return stacked.reshape(-1, len(EGO_FIELDS))


def usable_device(device: torch.device | str, name: str = "device") -> torch.device:
    """``device`` as a :class:`torch.device` this process can hold data on, with its index.

    Refuses, naming ``name``: what is not a device, ``meta`` (shapes without data: every check
    of a value would fail deep inside torch) and a device this machine lacks (``cuda`` without
    a GPU, a GPU index past the last).

    Example:
        >>> usable_device("cpu")
        device(type='cpu')
    """
    try:
        parsed = torch.device(device)
    except (RuntimeError, TypeError) as error:
        raise ValueError(f"`{name}` must name a torch device such as 'cpu' or 'cuda:0'; got {device!r}") from error
    if parsed.type == "meta":
        raise ValueError(f"`{name}` must be a device that holds data, such as 'cpu' or 'cuda:0'; got meta")
    try:
        return torch.empty(0, device=parsed).device  # with its index: cuda -> cuda:0
    except (RuntimeError, AssertionError) as error:  # torch without CUDA asserts
        raise ValueError(f"`{name}` is {parsed}, which this machine cannot use: {error}") from error


def require_on_device(device: torch.device, owner: str, **tensors: object) -> None:
    """Refuse a tensor of ``tensors`` that is not on ``device``, ``owner``'s device; values that
    are not tensors (``None``) pass, for the type checks to judge.

    Raises:
        ValueError: ``"`ego` is on meta but the optimizer is on cpu; move it with .to()"``.
    """
    for name, value in tensors.items():
        if isinstance(value, torch.Tensor) and value.device != device:
            raise ValueError(f"`{name}` is on {value.device} but {owner} is on {device}; move it with .to()")
