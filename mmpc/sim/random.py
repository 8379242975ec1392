"""Counter-based random draws: a number is a hash of (seed, stream, indices), not a generator's state.

An environment's draws depend only on its own seed and on where they are made (which stream,
frame, vehicle slot, attempt), so an environment with a given seed runs the same episode alone
or among thousands, whatever the others do, on CPU or CUDA. The hash is SplitMix64's finaliser
on int64 tensors (wrapping multiplication, logical shifts).
"""

from __future__ import annotations

from typing import Union

import torch

Index = Union[int, torch.Tensor]

_GOLDEN = 0x9E3779B97F4A7C15 - (1 << 64)  # 2^64 / golden ratio, as a signed int64
_MULTIPLIERS = (0xBF58476D1CE4E5B9 - (1 << 64), 0x94D049BB133111EB - (1 << 64))


def _shift_right(value: torch.Tensor, bits: int) -> torch.Tensor:
    """Logical right shift of int64 (torch's ``>>`` is arithmetic on negative numbers)."""
    return (value >> bits) & ((1 << (64 - bits)) - 1)


def _mix(value: torch.Tensor) -> torch.Tensor:
    value = (value ^ _shift_right(value, 30)) * _MULTIPLIERS[0]
    value = (value ^ _shift_right(value, 27)) * _MULTIPLIERS[1]
    return value ^ _shift_right(value, 31)


def hash_indices(seed: torch.Tensor, *indices: Index) -> torch.Tensor:
    """int64 hash of ``seed`` and ``indices`` (ints or int64 tensors), broadcast together."""
    value = _mix(seed.to(torch.int64) * _GOLDEN)
    for index in indices:
        value = _mix(value + (torch.as_tensor(index, dtype=torch.int64, device=seed.device) + 1) * _GOLDEN)
    return value


def uniform(seed: torch.Tensor, *indices: Index, low: float = 0.0, high: float = 1.0) -> torch.Tensor:
    """Uniform float64 draws in ``[low, high)``, one per broadcast element of ``seed`` and ``indices``.

    Args:
        seed: int64 tensor, typically (E, 1, ...) an environment's seed.
        indices: ints or int64 tensors naming the draw (stream, frame, slot, attempt, ...).

    Example:
        >>> seed = torch.tensor([[3], [4]])
        >>> a = uniform(seed, 0, torch.arange(5))
        >>> a.shape, bool((a == uniform(seed, 0, torch.arange(5))).all())
        (torch.Size([2, 5]), True)
    """
    top53 = _shift_right(hash_indices(seed, *indices), 11)
    return low + (high - low) * (top53.to(torch.float64) * 2.0 ** -53)


def integers(seed: torch.Tensor, *indices: Index, high: int) -> torch.Tensor:
    """Uniform int64 draws in ``[0, high)`` (see :func:`uniform`)."""
    return torch.floor(uniform(seed, *indices) * high).to(torch.int64).clamp(max=high - 1)
