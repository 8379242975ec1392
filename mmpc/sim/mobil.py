"""Lane changes of the other vehicles: highway-env's ``IDMVehicle.change_lane_policy`` and
``mobil``, batched.

Every frame, before the commands, each IDM vehicle that is not crashed and may change lane:

- if it is off its target lane (a change under way), aborts the change (target := current
  lane) when another IDM vehicle, not on that target lane but heading for it, is ahead by
  ``0 < d < d*`` (``d*`` the IDM desired gap of the aborting vehicle behind it). highway-env
  lets the vehicles act in slot order, so a vehicle sees the targets the earlier slots chose
  in this frame and the later slots' targets of the previous frame; this rule is the one
  sequential step here (a loop over the slots);
- otherwise, once its timer exceeds ``lane_change_delay``, restarts the timer and asks MOBIL
  about the left (lane - 1) then the right (lane + 1) neighbour lane; the later accepted one
  wins. A candidate lane must exist, lie within two lane widths and the vehicle must move at
  1 m/s or more. With the new leader/follower on the candidate lane and the old ones on the
  current lane, and every acceleration ``a(follower, leader)`` the IDM of
  :func:`mmpc.sim.idm.idm_between` with the deciding vehicle's exponent, MOBIL accepts when::

      a(new follower, me) >= -lane_change_max_braking_imposed                      (safety)
      a(me, new leader) - a(me, old leader) + politeness * (a(new follower, me) - a(new follower, new leader)
          + a(old follower, old leader) - a(old follower, me)) >= lane_change_min_acc_gain

  A missing follower contributes 0 (highway-env's ``acceleration(None) = 0``).

The ego (slot 0) never decides and, being highway-env's plain ``Vehicle`` under the project's
continuous actions, has no target speed: as a follower MOBIL reads it as 0, which ``not_zero``
makes 0.01 m/s, so the predicted braking of a moving ego is huge and no IDM vehicle cuts in
directly ahead of it. It does not count in the abort rule either (not a ``ControlledVehicle``).
With ``SimConfig.ego_as_follower`` MOBIL reads the ego's present speed as its target speed instead
(an IDM follower that holds its speed), and cars cut in ahead of it where that follower would brake
at most ``lane_change_max_braking_imposed``.

Every vehicle's timer then grows by dt with the frame (:func:`advance_timers`).
"""

from __future__ import annotations

from typing import Optional

import torch

from mmpc.compaction import capacity, compact
from mmpc.sim.config import SimConfig
from mmpc.sim.idm import desired_gap, idm_between, vehicle_ahead, vehicle_behind
from mmpc.sim.state import VehicleState

#: MOBIL's buffer: evaluations per environment per frame on average (traffic asks ~1.9: each vehicle
#: once a second), and at least one per vehicle of one environment.
EVALUATIONS_PER_ENV = 3.0


def mobil_accepts(state: VehicleState, candidate: torch.Tensor, config: SimConfig,
                  query: Optional[torch.Tensor] = None) -> torch.Tensor:
    """(E, Q) bool: MOBIL recommends lane ``candidate`` (E, Q) int64 (any value; lanes off the
    road, out of reach or a vehicle below 1 m/s are refused) to each vehicle of ``query`` (E, Q)
    int64 slots (default: every slot, Q = V)."""
    possible, safe, gain = _mobil(state, candidate, config, query)
    return possible & safe & (gain >= config.lane_change_min_acc_gain)


def mobil_safe(state: VehicleState, candidate: torch.Tensor, config: SimConfig,
               query: Optional[torch.Tensor] = None) -> torch.Tensor:
    """(E, Q) bool: a change to lane ``candidate`` is possible for each vehicle of ``query`` and
    passes MOBIL's safety criterion, whatever it gains (arguments as :func:`mobil_accepts`)."""
    possible, safe, _ = _mobil(state, candidate, config, query)
    return possible & safe


