"""Where a run computes: the device of the batched simulator and of the MPCs a run builds.

Like compiling, the device is a run option, not part of a scenario: the command line's
``--device`` sets the environment variable :data:`DEVICE_ENV`, read in one place
(:func:`run_device`), so that worker processes inherit it and a scenario's results stay the
same wherever it ran.
"""

from __future__ import annotations

import os

import torch

from mmpc.problem import usable_device

#: Environment variable naming the device of a run: ``cpu`` (default when unset), ``cuda``,
#: ``cuda:N``, or ``auto`` (the current CUDA device when there is one, else the CPU).
DEVICE_ENV = "MMPC_DEVICE"


def run_device() -> torch.device:
    """The device this run computes on (:data:`DEVICE_ENV`), with its index.

    Raises:
        ValueError: the variable names no device, or one this machine lacks (``cuda`` without a GPU).

    Example:
        >>> run_device()  # MMPC_DEVICE unset
        device(type='cpu')
    """
    return resolve_device(os.environ.get(DEVICE_ENV, ""))


def resolve_device(setting: str) -> torch.device:
    """A device setting (``cpu``, ``cuda``, ``cuda:N``, ``auto``; empty: ``cpu``) -> the device, with its index.

    Raises:
        ValueError: it names no device, or one this machine lacks, naming :data:`DEVICE_ENV`.
    """
    setting = setting.strip() or "cpu"
    if setting == "auto":
        return torch.device("cuda", torch.cuda.current_device()) if torch.cuda.is_available() else torch.device("cpu")
    return usable_device(setting, name=f"{DEVICE_ENV} (--device)")
