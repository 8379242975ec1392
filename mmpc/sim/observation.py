"""highway-env's ``Kinematics`` observation of the egos, batched: ``KinematicObservation`` with
its defaults, as the project's environments create it (``{"type": "Kinematics"}``, only
``vehicles_count`` set), written from highway-env's equations.

Row 0 is the ego: presence 1, its absolute x, y, vx, vy. The other rows are the present vehicles
(``alive``, slots 1..; highway-v0 has no static objects) that the ego perceives
(``Road.close_objects_to``, ``see_behind=False``): a Euclidean centre distance below 200 m
(``AbstractEnv.PERCEPTION_DISTANCE``, 5 x ``Vehicle.MAX_SPEED``) and less than two ego lengths
behind, both strict; the nearest ``vehicles_count - 1`` by the absolute distance along the road
(the ego's lane, +x), ties in slot order (Python's stable ``sorted`` over ``road.vehicles``);
x, y, vx, vy relative to the ego's. Velocities are the speed along the body heading
(``Vehicle.velocity``, no slip angle).

Every row is then mapped onto [-1, 1] (``utils.lmap``) from x in +-200 m, y in +-(4 m x lanes)
(``AbstractLane.DEFAULT_WIDTH`` times the road's lanes, whatever the lane width), vx and vy in
+-80 m/s (2 x ``Vehicle.MAX_SPEED``), and clipped to [-1, 1]; presence stays 0 or 1. Rows without
a vehicle are zeros.

The observation is computed in float64 and returned in the state's dtype, as highway-env computes
in float64 and returns float32: float32 differences could tie or reorder distances, or cross the
200 m and two-length borders, that float64 keeps apart.
"""

from __future__ import annotations

import torch

from mmpc.config import require_int
from mmpc.sim.config import SimConfig
from mmpc.sim.state import VehicleState, check_state

#: Features of a row, in order.
FEATURES = ("presence", "x", "y", "vx", "vy")
#: highway-env's ``Vehicle.MAX_SPEED`` [m/s]; the perception distance and the ranges derive from it.
MAX_SPEED = 40.0
#: highway-env's ``AbstractEnv.PERCEPTION_DISTANCE`` [m]: vehicles at least this far (centres, Euclidean) are not seen.
PERCEPTION_DISTANCE = 5.0 * MAX_SPEED
#: Vehicles at least this many ego lengths behind the ego are not seen (``see_behind=False``).
LENGTHS_SEEN_BEHIND = 2.0
#: Half-widths of the ranges mapped onto [-1, 1]: x [m], vx and vy [m/s]; y's is ``LANE_RANGE_WIDTH * lanes``.
X_RANGE = 5.0 * MAX_SPEED
SPEED_RANGE = 2.0 * MAX_SPEED
#: highway-env's ``AbstractLane.DEFAULT_WIDTH`` [m], the unit of the y range.
LANE_RANGE_WIDTH = 4.0


def kinematics_observation(state: VehicleState, config: SimConfig, *, vehicles_count: int = 5,
                           check: bool = True) -> torch.Tensor:
    """The egos' ``Kinematics`` observations, equal to highway-env's ``KinematicObservation.observe()``.

    Args:
        state: E environments x V slots (slot 0 the ego, which must be ``alive``), checked with
            :func:`mmpc.sim.state.check_state`; E = 0 gives an empty batch.
        config: the road; ``config.lanes`` sets the y range.
        vehicles_count: rows per observation, the ego's included (int >= 1). With 1, the ego's
            row only: highway-env then returns every perceived vehicle too (its ``count=0``
            means "no limit"), more rows than its own observation space.
        check: False where the state is a simulator's own (:class:`mmpc.sim.SimEpisodes`): its
            values are not read back to be checked (a host synchronisation on a GPU).

    Returns:
        (E, vehicles_count, 5) in the state's dtype and device: :data:`FEATURES` per row,
        normalized to [-1, 1] (presence 0 or 1); rows without a vehicle are zeros.

    Example:
        >>> from mmpc.sim.state import vehicle_state
        >>> state = vehicle_state(torch.tensor([[100.0, 150.0]]), torch.tensor([[4.0, 8.0]]), speed=20.0)
        >>> kinematics_observation(state, SimConfig(lanes=3), vehicles_count=3)[0].tolist()
        [[1.0, 0.5, 0.3333333432674408, 0.25, 0.0], [1.0, 0.25, 0.3333333432674408, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, 0.0]]
    """
    if check:
        _check_inputs(state, config, vehicles_count)
    x, y, heading, speed = (value.double() for value in (state.x, state.y, state.heading, state.speed))
    absolute = torch.stack([torch.ones_like(x), x, y, speed * torch.cos(heading), speed * torch.sin(heading)], dim=2)
    ego = absolute[:, :1]  # (E, 1, 5)
    others = torch.cat([absolute[:, 1:, :1], absolute[:, 1:, 1:] - ego[:, :, 1:]], dim=2)  # (E, V - 1, 5) relative
    seen = _perceived(others[..., 1], others[..., 2], state.alive[:, 1:], state.length[:, :1].double())
    rows, present = _nearest(others, seen, vehicles_count - 1)
    observation = _normalized(torch.cat([ego, rows], dim=1), config.lanes)
    present = torch.cat([state.alive[:, :1], present], dim=1)  # the egos are present (checked)
    return torch.where(present[..., None], observation, torch.zeros_like(observation)).to(state.x.dtype)


