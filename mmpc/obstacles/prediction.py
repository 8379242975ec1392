"""Where the obstacles go: predictions of their centres over the horizon, in the road frame.

:data:`PREDICTIONS` names them for :attr:`mmpc.MPCConfig.prediction`; :class:`mmpc.MPC` predicts
the obstacles it plans around with the one its config names (:meth:`mmpc.MPC.predict`, a
:data:`Predictor`).
"""

from __future__ import annotations

from typing import Callable

import torch

from mmpc.road import Road

#: ``(states (E, M, 4), times (N,)) -> (E, M, N, 2)`` predicted obstacle centres, e.g. :meth:`mmpc.MPC.predict`.
Predictor = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def predict_constant_velocity(states: torch.Tensor, times: torch.Tensor) -> torch.Tensor:
    """Constant-velocity prediction of obstacle centres.

    Args:
        states: (E, M, 4) obstacle states (x [m], y [m], vx [m/s], vy [m/s]).
        times: (N,) prediction instants [s] measured from now.

    Returns:
        (E, M, N, 2) predicted centres ``p + v t``.
    """
    if states.ndim != 3 or states.shape[-1] != 4:
        raise ValueError(f"`states` must have shape (E, M, 4); got {tuple(states.shape)}")
    if times.ndim != 1:
        raise ValueError(f"`times` must have shape (N,); got {tuple(times.shape)}")
    times = times.to(dtype=states.dtype, device=states.device)
    position = states[..., None, 0:2]
    velocity = states[..., None, 2:4]
    return position + velocity * times[:, None]


#: How far past a lane centre [in lane widths] a vehicle must have moved laterally before
#: :func:`predict_within_lanes` takes it for changing to the next lane; closer in, its lateral
#: velocity is taken for settling onto that centre.
LANE_CHANGE_ONSET = 0.1


def predict_within_lanes(states: torch.Tensor, times: torch.Tensor, road: Road) -> torch.Tensor:
    """Constant-velocity prediction whose lateral motion ends on a lane centre.

    Along the road the centre moves at ``vx``. Across it, the vehicle moves at ``vy`` until it
    reaches the next lane centre in the direction of ``vy`` and stays there: a lane change is
    predicted to end in the adjacent lane, and a vehicle drifting back to its lane centre to
    stop on it. (Plain :func:`predict_constant_velocity` carries a lane change's 2-4 m/s of
    ``vy`` across every lane of the road within an 8 s horizon, so that no plan of the ego can
    avoid the prediction.) A vehicle counts as leaving its lane once it is more than
    :data:`LANE_CHANGE_ONSET` lane widths off the centre in the direction of ``vy``. Vehicles
    outside the outermost lane centres keep their lateral position when moving outwards.

    Args:
        states: (E, M, 4) obstacle states (x [m], y [m], vx [m/s], vy [m/s]) in the road frame.
        times: (N,) prediction instants [s] measured from now.
        road: the lanes (centres at ``y = k * lane_width``).

    Returns:
        (E, M, N, 2) predicted centres [m].
    """
    centres = predict_constant_velocity(states, times)
    y0, vy = states[..., 1:2], states[..., 3:4]  # (E, M, 1)
    lane = y0 / road.lane_width
    onward = torch.where(vy > 0, torch.ceil(lane - LANE_CHANGE_ONSET), torch.floor(lane + LANE_CHANGE_ONSET))
    target = onward.clamp(0, road.num_lanes - 1) * road.lane_width
    lateral = torch.minimum(torch.maximum(centres[..., 1], torch.minimum(y0, target)), torch.maximum(y0, target))
    return torch.stack([centres[..., 0], lateral], dim=-1)


#: Obstacle predictions by :attr:`mmpc.MPCConfig.prediction` name: ``(states (E, M, 4), times (N,),
#: road) -> (E, M, N, 2)`` centres.
PREDICTIONS = {
    "lanes": predict_within_lanes,
    "constant_velocity": lambda states, times, road: predict_constant_velocity(states, times),
}
