"""The ego's command path, as the project drives highway-env (``mmpc.highway.episode``).

``HighwayEpisode.apply`` floors the acceleration at ``-max(v, 0) * policy_frequency`` (no
braking through rest), ``command_to_action`` normalises (acceleration, steering) to
highway-env's ``[-1, 1]`` as float32 and clips, and ``ContinuousAction`` maps it back to the
ranges, in float32 arithmetic (numpy's rules for a float32 scalar and Python numbers). After
the command's frames a speed that crossed below zero is set to zero.
"""

from __future__ import annotations

import torch

from mmpc.sim.config import SimConfig


def _to_unit(value: torch.Tensor, bounds: tuple[float, float]) -> torch.Tensor:
    low, high = bounds
    return (2.0 * (value - low) / (high - low) - 1.0).to(torch.float32).clamp(-1.0, 1.0)


def _from_unit(unit: torch.Tensor, bounds: tuple[float, float]) -> torch.Tensor:
    low, high = bounds
    return low + (unit - (-1)) * (high - low) / (1 - (-1))


def ego_action(
    acceleration: torch.Tensor, steering: torch.Tensor, speed: torch.Tensor, config: SimConfig
) -> tuple[torch.Tensor, torch.Tensor]:
    """The (acceleration [m/s^2], steering [rad]) highway-env applies for a command.

    Args:
        acceleration, steering: (E,) the command.
        speed: (E,) the ego's speed when the command is given [m/s].

    Returns:
        (E,) each, in the dtype of ``acceleration`` (float32-rounded values, as highway-env gets them).
    """
    floor = -speed.clamp(min=0.0) * config.policy_frequency
    acceleration = torch.maximum(acceleration, floor)
    applied_acceleration = _from_unit(_to_unit(acceleration, config.acceleration_range), config.acceleration_range)
    applied_steering = _from_unit(_to_unit(steering, config.steering_range), config.steering_range)
    return applied_acceleration.to(acceleration.dtype), applied_steering.to(acceleration.dtype)
