"""Random IDM traffic of a scenario, placed as highway-env and the project's traffic controller
place it, and the window that keeps it around the ego.

Placement (highway-env's ``HighwayEnv._create_vehicles`` with ``Vehicle.create_random``): the
ego on its lane (the scenario's, or drawn) at ``3 o + o U(0.9, 1.1)`` with
``o = ego_spacing (12 + 25) exp(-5 L / 40)`` for L lanes; then each other vehicle on a random
lane at a speed drawn in [21, 24] m/s (0.7 to 0.8 of the 30 m/s limit), ahead of the foremost
vehicle by ``(12 + speed) exp(-5 L / 40) / density`` times ``U(0.9, 1.1)``, with an IDM
exponent drawn in [3.5, 4.5]. Then the project's controller (``mmpc.highway.traffic``) sets the
ego's speed, redraws the other speeds from the scenario's ``target_speeds`` and moves the
vehicles too close to the ego in its lane into free gaps ahead.

The draws come from :mod:`mmpc.sim.random` (numpy's generator cannot be followed draw by
draw in a batch), so a seed gives the same distribution of scenes as in highway-env, not the
same scene.
"""

from __future__ import annotations

import math
from typing import Optional

import torch

from mmpc.scenario import ScenarioConfig, batched_unsupported
from mmpc.traffic_config import IDMTraffic
from mmpc.compaction import capacity, compact, scatter
from mmpc.sim.config import SimConfig
from mmpc.sim.random import integers, uniform
from mmpc.sim.state import VehicleState, vehicle_state

#: highway-env's ``ego_spacing`` of the environments the batched simulator reproduces
#: (:data:`mmpc.scenario.BATCHED_ENV_IDS`); ``highway-fast-v0`` checks the ego's collisions only.
EGO_SPACING = {"highway-v0": 2.0, "highway-fast-v0": 1.5}
EGO_ONLY_COLLISIONS = ("highway-fast-v0",)
#: highway-env's speed at which the ego is placed [m/s], the range other vehicles' speeds are
#: drawn from [m/s], and the range of their IDM exponent.
EGO_PLACEMENT_SPEED = 25.0
TRAFFIC_SPEEDS = (21.0, 24.0)
IDM_DELTA_RANGE = (3.5, 4.5)
#: Free distance along the road around a (re)placed vehicle [m], and placement attempts (as
#: :mod:`mmpc.highway.traffic`).
PLACEMENT_GAP = 30.0
PLACEMENT_TRIES = 30
#: Vehicles per environment the window moves in one frame (a fixed count: no host read); more than
#: two leaving in one step was seen 13 times in 76,800 environment-steps of cruise traffic, three never;
#: those past the rounds move at the next step.
WINDOW_ROUNDS = 2
#: The window's buffer per round: environments that move a vehicle, per environment and at least
#: (traffic moves one in ~1.3 % of them per step); those past it move at the next step.
WINDOW_MOVES_PER_ENV = 1 / 16
WINDOW_MOVES_FLOOR = 8

# Streams of draws (:mod:`mmpc.sim.random`): each purpose its own.
_EGO_LANE, _EGO_X, _LANE, _SPEED, _SPACING, _DELTA, _TARGET_SPEED, _CLEAR, _CLEAR_FAR, _WINDOW = range(10)


def sim_config(scenario: ScenarioConfig) -> SimConfig:
    """The simulator's constants of a scenario (its lanes, its frequency for both the simulation and
    the commands, as :func:`mmpc.highway.episode.env_config` configures highway-env, and how MOBIL
    reads the ego)."""
    return SimConfig(simulation_frequency=scenario.frequency, policy_frequency=scenario.frequency, lanes=scenario.lanes,
                     ego_as_follower=getattr(scenario.traffic, "ego_as_follower", False))


def check_supported(scenario: ScenarioConfig) -> None:
    """Raise ``ValueError`` unless the batched simulator can run ``scenario``
    (:func:`mmpc.scenario.batched_unsupported`), naming the way to run it otherwise."""
    reason = batched_unsupported(scenario)
    if reason is not None:
        raise ValueError(f"scenario {scenario.name!r}: {reason}")


