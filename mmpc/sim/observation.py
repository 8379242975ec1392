"""highway-env's ``Kinematics`` observation of the egos, batched (``KinematicObservation`` with
its defaults, as the project's environments create it).

Row 0 is the ego: presence 1, its absolute x, y and velocity. The other rows are the nearest
present vehicles (at most ``vehicles_count - 1``) closer than 200 m (highway-env's perception
distance, 5 x the 40 m/s speed limit of its vehicles) and not more than two ego lengths behind,
sorted by distance along the road (ties in slot order), relative to the ego. x is divided by
200 m, y by the road's width (lane width x lanes), vx and vy by 80 m/s, then clipped to [-1, 1];
missing rows are zeros. Velocities are the speed along the body heading.
"""

from __future__ import annotations

import torch

from mmpc.sim.config import SimConfig
from mmpc.sim.state import VehicleState, check_state

#: Features of a row, in order.
FEATURES = ("presence", "x", "y", "vx", "vy")
#: highway-env's ``Vehicle.MAX_SPEED`` [m/s]: the perception distance is 5 x it, the x range
#: +-5 x it, the velocity range +-2 x it.
MAX_SPEED = 40.0
PERCEPTION_DISTANCE = 5.0 * MAX_SPEED


def kinematics_observation(state: VehicleState, config: SimConfig, *, vehicles_count: int = 5) -> torch.Tensor:
    """(E, vehicles_count, 5) the egos' observations (:data:`FEATURES`), in the state's dtype.

    Args:
        state: the vehicles (slot 0 the ego), checked with :func:`mmpc.sim.state.check_state`.
        config: the road (lanes, lane width).
        vehicles_count: rows, the ego's included (int >= 1).
    """
    if not isinstance(vehicles_count, int) or isinstance(vehicles_count, bool) or vehicles_count < 1:
        raise ValueError(f"`vehicles_count` must be an int >= 1; got {vehicles_count!r}")
    check_state(state, config)
    vx = state.speed * torch.cos(state.heading)
    vy = state.speed * torch.sin(state.heading)
    ego = torch.stack([torch.ones_like(state.x[:, 0]), state.x[:, 0], state.y[:, 0], vx[:, 0], vy[:, 0]], dim=1)
    dx, dy = state.x[:, 1:] - state.x[:, :1], state.y[:, 1:] - state.y[:, :1]
    visible = state.alive[:, 1:] & (torch.sqrt(dx * dx + dy * dy) < PERCEPTION_DISTANCE) & (dx > -2 * state.length[:, :1])
    distance = torch.where(visible, dx.abs(), torch.full_like(dx, torch.inf))
    order = torch.sort(distance, dim=1, stable=True).indices[:, :vehicles_count - 1]  # (E, R - 1)
    others = torch.stack([visible.to(state.x.dtype), dx, dy, vx[:, 1:] - vx[:, :1], vy[:, 1:] - vy[:, :1]], dim=2)
    rows = torch.gather(others, 1, order[..., None].expand(-1, -1, len(FEATURES)))
    rows = rows * torch.gather(visible, 1, order)[..., None]  # invisible vehicles: zero rows
    observation = torch.cat([ego[:, None], rows], dim=1)
    scale = observation.new_tensor([1.0, PERCEPTION_DISTANCE, config.lane_width * config.lanes, 2 * MAX_SPEED, 2 * MAX_SPEED])
    observation = (observation / scale).clamp(-1.0, 1.0)
    missing = vehicles_count - observation.shape[1]  # fewer slots than rows
    return torch.nn.functional.pad(observation, (0, 0, 0, missing)) if missing > 0 else observation