def _mobil(state: VehicleState, candidate: torch.Tensor, config: SimConfig, query: Optional[torch.Tensor]
           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """MOBIL's three parts, (E, Q) each: the change is possible (lane on the road, within reach,
    the vehicle moving), it is safe (the new follower brakes no harder than allowed), its gain [m/s^2]."""
    own = torch.arange(state.x.shape[1], device=state.x.device).expand(state.x.shape) if query is None else query
    everyone = torch.ones_like(own, dtype=torch.bool)
    delta = torch.gather(state.idm_delta, 1, own)
    ego_target = state.speed[:, :1] if config.ego_as_follower else torch.zeros_like(state.target_speed[:, :1])
    target_speed = torch.cat([ego_target.to(state.target_speed.dtype), state.target_speed[:, 1:]], dim=1)
    on_road = (candidate >= 0) & (candidate < config.lanes)
    lane = candidate.clamp(0, config.lanes - 1)
    current_lane = torch.gather(state.lane, 1, own)
    new_leader, has_new_leader = vehicle_ahead(state, lane, config, own)
    new_follower, has_new_follower = vehicle_behind(state, lane, config, own)
    old_leader, has_old_leader = vehicle_ahead(state, current_lane, config, own)
    old_follower, has_old_follower = vehicle_behind(state, current_lane, config, own)

    def idm(follower, has_follower, leader, has_leader):
        return idm_between(state, follower, has_follower, leader, has_leader, delta, target_speed, config)

    new_follower_before = idm(new_follower, has_new_follower, new_leader, has_new_leader)
    new_follower_after = idm(new_follower, has_new_follower, own, everyone)
    self_after = idm(own, everyone, new_leader, has_new_leader)
    self_before = idm(own, everyone, old_leader, has_old_leader)
    old_follower_before = idm(old_follower, has_old_follower, own, everyone)
    old_follower_after = idm(old_follower, has_old_follower, old_leader, has_old_leader)
    gain = self_after - self_before + config.politeness * (
        new_follower_after - new_follower_before + old_follower_after - old_follower_before)
    safe = new_follower_after >= -config.lane_change_max_braking_imposed
    y, speed = torch.gather(state.y, 1, own), torch.gather(state.speed, 1, own)
    reachable = (y - lane.to(y.dtype) * config.lane_width).abs() <= 2 * config.lane_width
    return on_road & reachable & (speed.abs() >= 1), safe, gain


def abort_blockers(state: VehicleState, config: SimConfig) -> torch.Tensor:
    """(E, V, V) bool: [e, i, j] IDM vehicle j is ahead of vehicle i by ``0 < d < d*`` (i's
    desired gap behind j) and not on i's target lane: j would abort i's change if heading for it."""
    num_vehicles = state.x.shape[1]
    slots = torch.arange(num_vehicles, device=state.x.device)
    gap = desired_gap(state.speed[:, :, None], state.heading[:, :, None],
                      state.speed[:, None, :], state.heading[:, None, :], config)
    distance = state.x[:, None, :] - state.x[:, :, None]
    other = (slots[:, None] != slots[None, :]) & (slots[None, :] > 0) & state.alive[:, None, :]
    off_target = state.lane[:, None, :] != state.target_lane[:, :, None]
    return other & off_target & (distance > 0) & (distance < gap)


def change_lanes(state: VehicleState, config: SimConfig) -> VehicleState:
    """One frame of lane-change decisions (module docstring): new ``target_lane`` and
    restarted ``lane_change_timer`` of the vehicles that evaluated MOBIL."""
    num_vehicles = state.x.shape[1]
    slots = torch.arange(num_vehicles, device=state.x.device)
    deciding = state.alive & ~state.crashed & state.lane_change_enabled & (slots > 0)
    changing = state.lane != state.target_lane
    evaluating = deciding & ~changing & (state.lane_change_timer > config.lane_change_delay)
    decided, evaluating = _mobil_decisions(state, evaluating, config)
    blockers = abort_blockers(state, config)
    aborting = deciding & changing
    target = state.target_lane.clone()
    for slot in range(1, num_vehicles):  # earlier slots already hold this frame's targets, later ones the last frame's
        heading_there = target == state.target_lane[:, slot:slot + 1]
        abort = aborting[:, slot] & (blockers[:, slot] & heading_there).any(dim=1)
        target[:, slot] = torch.where(evaluating[:, slot], decided[:, slot],
                                      torch.where(abort, state.lane[:, slot], target[:, slot]))
    timer = torch.where(evaluating, torch.zeros_like(state.lane_change_timer), state.lane_change_timer)
    return state._replace(target_lane=target, lane_change_timer=timer)


def _mobil_decisions(state: VehicleState, evaluating: torch.Tensor, config: SimConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """(E, V) the lane MOBIL picks (left, then right, the later accepted winning; else the
    current lane) for the ``evaluating`` vehicles, the current lane elsewhere; and (E, V) bool,
    the vehicles evaluated. Only the evaluating vehicles are asked, each with a copy of its
    environment (``config.fixed_shapes``: in a buffer of :data:`EVALUATIONS_PER_ENV` per environment,
    :mod:`mmpc.compaction`; those past it are evaluated at the next frame)."""
    num_envs, num_vehicles = state.x.shape
    buffer = capacity(config.fixed_shapes, num_envs, EVALUATIONS_PER_ENV, num_vehicles, num_envs * num_vehicles)
    found = compact(evaluating, buffer)
    env, slot = found.index  # the padding points at (0, 0), the ego, which never evaluates
    if buffer is None and env.numel() == 0:  # exact sizes: nobody asks this frame
        return state.lane.clone(), evaluating
    copies = VehicleState(*(torch.cat([field[env], field[env]]) for field in state))  # (2K, V): left, then right
    lane = state.lane[env, slot]
    query = torch.cat([slot, slot])[:, None]
    left, right = mobil_accepts(copies, torch.cat([lane - 1, lane + 1])[:, None], config, query)[:, 0].chunk(2)
    decided = state.lane.clone()
    decided[env, slot] = torch.where(found.valid & right, lane + 1, torch.where(found.valid & left, lane - 1, lane))
    return decided, evaluating & ~found.dropped


def advance_timers(state: VehicleState, config: SimConfig) -> VehicleState:
    """Every present vehicle's lane-change timer grown by one frame, ``config.dt`` [s]
    (highway-env's ``IDMVehicle.step``, crashed vehicles included)."""
    return state._replace(lane_change_timer=torch.where(state.alive, state.lane_change_timer + config.dt,
                                                        state.lane_change_timer))