def initial_state(scenario: ScenarioConfig, seeds: torch.Tensor, *, dtype: torch.dtype = torch.float32) -> VehicleState:
    """The start of one episode per seed.

    Args:
        scenario: an IDM-traffic scenario (:func:`check_supported`).
        seeds: (E,) int64 episode seeds; the state is built on their device.
        dtype: float32 or float64 state.

    Returns:
        A :class:`VehicleState` of E x (1 + vehicles_count) slots, slot 0 the ego.
    """
    check_supported(scenario)
    traffic: IDMTraffic = scenario.traffic
    config = sim_config(scenario)
    seeds = seeds.to(torch.int64)
    seed, count, lanes = seeds[:, None], traffic.vehicles_count, scenario.lanes
    slots = torch.arange(1, count + 1, device=seeds.device)
    crowding = math.exp(-5.0 / 40.0 * lanes)

    ego_lane = (integers(seed, _EGO_LANE, high=lanes) if scenario.ego.lane is None
                else torch.full_like(seed, scenario.ego.lane))
    ego_offset = EGO_SPACING[scenario.env_id] * (12.0 + EGO_PLACEMENT_SPEED) * crowding
    ego_x = 3 * ego_offset + ego_offset * uniform(seed, _EGO_X, low=0.9, high=1.1)
    lane = integers(seed, _LANE, slots, high=lanes)
    speed = uniform(seed, _SPEED, slots, low=TRAFFIC_SPEEDS[0], high=TRAFFIC_SPEEDS[1])
    spacing = (12.0 + speed) * crowding / traffic.vehicles_density * uniform(seed, _SPACING, slots, low=0.9, high=1.1)
    x = torch.cat([ego_x, ego_x + torch.cumsum(spacing, dim=1)], dim=1)
    if traffic.target_speeds is not None:
        speed = uniform(seed, _TARGET_SPEED, slots, low=traffic.target_speeds[0], high=traffic.target_speeds[1])
    lanes_all = torch.cat([ego_lane, lane], dim=1)
    length, width = scenario.vehicle
    ego_only = scenario.env_id in EGO_ONLY_COLLISIONS
    state = vehicle_state(
        x, lanes_all.to(torch.float64) * config.lane_width,
        speed=torch.cat([torch.full_like(ego_x, scenario.ego.speed), speed], dim=1),
        config=config, length=length, width=width,
        idm_delta=torch.cat([torch.full_like(ego_x, 4.0), uniform(seed, _DELTA, slots, low=IDM_DELTA_RANGE[0],
                                                                    high=IDM_DELTA_RANGE[1])], dim=1),
        lane_change_enabled=torch.cat([torch.zeros_like(seed, dtype=torch.bool),
                                       torch.full_like(lane, traffic.lane_changes, dtype=torch.bool)], dim=1),
        check_collisions=torch.cat([torch.ones_like(seed, dtype=torch.bool),
                                    torch.full_like(lane, not ego_only, dtype=torch.bool)], dim=1),
    )
    state = _clear_ego_start(state, traffic, seeds, config)
    return VehicleState(*(field.to(dtype) if field.dtype == torch.float64 and name != "lane_change_timer" else field
                          for name, field in zip(VehicleState._fields, state)))


def _clear_ego_start(state: VehicleState, traffic: IDMTraffic, seeds: torch.Tensor, config: SimConfig) -> VehicleState:
    """Move the vehicles within ``initial_clearance`` ahead of the ego in its lane (or half of
    it behind) to a free gap ahead, in slot order; where none is found, farther ahead."""
    clearance = traffic.initial_clearance
    ego_x, ego_lane = state.x[:, 0], state.lane[:, 0]
    far = state.x.max(dim=1).values + PLACEMENT_GAP
    for slot in range(1, state.x.shape[1]):
        gap = state.x[:, slot] - ego_x
        too_close = (state.lane[:, slot] == ego_lane) & (gap > -0.5 * clearance) & (gap < clearance)
        slots = torch.full_like(ego_lane, slot)
        state, placed = relocate(state, slots, too_close, ego_x + clearance, far, seeds, (_CLEAR, slot), config)
        state, _ = relocate(state, slots, too_close & ~placed, far, far + 10 * PLACEMENT_GAP, seeds,
                            (_CLEAR_FAR, slot), config)
    return state


