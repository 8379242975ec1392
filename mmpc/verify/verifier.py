"""The check: does a command keep a way out, whatever the other cars may do?

A candidate command of an environment is *verified* when the ego, after the command's control
period, has a fail-safe (:mod:`mmpc.verify.failsafe`) whose whole path, to rest, meets no
occupancy set (:mod:`mmpc.verify.occupancy`) of a car it answers for, the command's own period
included, and that keeps the ego's centre on the road (the lane rules the sets rest on are about
cars on their lanes). Every environment, candidate, fail-safe, car and time step is one tensor program.

What "meets" means is the worlds' collision rule, which looks one frame ahead: after each frame,
highway-env (and :mod:`mmpc.sim.collision`) crashes two cars at the next frame where their
rectangles, each swept by its speed x ``dt`` along its body heading, overlap on every one of the
eight separating axes. Where the ego's rectangle stretched forward by its own sweep misses a box
that holds the car and the car's sweep over that frame (the box of the interval that starts at
the pose), some of those axes separates the two: no crash. The sweep is ``speed x dt``, so it
matters most at low frequencies (a 0.5 s frame at 2 Hz sweeps 5 m at 10 m/s).
"""

from __future__ import annotations

import functools
import math
from typing import Callable, NamedTuple, Optional

import torch

from mmpc.compaction import capacity, compact, scatter
from mmpc.problem import EGO_V
from mmpc.road import Road
from mmpc.scenario import ScenarioConfig
from mmpc.sim.config import SimConfig
from mmpc.sim.traffic import sim_config
from mmpc.verify.assumptions import TrafficAssumptions
from mmpc.verify.compiling import CheckCompiling
from mmpc.verify.cut_ins import entry_floor, turn_frames
from mmpc.verify.failsafe import Body, FailSafeRollout, FailSafes, drive, ego_body, failsafe_command, failsafe_table
from mmpc.verify.geometry import rectangle_meets_box
from mmpc.verify.occupancy import Occupancy, held_variant, occupancy


#: With ``fixed_shapes``: the (car, pose) pairs per environment whose boxes come near a path get the
#: exact test in a buffer of this many per environment (an environment past it is not verified).
TRIPLES_PER_ENV = 1024

#: With ``fixed_shapes``: the cars per environment that may still cut in whose entry floors are computed.
PAIRS_PER_ENV = 8


class Verdict(NamedTuple):
    """The check of K candidate commands in E environments.

    Fields:
        verified: (E, K) bool, some fail-safe from the command's end verifies.
        lane: (E, K) long, the first such fail-safe's target lane (-1 where none).
        deceleration: (E, K), its deceleration [m/s^2] (NaN where none).
        crowded: (E,) bool, the environment's exact tests did not fit the buffer of a fixed-shape
            check (nothing of it verified; always False otherwise).
    """

    verified: torch.Tensor
    lane: torch.Tensor
    deceleration: torch.Tensor
    crowded: torch.Tensor


