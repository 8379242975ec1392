"""highway-env's kinematic bicycle (``Vehicle.step``), batched.

One frame of length dt, explicit Euler with every right-hand side taken at the start of the frame::

    beta     = atan(tan(steering) / 2)                      slip angle at the centre
    x, y    += v (cos(heading + beta), sin(heading + beta)) dt   (then a pending collision push)
    heading += v sin(beta) / (length / 2) dt
    v       += a dt

The position moves with the speed *before* this frame's acceleration. Before integrating, the
command is limited as highway-env's ``clip_actions`` does: a crashed vehicle gets zero steering
and ``a = -v``; above ``max_speed`` the acceleration is at most ``max_speed - v`` (below
``min_speed`` at least ``min_speed - v``); the speed itself is never clipped.
"""

from __future__ import annotations

import torch

from mmpc.sim.config import SimConfig
from mmpc.sim.state import VehicleState, lane_of


def limit_command(
    state: VehicleState, acceleration: torch.Tensor, steering: torch.Tensor, config: SimConfig
) -> tuple[torch.Tensor, torch.Tensor]:
    """highway-env's ``clip_actions``: (acceleration [m/s^2], steering [rad]), each (E, V)."""
    steering = torch.where(state.crashed, torch.zeros_like(steering), steering)
    acceleration = torch.where(state.crashed, -state.speed, acceleration)
    too_fast = state.speed > config.max_speed
    too_slow = ~too_fast & (state.speed < config.min_speed)
    acceleration = torch.where(too_fast, torch.minimum(acceleration, config.max_speed - state.speed), acceleration)
    acceleration = torch.where(too_slow, torch.maximum(acceleration, config.min_speed - state.speed), acceleration)
    return acceleration, steering


def bicycle_frame(x: torch.Tensor, y: torch.Tensor, heading: torch.Tensor, speed: torch.Tensor,
                  length: torch.Tensor | float, acceleration: torch.Tensor, steering: torch.Tensor,
                  dt: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """One frame of the bicycle (module docstring) for any shape of tensors (broadcast): the new
    (x, y [m], heading [rad], speed [m/s]), without command limits or collision pushes."""
    beta = torch.atan(0.5 * torch.tan(steering))
    return (x + speed * torch.cos(heading + beta) * dt, y + speed * torch.sin(heading + beta) * dt,
            heading + speed * torch.sin(beta) / (length / 2) * dt, speed + acceleration * dt)


def bicycle_step(
    state: VehicleState, acceleration: torch.Tensor, steering: torch.Tensor, config: SimConfig
) -> VehicleState:
    """Advance every present vehicle one frame of ``config.dt`` [s].

    Args:
        state: the vehicles.
        acceleration: (E, V) commanded acceleration [m/s^2], limited here by :func:`limit_command`.
        steering: (E, V) front-wheel angle [rad].

    Returns:
        The state after the frame: pending collision pushes applied (those vehicles marked
        crashed), lanes updated; padding slots unchanged.
    """
    acceleration, steering = limit_command(state, acceleration, steering, config)
    x, y, heading, speed = bicycle_frame(state.x, state.y, state.heading, state.speed, state.length,
                                         acceleration, steering, config.dt)
    pushed = state.impact_pending & state.alive
    x = torch.where(pushed, x + state.impact[..., 0], x)
    y = torch.where(pushed, y + state.impact[..., 1], y)
    alive = state.alive
    return state._replace(
        x=torch.where(alive, x, state.x),
        y=torch.where(alive, y, state.y),
        heading=torch.where(alive, heading, state.heading),
        speed=torch.where(alive, speed, state.speed),
        lane=torch.where(alive, lane_of(y, config), state.lane),
        crashed=state.crashed | pushed,
        impact=torch.where(pushed[..., None], torch.zeros_like(state.impact), state.impact),
        impact_pending=state.impact_pending & ~pushed,
    )