def _check_inputs(state: VehicleState, config: SimConfig, vehicles_count: int) -> None:
    """Raise ``ValueError`` unless ``vehicles_count`` is an int >= 1, ``config`` a :class:`SimConfig`
    and ``state`` a consistent state whose egos are all present."""
    require_int("", low=1, vehicles_count=vehicles_count)
    if not isinstance(config, SimConfig):
        raise ValueError(f"`config` must be a SimConfig; got {type(config).__name__}")
    check_state(state, config)
    if not bool(state.alive[:, 0].all()):
        dead = torch.nonzero(~state.alive[:, 0])[:3, 0].tolist()
        raise ValueError(f"`state.alive[:, 0]` must be True: slot 0 is the observing ego (environments {dead}... have none)")


def _perceived(dx: torch.Tensor, dy: torch.Tensor, alive: torch.Tensor, ego_length: torch.Tensor) -> torch.Tensor:
    """(E, N) bool, the vehicles the ego sees: present, centres closer than :data:`PERCEPTION_DISTANCE`
    and less than :data:`LENGTHS_SEEN_BEHIND` ego lengths behind.

    Args:
        dx, dy: (E, N) positions relative to the ego, float64 [m]; dx is also the distance along
            the ego's lane (``lane_distance_to`` on a road along +x).
        alive: (E, N) bool.
        ego_length: (E, 1) [m].
    """
    near = torch.sqrt(dx * dx + dy * dy) < PERCEPTION_DISTANCE  # highway-env's np.linalg.norm, strict
    return alive & near & (-LENGTHS_SEEN_BEHIND * ego_length < dx)


def _nearest(others: torch.Tensor, seen: torch.Tensor, count: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``count`` seen vehicles nearest along the road, ties in slot order.

    Args:
        others: (E, N, 5) rows of the vehicles (dx is feature 1) [m, m/s].
        seen: (E, N) bool.
        count: rows wanted (>= 0); fewer seen vehicles leave rows with ``present`` False.

    Returns:
        rows (E, count, 5) and present (E, count) bool.
    """
    missing = max(count - others.shape[1], 0)  # fewer slots than rows: pad with unseen ones
    others = torch.nn.functional.pad(others, (0, 0, 0, missing))
    seen = torch.nn.functional.pad(seen, (0, missing), value=False)
    distance = torch.where(seen, others[..., 1].abs(), torch.full_like(others[..., 1], torch.inf))
    order = torch.sort(distance, dim=1, stable=True).indices[:, :count]  # stable: Python's sorted keeps road order
    rows = torch.gather(others, 1, order[..., None].expand(-1, -1, others.shape[2]))
    return rows, torch.gather(seen, 1, order)


def _normalized(rows: torch.Tensor, lanes: int) -> torch.Tensor:
    """(E, R, 5) rows with x, y, vx, vy mapped from their ranges onto [-1, 1] and clipped (presence kept).

    The same operations as highway-env's ``lmap(v, [-h, h], [-1, 1]) = -1 + (v + h) * 2 / (2 h)``,
    for the same float64 rounding.
    """
    half_width = rows.new_tensor([X_RANGE, LANE_RANGE_WIDTH * lanes, SPEED_RANGE, SPEED_RANGE])
    mapped = (-1.0 + (rows[..., 1:] + half_width) * 2.0 / (2.0 * half_width)).clamp(-1.0, 1.0)
    return torch.cat([rows[..., :1], mapped], dim=2)