class Verifier:
    """Checks commands against the occupancy sets of the cars around each ego.

    Args:
        road: the road.
        sim: the worlds' constants (the ego's command path, the lane-change controller).
        assumptions: what the other cars may do.
        failsafes: the fail-safes tried from each end state.
        ego_size: the ego's (length, width) [m].
        margin: kept between the ego's footprint and every set [m]; it also holds the one-frame sweep
            across the road of a car the lane rule keeps in its band (``|vy| <= change_speed``), which
            the band does not widen by, so it must be at least ``change_speed x dt``.
        max_horizon: the longest fail-safe checked [s] (one that has not come to rest by then fails).
        compile: whether the fail-safe rollout and the occupancy sets run compiled
            (:class:`mmpc.verify.compiling.CheckCompiling`): ``"auto"``, ``True`` or ``False``.
        fixed_shapes: check without reading a value on the host, every shape known from the input's
            (one graph per step, :mod:`mmpc.compaction`): fail-safes over the whole horizon, the exact
            tests in buffers of :data:`TRIPLES_PER_ENV` and :data:`PAIRS_PER_ENV` per environment (an
            environment past them is not verified: safe, never wrong), values unchecked (a NaN or
            inf state, car or command is not verified).
    """

    def __init__(self, road: Road, sim: SimConfig = SimConfig(), assumptions: TrafficAssumptions = TrafficAssumptions(),
                 failsafes: FailSafes = FailSafes(), ego_size: tuple[float, float] = (5.0, 2.0), margin: float = 0.1,
                 max_horizon: float = 12.0, compile: bool | str = "auto", fixed_shapes: bool = False) -> None:
        if not (margin >= 0 and max_horizon > 0):
            raise ValueError(f"Verifier: `margin` must be >= 0 m and `max_horizon` > 0 s; got {margin!r}, {max_horizon!r}")
        if sim.simulation_frequency < sim.kp_heading:
            raise ValueError(
                f"Verifier: verification needs frames of at most 1 / kp_heading = {1 / sim.kp_heading:.2f} s, a simulation "
                f"frequency >= {sim.kp_heading:g} Hz (with longer frames the lane-keeping controller overshoots and the "
                f"cars leave the assumed headings and lateral speeds); got {sim.simulation_frequency:g} Hz")
        if margin < assumptions.change_speed * sim.dt - 1e-12:
            raise ValueError(f"Verifier: `margin` must cover the one-frame sweep across the road of a car the lane rule "
                             f"holds (change_speed x dt = {assumptions.change_speed * sim.dt:g} m); got {margin!r}")
        if sim.frames_per_command != 1:
            raise ValueError(f"Verifier: the check samples the ego once per command, so it needs one simulation frame per "
                             f"command; got {sim.simulation_frequency} Hz simulation for {sim.policy_frequency} Hz commands")
        if not isinstance(fixed_shapes, bool):
            raise TypeError(f"Verifier: `fixed_shapes` must be True or False; got {fixed_shapes!r}")
        self.road, self.sim, self.assumptions, self.failsafes = road, sim, assumptions, failsafes
        self.length, self.width = ego_size
        self.margin = margin
        self.period = 1.0 / sim.policy_frequency
        self.max_frames = max(1, math.ceil(max_horizon / self.period))
        self.compiling = CheckCompiling(compile)
        self.rollout = FailSafeRollout(self.length, road, sim, self.compiling)
        self.fixed_shapes = fixed_shapes

    @classmethod
    def for_scenario(cls, scenario: ScenarioConfig, **settings) -> "Verifier":
        """The check of a scenario's worlds: its road, command path and vehicle size, the ego's and the
        other cars' (``settings``: the other arguments).

        Raises:
            ValueError: a scenario the check cannot cover (a frequency below the lane-keeping controller's gain).
        """
        settings.setdefault("assumptions", TrafficAssumptions.for_scenario(scenario))
        return cls(scenario.road, sim_config(scenario), ego_size=scenario.vehicle, **settings)

    def body(self, ego: torch.Tensor) -> Body:
        """(E,) bodies of (E, 6) ego states."""
        return ego_body(ego, self.length)

    def failsafe_command(self, ego: torch.Tensor, lane: torch.Tensor, deceleration: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor]:
        """(E,) each: the fail-safe (``lane`` (E,) long, ``deceleration`` (E,)) law's command at the (E, 6) ``ego``."""
        return failsafe_command(self.body(ego), lane, deceleration.to(ego.dtype), self.length, self.road, self.sim)

    def failsafe_candidates(self, ego: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The first commands of every fail-safe from the (E, 6) ``ego``: (acceleration, steering), (E, F) each."""
        body = self.body(ego)
        lanes, decelerations = failsafe_table(body, self.road, self.failsafes)
        wide = Body(*(field[:, None].expand(lanes.shape) for field in body))
        return failsafe_command(wide, lanes, decelerations, self.length, self.road, self.sim)

    def frames(self, ego: torch.Tensor, vehicles: torch.Tensor, mask: torch.Tensor) -> int:
        """Fail-safe frames that bring every ego and every car's slowest motion to rest, and under the
        follower rule a turn's time more, until where a car may cut in has settled (at most the horizon;
        with :attr:`fixed_shapes` the horizon: a verdict does not change with frames past that)."""
        if self.fixed_shapes:
            return self.max_frames
        fastest = ego[:, EGO_V].amax() if ego.shape[0] else ego.new_zeros(())
        if mask.any():
            fastest_car = torch.hypot(vehicles[..., 2], vehicles[..., 3])[mask].amax()
            rest = torch.maximum(fastest / min(self.failsafes.decelerations), fastest_car / self.assumptions.max_deceleration)
        else:
            rest = fastest / min(self.failsafes.decelerations)
        settle = turn_frames(self.assumptions, self.period) + 1 if self.assumptions.cut_in == "follower" else 0
        return min(self.max_frames, int(math.ceil(float(rest) / self.period)) + 2 + settle)

    @torch.no_grad()
    def check(self, ego: torch.Tensor, vehicles: torch.Tensor, mask: torch.Tensor, acceleration: torch.Tensor,
              steering: torch.Tensor) -> Verdict:
        """Verify K candidate commands per environment.

        Args:
            ego: (E, 6) ego states now.
            vehicles: (E, M, 4) other cars' x, y [m], vx, vy [m/s] now.
            mask: (E, M) bool, present cars.
            acceleration, steering: (E, K) candidate commands [m/s^2], [rad].

        Returns:
            The :class:`Verdict`.

        Raises:
            ValueError: shapes other than these, or a NaN/inf state or command of a present car (with
                :attr:`fixed_shapes` such an environment's commands are not verified instead).
        """
        _check_inputs(ego, vehicles, mask, acceleration, steering, values=not self.fixed_shapes)
        num_envs, num_candidates = acceleration.shape
        if not num_envs:  # nothing to check (a fixed-shape buffer holds at least one entry)
            verified = torch.zeros(acceleration.shape, dtype=torch.bool, device=ego.device)
            return Verdict(verified, torch.full_like(verified, -1, dtype=torch.long),
                           torch.full_like(acceleration, float("nan")), verified.new_zeros(0))
        if self.fixed_shapes:  # what cannot be read is checked as zeros and not verified (below)
            finite_state, finite_commands = _finite(ego, vehicles, mask, acceleration, steering)
            readable = finite_state[:, None] & finite_commands  # (E, K)
            ego, vehicles = ego.nan_to_num(0.0, 0.0, 0.0), vehicles.nan_to_num(0.0, 0.0, 0.0)
            acceleration, steering = acceleration.nan_to_num(0.0, 0.0, 0.0), steering.nan_to_num(0.0, 0.0, 0.0)
        frames = self.frames(ego, vehicles, mask)
        times = torch.arange(frames + 3, dtype=ego.dtype, device=ego.device) * self.period  # an interval from each pose
        sets = self._occupancy(ego, vehicles, mask, times)
        now = self.body(ego)
        end = drive(Body(*(field[:, None].expand(num_envs, num_candidates) for field in now)), acceleration, steering,
                    self.length, self.sim)
        lanes, decelerations = failsafe_table(end, self.road, self.failsafes)  # (E, K, F)
        count = lanes.shape[-1]
        start = Body(*(field[..., None].expand(*lanes.shape) for field in end))
        path = self.rollout(start, lanes, decelerations, frames)  # (E, K, F, frames)
        poses = Body(*(torch.cat([a[:, None, None, None].expand(num_envs, num_candidates, count, 1),
                                  b[..., None, None].expand(num_envs, num_candidates, count, 1), c], dim=-1)
                       for a, b, c in zip(now, end, path)))  # (E, K, F, frames + 2) at times[:-1]
        meets, crowded = self._meets(poses, sets, mask, vehicles, times)  # (E, K, F), (E,)
        left, right = self.road.bounds  # the lane rules hold for an ego on its lanes: it keeps its centre there
        on_road = ((poses.y[..., 1:] >= left) & (poses.y[..., 1:] <= right)).all(dim=-1)
        verified_f = ~meets & on_road
        if self.fixed_shapes:
            verified_f &= readable[..., None]
        verified = verified_f.any(dim=-1)
        first = verified_f.int().argmax(dim=-1, keepdim=True)
        lane = torch.where(verified, lanes.gather(-1, first)[..., 0], -1)
        deceleration = torch.where(verified, decelerations.gather(-1, first)[..., 0],
                                   torch.full_like(decelerations[..., 0], float("nan")))
        return Verdict(verified, lane, deceleration, crowded)

    def _occupancy(self, ego: torch.Tensor, vehicles: torch.Tensor, mask: torch.Tensor, times: torch.Tensor) -> Occupancy:
        """:func:`mmpc.verify.occupancy.occupancy` of the cars the ego may meet, compiled where :attr:`compiling` says."""
        if torch.compiler.is_compiling():  # inside a caller's graph
            return occupancy(ego, vehicles, mask, self.road, times, self.assumptions)
        if self.compiling.compiled and ego.shape[0] and ego.device.type == "cpu":  # compiled for the CPU, as the rollout
            sets = _compiled_occupancy(self.road, self.assumptions)
            found = self.compiling.attempt(lambda: sets(ego, vehicles, mask, times))
            if found is not None:
                return found
        return self.compiling.eager(occupancy, ego, vehicles, mask, self.road, times, self.assumptions)

    def _meets(self, poses: Body, sets: Occupancy, mask: torch.Tensor, vehicles: torch.Tensor, times: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor]:
        """(E, K, F) bool: a path of ``poses`` (E, K, F, P) meets a set of ``sets`` (P intervals of
        ``times``): pose i, stretched forward by its frame's sweep (module docstring), against the
        box of interval i, and for a car that may still cut in (:attr:`Occupancy.enters`) against
        its uncut band past where it could enter on this path. Only the (environment, car, pose)
        triples whose bounding boxes overlap get the exact test; with :attr:`fixed_shapes` in a buffer,
        and an environment past it meets everything: (E,) bool, those environments."""
        variant = held_variant(sets.ego_lanes, poses.y, self.road, self.assumptions.lane_margin)  # (E, K, F)
        sweep = poses.speed.clamp_min(0.0) * self.sim.dt  # (E, K, F, P) [m]
        cos, sin = torch.cos(poses.heading), torch.sin(poses.heading)
        x, y = poses.x + 0.5 * sweep * cos, poses.y + 0.5 * sweep * sin  # the swept rectangle's centre
        half_length = 0.5 * self.length + self.margin + 0.5 * sweep
        half_width = 0.5 * self.width + self.margin
        reach = torch.hypot(half_length.amax() if half_length.numel() else half_length.new_zeros(()),
                            half_length.new_tensor(half_width))
        flat_x, flat_y = x.flatten(1, 2), y.flatten(1, 2)  # (E, K F, P)
        near = ((flat_x.amin(dim=1)[:, None] - reach <= sets.x_high) & (flat_x.amax(dim=1)[:, None] + reach >= sets.x_low)
                & (flat_y.amin(dim=1)[:, None] - reach <= sets.y_high.amax(dim=1))
                & (flat_y.amax(dim=1)[:, None] + reach >= sets.y_low.amin(dim=1)) & mask[..., None])
        num_envs = near.shape[0]
        triples = compact(near, self._capacity(num_envs, TRIPLES_PER_ENV, near.numel()))
        env, car, pose = triples.index  # (Q,)
        meets = torch.zeros(variant.shape, dtype=torch.int32, device=variant.device)
        if env.numel():  # with fixed shapes the buffer's size, known before the data
            chosen = variant[env]  # (Q, K, F)
            rows = torch.arange(env.numel(), device=env.device)[:, None, None]
            y_low = sets.y_low[env, :, car, pose][rows, chosen]
            y_high = sets.y_high[env, :, car, pose][rows, chosen]
            x_low, x_high = sets.x_low[env, car, pose, None, None], sets.x_high[env, car, pose, None, None]
            rectangle = (x[env, ..., pose], y[env, ..., pose], poses.heading[env, ..., pose], half_length[env, ..., pose],
                         half_width)
            hit = rectangle_meets_box(*rectangle, x_low, x_high, y_low, y_high)
            # the triples of cars that may still cut in: the cheap floor first, the full one where the cheap one meets
            entering = compact(sets.enters[env, car] & triples.valid, env.numel() if self.fixed_shapes else None,
                               fill=env.numel())
            for moving in (False, True):
                if not entering.index[0].numel():
                    break
                which = entering.index[0].clamp_max(env.numel() - 1)  # (Q',): the padding reads the last triple
                floor, known = self._entry_floor(poses, vehicles, times, env[which], car[which], pose[which],
                                                 entering.valid, moving)
                entered = rectangle_meets_box(*(part[which] for part in rectangle[:4]), half_width,
                                              torch.maximum(x_low[which], floor), x_high[which],
                                              sets.y_low[env[which], 0, car[which], pose[which], None, None],
                                              sets.y_high[env[which], 0, car[which], pose[which], None, None])
                entered = (entered | ~known[:, None, None]) & entering.valid[:, None, None]  # a pair past its buffer: met
                if moving:
                    hit = scatter(hit, 0, entering.index[0], hit[which] | entered)
                else:
                    still = entered.flatten(1).any(dim=1)  # (Q',), False on the padding
                    entering = entering._replace(valid=still)
                    if not self.fixed_shapes:  # the exact path keeps only those
                        entering = entering._replace(index=(entering.index[0][still],), valid=still[still])
            meets.index_add_(0, env, (hit & triples.valid[:, None, None]).int())
        crowded = triples.dropped.flatten(1).any(dim=1)  # (E,): an environment past the buffer is not verified
        return (meets > 0) | crowded[:, None, None], crowded

    def _entry_floor(self, poses: Body, vehicles: torch.Tensor, times: torch.Tensor, env: torch.Tensor, car: torch.Tensor,
                     pose: torch.Tensor, valid: torch.Tensor, moving: bool) -> tuple[torch.Tensor, torch.Tensor]:
        """Where the cars ``car`` of environments ``env`` (Q,) could be at ``pose`` (Q,) had they decided
        to cut in on each path (:func:`mmpc.verify.cut_ins.entry_floor`, once per (environment, car)
        pair of the ``valid`` (Q,) triples): (Q, K, F) floors [m] and (Q,) bool, whether the pair found
        room in the buffer of :data:`PAIRS_PER_ENV` (with :attr:`fixed_shapes`; else always)."""
        num_envs, num_cars = vehicles.shape[:2]
        key = env * num_cars + car  # (Q,)
        wanted = torch.zeros(num_envs * num_cars, dtype=torch.int32, device=env.device).index_add_(0, key, valid.int()) > 0
        pairs = compact(wanted, self._capacity(num_envs, PAIRS_PER_ENV, wanted.numel()), fill=wanted.numel())
        flat = pairs.index[0]  # (N,) padding: one past the last pair
        slot = scatter(torch.full_like(wanted, -1, dtype=torch.long), 0, flat, torch.arange(flat.numel(), device=env.device))
        pair = flat.clamp_max(wanted.numel() - 1)
        pair_env, pair_car = pair // num_cars, pair % num_cars
        floor = entry_floor(poses.x[pair_env], poses.speed[pair_env], vehicles[pair_env, pair_car], times, self.assumptions,
                            moving, frame=self.period)  # (N, K, F, P)
        which = slot[key]  # (Q,) -1: the pair is past the buffer
        return floor[which.clamp_min(0), ..., pose], which >= 0

    def _capacity(self, num_envs: int, per_env: int, most: int) -> Optional[int]:
        """A buffer of ``per_env`` entries per environment, at most ``most``, with :attr:`fixed_shapes`; else ``None``."""
        return capacity(self.fixed_shapes, num_envs, per_env, per_env, most)


@functools.lru_cache(maxsize=None)
def _compiled_occupancy(road: Road, assumptions: TrafficAssumptions) -> Callable[..., Occupancy]:
    """The occupancy sets of a road and assumptions, compiled for any numbers of environments, cars and times."""

    def sets(ego: torch.Tensor, vehicles: torch.Tensor, mask: torch.Tensor, times: torch.Tensor) -> Occupancy:
        return occupancy(ego, vehicles, mask, road, times, assumptions)

    return torch.compile(sets, dynamic=True, fullgraph=True)


def _check_inputs(ego: torch.Tensor, vehicles: torch.Tensor, mask: torch.Tensor, acceleration: torch.Tensor,
                  steering: torch.Tensor, values: bool = True) -> None:
    """:meth:`Verifier.check`'s inputs: shapes that agree and (``values``: read on the host) finite
    values, or a ValueError saying what came."""
    envs = ego.shape[0] if ego.dim() == 2 else -1
    if ego.dim() != 2 or ego.shape[1] != 6:
        raise ValueError(f"`ego` must be (E, 6) ego states; got shape {tuple(ego.shape)}")
    if vehicles.dim() != 3 or vehicles.shape[0] != envs or vehicles.shape[2] != 4:
        raise ValueError(f"`vehicles` must be (E={envs}, M, 4) x, y, vx, vy; got shape {tuple(vehicles.shape)}")
    if mask.shape != vehicles.shape[:2] or mask.dtype != torch.bool:
        raise ValueError(f"`mask` must be a bool tensor of shape {tuple(vehicles.shape[:2])}; got {mask.dtype} {tuple(mask.shape)}")
    if acceleration.dim() != 2 or acceleration.shape[0] != envs or steering.shape != acceleration.shape:
        raise ValueError(f"`acceleration` and `steering` must be (E={envs}, K) each; got {tuple(acceleration.shape)} "
                         f"and {tuple(steering.shape)}")
    if not values:
        return
    finite_state, finite_commands = _finite(ego, vehicles, mask, acceleration, steering)
    if not bool(finite_state.all()):
        raise ValueError("the ego states and the present cars must be finite; got NaN or inf")
    if not bool(finite_commands.all()):
        raise ValueError("the candidate commands must be finite; got NaN or inf")


def _finite(ego: torch.Tensor, vehicles: torch.Tensor, mask: torch.Tensor, acceleration: torch.Tensor,
            steering: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(E,) bool: the ego state and the present cars finite; (E, K) bool: the command finite."""
    state = ego.isfinite().all(dim=1) & (vehicles.isfinite().all(dim=2) | ~mask).all(dim=1)
    return state, acceleration.isfinite() & steering.isfinite()
