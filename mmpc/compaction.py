"""Fixed-size compaction: the few set entries of a large mask gathered into a buffer whose size is
known before the data, so that a step keeps its shapes (one graph, nothing read on the host) and
its work stays proportional to the entries, not to the mask."""

from __future__ import annotations

from typing import NamedTuple, Optional

import torch


class Compacted(NamedTuple):
    """The first ``K`` set entries of a mask in row-major order.

    Shapes: ``index`` one (K,) int64 tensor per dimension of the mask (the padding holds ``fill``),
    ``valid`` (K,) bool (False on the padding), ``dropped`` the mask's set entries past the
    buffer, mask-shaped bool.
    """

    index: tuple[torch.Tensor, ...]
    valid: torch.Tensor
    dropped: torch.Tensor


def compact(mask: torch.Tensor, capacity: Optional[int], fill: int = 0) -> Compacted:
    """The set entries of ``mask`` (any shape, bool) in a buffer of ``capacity`` (> 0) entries,
    the padding's indices ``fill``; ``None``: exactly as many as are set (the host reads how many)."""
    if capacity is None:
        found = torch.nonzero(mask)
        nothing_dropped = mask.new_zeros(()).expand(mask.shape)  # no allocation
        return Compacted(tuple(found.unbind(dim=1)), torch.ones_like(found[:, 0], dtype=torch.bool), nothing_dropped)
    if capacity < 1:
        raise ValueError(f"`capacity` must be >= 1; got {capacity}")
    found = torch.nonzero_static(mask, size=capacity, fill_value=fill)  # (K, mask.dim())
    running = torch.cumsum(mask.flatten().to(torch.int64), dim=0)  # set entries up to each one
    valid = torch.arange(capacity, device=mask.device) < running[-1]
    return Compacted(tuple(found.unbind(dim=1)), valid, mask & (running.view(mask.shape) > capacity))


def scatter(target: torch.Tensor, dim: int, index: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """``target.index_copy(dim, index, values)`` where an index of ``target.shape[dim]`` (one past the
    last: a buffer's padding, :func:`compact` with that ``fill``) writes nowhere: a scratch slice."""
    size = target.shape[dim]
    scratch = torch.cat([target, target.narrow(dim, 0, 1)], dim=dim)
    return scratch.index_copy(dim, index, values).narrow(dim, 0, size)


def capacity(fixed: bool, num_envs: int, per_env: float, floor: int, most: int) -> Optional[int]:
    """A buffer for ``num_envs`` environments: ``per_env`` entries each on average, at least
    ``floor`` (a small batch may hold one busy environment), at most ``most`` (every entry);
    ``None`` (exact sizes) unless ``fixed`` (:attr:`mmpc.sim.SimConfig.fixed_shapes`)."""
    return max(1, min(most, max(floor, int(per_env * num_envs)))) if fixed else None