def relocate(
    state: VehicleState,
    slot: torch.Tensor,
    moving: torch.Tensor,
    low: torch.Tensor,
    high: torch.Tensor,
    seeds: torch.Tensor,
    draw: tuple,
    config: SimConfig,
    buffer: Optional[int] = None,
) -> tuple[VehicleState, torch.Tensor]:
    """Move one vehicle per environment to the first of :data:`PLACEMENT_TRIES` random spots in
    ``[low, high)`` along the road, on a random lane, with no other
    vehicle within :data:`PLACEMENT_GAP` along the road and one lane width across; on the
    lane's centre, heading along it, speed and timer kept.

    Args:
        slot: (E,) long, the vehicle of each environment.
        moving: (E,) bool, the environments whose vehicle moves.
        low, high: (E,) the range of positions along the road [m].
        seeds: (E,) the environments' seeds; ``draw`` (ints or tensors) names the draws.
        buffer: the moving environments searched at most (:mod:`mmpc.compaction`); those past it
            do not move. ``None``: as many as move (the host reads how many).

    Returns:
        The state, and (E,) bool: moved (False where no free spot was found, not ``moving`` or
        past the buffer).
    """
    num_envs = moving.shape[0]
    rows = compact(moving, buffer, fill=num_envs)
    (index,) = rows.index  # the padding points one past the last environment: a scratch row
    if buffer is None and index.numel() == 0:  # exact sizes: no environment moves a vehicle (most steps)
        return state, torch.zeros_like(moving)
    picked = index.clamp(max=num_envs - 1)
    draw = tuple(part[picked] if isinstance(part, torch.Tensor) and part.dim() > 0 else part for part in draw)
    part, moved_part = _relocate_rows(VehicleState(*(field[picked] for field in state)), slot[picked], low[picked],
                                      high[picked], seeds[picked], draw, config)

    def back(field: torch.Tensor, new: torch.Tensor) -> torch.Tensor:  # the searched rows back in place
        return field.index_copy(0, index, new) if buffer is None else scatter(field, 0, index, new)

    # A searched row that found no spot is its old self (:func:`_relocate_rows`).
    return VehicleState(*(back(field, new) for field, new in zip(state, part))), back(torch.zeros_like(moving),
                                                                                       moved_part & rows.valid)


def _relocate_rows(state: VehicleState, slot: torch.Tensor, low: torch.Tensor, high: torch.Tensor, seeds: torch.Tensor,
                   draw: tuple, config: SimConfig) -> tuple[VehicleState, torch.Tensor]:
    """:func:`relocate` where every environment moves its vehicle."""
    tries = torch.arange(PLACEMENT_TRIES, device=slot.device)
    seed = seeds[:, None]
    lane = integers(seed, *draw, 0, tries, high=config.lanes)
    s = low[:, None].double() + (high - low)[:, None].double() * uniform(seed, *draw, 1, tries)  # (E, T)
    others = state.alive & (torch.arange(state.x.shape[1], device=slot.device) != slot[:, None])  # (E, V)
    near_across = (state.y[:, None, :] - lane[:, :, None] * config.lane_width).abs() < config.lane_width
    near_along = (state.x[:, None, :] - s[:, :, None]).abs() < PLACEMENT_GAP
    free = ~(near_across & near_along & others[:, None, :]).any(dim=2)  # (E, T)
    first = free.to(torch.int8).argmax(dim=1, keepdim=True)
    moved = free.any(dim=1)
    target = moved[:, None] & (torch.arange(state.x.shape[1], device=slot.device) == slot[:, None])  # (E, V)
    new_lane = lane.gather(1, first)
    new_x = s.gather(1, first).to(state.x.dtype)
    return state._replace(
        x=torch.where(target, new_x, state.x),
        y=torch.where(target, (new_lane * config.lane_width).to(state.y.dtype), state.y),
        heading=torch.where(target, 0.0, state.heading),
        lane=torch.where(target, new_lane, state.lane),
        target_lane=torch.where(target, new_lane, state.target_lane),
    ), moved


def keep_in_window(
    state: VehicleState, window: tuple[float, float], seeds: torch.Tensor, frame: torch.Tensor, config: SimConfig
) -> VehicleState:
    """Move every other vehicle farther than ``window = (behind, ahead)`` [m] from the ego
    along the road to the window's other end (its last quarter), into a free gap of a random
    lane, in slot order (:func:`relocate`); those without a free gap stay for this frame (and with
    ``config.fixed_shapes``, those past :data:`WINDOW_ROUNDS` per environment or the rounds' buffers).

    Args:
        frame: (E,) long, each environment's frame count (names the draws).
    """
    behind, ahead = window
    ego_x = state.x[:, :1]
    gap = state.x - ego_x
    slots = torch.arange(state.x.shape[1], device=state.x.device)
    outside = state.alive & (slots > 0) & ((gap < -behind) | (gap > ahead))
    order = torch.cumsum(outside.to(torch.int64), dim=1) - 1  # the vehicle's turn among its environment's
    rounds = WINDOW_ROUNDS if config.fixed_shapes else int(outside.sum(dim=1).max())
    for turn in range(rounds):
        mine = outside & (order == turn)
        moving = mine.any(dim=1)
        slot = mine.to(torch.int8).argmax(dim=1)
        left_behind = gap.gather(1, slot[:, None])[:, 0] < -behind
        x_ego = ego_x[:, 0]
        low = torch.where(left_behind, x_ego + 0.75 * ahead, x_ego - behind)
        high = torch.where(left_behind, x_ego + ahead, x_ego - 0.75 * behind)
        state, _ = relocate(state, slot, moving, low, high, seeds, (_WINDOW, frame[:, None], slot[:, None]), config,
                            capacity(config.fixed_shapes, len(moving), WINDOW_MOVES_PER_ENV, WINDOW_MOVES_FLOOR,
                                     len(moving)))
    return state
