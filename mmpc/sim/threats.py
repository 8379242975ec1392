"""Threatening traffic: the cars near the ego do what endangers it most that the rules allow.

The falsification mode of the batched simulator (:class:`mmpc.traffic_config.Threats`). Each frame,
after MOBIL has decided, cars within ``reach`` of the ego:

- **cut in**: a car ahead of the ego, settled on its lane, that MOBIL kept there at its decision
  of this frame (once a second), turns to a neighbouring lane the ego counts on or is moving into, wherever MOBIL's safety criterion
  (:func:`mmpc.sim.mobil.mobil_safe`) allows it and it need not brake harder than that itself
  behind its new leader, whatever it gains; the lane-change
  controller steers it there as any other change;
- **brake**: a car ahead, settled on its lane, brakes at ``SimConfig.acc_max`` (to rest, never
  reversing) in a random share of time windows, whatever IDM asks, where the car behind it,
  unless that is the ego, could stop in time (one braking that hard while it changes lane turns
  its body beyond ``TrafficAssumptions.lane_overreach`` as it slows: the lane-keeping controller
  asks for up to 45 degrees at low speed);
- **overtake**: a car behind in a lane beside the ego's speeds up at IDM's largest acceleration
  (``SimConfig.comfort_acc_max``, to the speed limit) wherever IDM would not brake.

:class:`Orders` give the same moves to single cars from outside (a red-team agent,
:mod:`mmpc.rl.red_team`), carried out under the same rules. Everything stays inside
:class:`mmpc.verify.TrafficAssumptions`; the episode runner's
:class:`mmpc.verify.AssumptionMonitor` reports any car that leaves its set. The draws come from
:mod:`mmpc.sim.random`, keyed by the episode's seed, step and the car's slot.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from mmpc.traffic_config import Threats
from mmpc.sim.config import SimConfig
from mmpc.sim.idm import idm_acceleration, vehicle_behind
from mmpc.sim.mobil import mobil_safe
from mmpc.sim.random import uniform
from mmpc.sim.state import VehicleState

# Streams of draws (:mod:`mmpc.sim.random`), apart from those of the traffic's placement.
_BRAKE, _CUT_IN, _SIDE = 100, 101, 102

#: A car whose centre is within this of its lane's centre has settled there [m]
#: (:attr:`mmpc.verify.TrafficAssumptions.change_offset`).
SETTLED_OFFSET = 0.5
#: A car that brakes hard leaves its follower (not the ego) this long to start braking too [s].
FOLLOWER_REACTION = 1.0
#: The ego moving across the road faster than this is moving into the next lane [m/s].
EGO_CROSSING_SPEED = 0.2


def threaten_lanes(state: VehicleState, threats: Threats, seeds: torch.Tensor, step: torch.Tensor,
                   config: SimConfig) -> VehicleState:
    """Target lanes after the cut-ins of this frame (module docstring); the timers of the cars
    that turned restart, as MOBIL's do.

    Args:
        state: the vehicles after MOBIL's decisions of this frame (slot 0 the ego).
        threats: the threats' settings.
        seeds, step: (E,) int64 each, the episodes' seeds and control steps (name the draws).
        config: the simulator's constants.
    """
    slots = torch.arange(state.x.shape[1], device=state.x.device)
    gap = state.x - state.x[:, :1]
    free = _deciding(state, config) & (gap > 0) & (gap < threats.reach)
    aimed = _ego_lanes(state, config)  # (E, L) bool
    options = []
    for side in (-1, 1):
        lane = (state.lane + side).clamp(0, config.lanes - 1)
        options.append(free & aimed.gather(1, lane) & _may_change(state, side, config))
    left, right = options
    seed = seeds[:, None]
    turns = (left | right) & (uniform(seed, _CUT_IN, step[:, None], slots) < threats.cut_in)
    go_right = right & (~left | (uniform(seed, _SIDE, step[:, None], slots) < 0.5))
    return _turn(state, turns, torch.where(go_right, 1, -1))


def threaten_speeds(state: VehicleState, acceleration: torch.Tensor, threats: Threats, seeds: torch.Tensor,
                    step: torch.Tensor, frequency: float, config: SimConfig) -> torch.Tensor:
    """(E, V) accelerations [m/s^2] after the braking and overtaking of this frame (module
    docstring), from the traffic's IDM ``acceleration`` (E, V); slot 0 (the ego) unchanged.

    Args:
        frequency: the scenario's control steps per second [Hz] (sizes the braking windows).
        Others as :func:`threaten_lanes`.
    """
    slots = torch.arange(state.x.shape[1], device=state.x.device)
    gap = state.x - state.x[:, :1]
    window = torch.div(step, max(1, round(threats.brake_window * frequency)), rounding_mode="floor")
    braking = ((gap > 0) & (gap < threats.reach) & _followers_stop(state, config)
               & (uniform(seeds[:, None], _BRAKE, window[:, None], slots) < threats.brake_share))
    passing = (state.lane - state.lane[:, :1]).abs() == 1  # beside the ego's lane, behind it
    passing &= (gap < 0) & (gap > -threats.reach) & threats.overtake
    speed = passing.long() - braking.long()  # a car is ahead or behind, never both
    return obey_speeds(state, acceleration, Orders(torch.zeros_like(speed), speed), config)


class Orders(NamedTuple):
    """Orders to single cars, carried out only within the rules (:func:`obey_lanes`, :func:`obey_speeds`).

    Fields:
        lane_change: (E, V) long, -1 / +1: change to the lane on that side at the car's next MOBIL
            decision, where it is settled and MOBIL's safety criterion allows it; 0: MOBIL decides.
        speed: (E, V) long, -1: brake as hard as IDM may (settled cars, to rest); +1: speed up as
            fast as IDM may (where IDM would not brake); 0: IDM.
    """

    lane_change: torch.Tensor
    speed: torch.Tensor


def obey_lanes(state: VehicleState, orders: Orders, config: SimConfig) -> VehicleState:
    """Target lanes after the lane orders that are legal this frame (:class:`Orders`), after MOBIL's decisions."""
    free = _deciding(state, config)
    side = orders.lane_change.clamp(-1, 1)
    turns = torch.zeros_like(free)
    for wanted in (-1, 1):
        turns |= free & (side == wanted) & _may_change(state, wanted, config)
    return _turn(state, turns, side)


def obey_speeds(state: VehicleState, acceleration: torch.Tensor, orders: Orders, config: SimConfig) -> torch.Tensor:
    """(E, V) accelerations [m/s^2] after the speed orders (:class:`Orders`), from IDM's ``acceleration``."""
    slots = torch.arange(state.x.shape[1], device=state.x.device)
    acting = state.alive & ~state.crashed & (slots > 0)
    braking = acting & (orders.speed < 0) & _settled(state, config)
    speeding = acting & (orders.speed > 0) & (acceleration >= 0)
    acceleration = torch.where(braking, _full_stop(state, config).to(acceleration.dtype), acceleration)
    return torch.where(speeding, _fastest(state, config).to(acceleration.dtype), acceleration)


def _deciding(state: VehicleState, config: SimConfig) -> torch.Tensor:
    """(E, V) bool: the other cars that MOBIL, at its decision of this frame, kept settled on their lane."""
    slots = torch.arange(state.x.shape[1], device=state.x.device)
    return (state.alive & ~state.crashed & state.lane_change_enabled & (slots > 0) & _settled(state, config)
            & (state.lane_change_timer == 0))  # MOBIL restarts the timer of the cars it evaluated


def _turn(state: VehicleState, turns: torch.Tensor, side: torch.Tensor) -> VehicleState:
    """The cars of ``turns`` (E, V) bool bound for the lane on their ``side`` (E, V), -1 / +1; their
    timers restart, as after MOBIL's own decision."""
    target = torch.where(turns, state.lane + side, state.target_lane)
    timer = torch.where(turns, torch.zeros_like(state.lane_change_timer), state.lane_change_timer)
    return state._replace(target_lane=target, lane_change_timer=timer)


def _may_change(state: VehicleState, side: int, config: SimConfig) -> torch.Tensor:
    """(E, V) bool: a change to the lane on ``side`` (-1 / +1) is on the road, passes MOBIL's safety
    criterion, and the car need not brake harder than that criterion allows behind its new leader."""
    lane = state.lane + side
    on_road = (lane >= 0) & (lane < config.lanes)
    query = torch.arange(state.x.shape[1], device=state.x.device).expand(state.x.shape)
    own_braking = idm_acceleration(state, lane, config) >= -config.lane_change_max_braking_imposed
    return on_road & mobil_safe(state, lane, config, query) & own_braking


def _full_stop(state: VehicleState, config: SimConfig) -> torch.Tensor:
    """(E, V) IDM's hardest braking, to rest and not beyond [m/s^2]."""
    return torch.maximum(torch.full_like(state.speed, -config.acc_max), -state.speed / config.dt)


def _fastest(state: VehicleState, config: SimConfig) -> torch.Tensor:
    """(E, V) IDM's largest acceleration, to the speed limit and not beyond [m/s^2]."""
    return ((config.speed_limit - state.speed) / config.dt).clamp(0.0, config.comfort_acc_max)


def _settled(state: VehicleState, config: SimConfig) -> torch.Tensor:
    """(E, V) bool: the car is on its target lane within :data:`SETTLED_OFFSET` of its centre."""
    offset = (state.y - state.lane.to(state.y.dtype) * config.lane_width).abs()
    return (state.lane == state.target_lane) & (offset < SETTLED_OFFSET)


def _followers_stop(state: VehicleState, config: SimConfig) -> torch.Tensor:
    """(E, V) bool: the car behind each car on its lane and target lane, unless that is the ego, stops behind it if
    both brake at ``acc_max``, the follower :data:`FOLLOWER_REACTION` later: a braking threat aims
    at the ego, not at a chain of IDM cars (their crashes push cars outside every assumption)."""
    stops = torch.ones_like(state.alive)
    for lane in (state.lane, state.target_lane):  # a car changing lane has a follower on both
        follower, found = vehicle_behind(state, lane, config)
        speed = state.speed.gather(1, follower)
        bumper_gap = state.x - state.x.gather(1, follower) - 0.5 * (state.length + state.length.gather(1, follower))
        needed = speed * FOLLOWER_REACTION + (speed ** 2 - state.speed ** 2).clamp_min(0.0) / (2 * config.acc_max)
        stops &= ~found | (follower == 0) | (bumper_gap > needed)
    return stops


def _ego_lanes(state: VehicleState, config: SimConfig) -> torch.Tensor:
    """(E, lanes) bool: the lanes the ego counts on (within ``lane_width / 2 + lane_margin`` of
    their centre, as MOBIL's neighbour search counts) and the one it is moving into."""
    lanes = torch.arange(config.lanes, device=state.x.device)
    centre = lanes.to(state.y.dtype) * config.lane_width
    ego_y = state.y[:, :1]
    counts = (ego_y - centre).abs() <= config.lane_width / 2 + config.lane_margin
    across = state.speed[:, :1] * torch.sin(state.heading[:, :1])
    nearest = state.lane[:, :1]
    moving_to = torch.where(across > EGO_CROSSING_SPEED, nearest + 1,
                            torch.where(across < -EGO_CROSSING_SPEED, nearest - 1, nearest))
    return counts | (lanes == moving_to)
