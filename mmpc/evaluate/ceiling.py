"""The ceiling: how well a driver could do on a seed, found by a search that knows the future.

On the batched simulator the traffic is a function of the ego's commands (its draws are keyed on
the seed and the step), so an episode is a tree of command sequences. :func:`search_ceiling` runs
a beam search over that tree for several seeds at once: every control step each node of the beam
branches into the multi-modal MPC's whole candidate set (every feasible goal's first command and
the chosen plan's), the chosen command with the guard's braking variants
(:data:`mmpc.verify.guard.BRAKING`) and the fail-safes' first commands, each child a clone of the
simulator state (:meth:`mmpc.sim.SimEpisodes.take`). Children are ranked by the scenario's score
(distance travelled at high speed, the meta cost's sum in cruise) or by highway-env's task reward
summed over the frames (``rank="task_return"``) or the distance in any scenario (``"distance"``),
one per cell of ego state kept,
with a share of the beam reserved for each lane so that a pass that first brakes survives
long enough to pay off.

``verify=True`` keeps only children whose command keeps a verified way out by the same check
the verified driver uses (:class:`mmpc.verify.Verifier`), or that continue the fail-safe
verified at the node's last step, as :class:`mmpc.verify.Guard` does: the *verified ceiling*.
``verify=False`` keeps every child that does not collide: the *unprotected ceiling*. Their
difference is what the check's assumptions cost; (verified ceiling - ``verified:mpc``) is what a
better causal driver could win back.

The driver the ceiling bounds (``verified:mpc`` or ``mpc``) drives one node of each beam, never
pruned, with its own warm starts; its children branch as every node's do. The ceiling therefore
includes the driver's own episode and is at or above it on every seed by construction.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, NamedTuple, Optional, Sequence

import torch

from mmpc.config import require, require_field_types, require_int, require_positive
from mmpc.drivers import Driver, Observation, make_driver
from mmpc.drivers.registry import check_spec
from mmpc.problem import EGO_V, EGO_X, EGO_Y
from mmpc.scenario import CruiseObjective, ScenarioConfig, build_mpc
from mmpc.sim import SimEpisodes
from mmpc.sim.reward import highway_reward
from mmpc.sim.state import lane_of, on_road
from mmpc.task_reward import HighwayReward
from mmpc.verify import Verifier
from mmpc.verify.failsafe import Body, drive, failsafe_table
from mmpc.verify.guard import BRAKING


#: What the search can maximise (:attr:`CeilingConfig.rank`).
RANKS = ("scenario", "task_return", "distance")


@dataclass(frozen=True)
class CeilingConfig:
    """The beam search's settings.

    Attributes:
        beam: nodes kept per seed after each control step.
        verify: keep only children whose command verifies (or that continue the node's verified
            fail-safe); ``False``: every child that does not collide.
        screened: per seed, ``screened x beam`` of the best-ranked children are checked (the
            check is the search's dearest part); the beam is chosen among those that verify.
        cell: a child per cell of (x [m], y [m], speed [m/s]) of the ego's state after the step
            is kept, the best-ranked: near-equal states crowd out the others otherwise.
        branch_period: the beam branches at least this often [s] (every control step where the
            scenario's period is longer); between branchings each node drives its mode, the goal it
            chose re-planned alone or the fail-safe it chose, behind the guard's order.
        siblings: at most this many children of one node are kept before the others' (a beam
            of one node's near-equal children is a beam of one idea).
        driver: the driver the ceiling bounds, driving one node of each beam (a driver spec:
            ``verified:mpc``, ``mpc``); ``None``: the scenario's MPC behind the check where
            ``verify``, alone otherwise.
        rank: what the search maximises: ``"scenario"``, the scenario's score (distance at high
            speed, minus the meta cost in cruise); ``"task_return"``, highway-env's reward
            (:class:`mmpc.task_reward.HighwayReward`) summed over the frames, as the RL agents' task;
            ``"distance"``, the distance travelled in any scenario (how fast a driver could go).
    """

    beam: int = 64
    verify: bool = True
    screened: int = 3
    cell: tuple[float, float, float] = (0.25, 0.25, 0.1)
    driver: Optional[str] = None
    branch_period: float = 0.5
    siblings: int = 8
    rank: str = "scenario"

    def __post_init__(self) -> None:
        require_field_types(self)
        require(self.rank in RANKS, f"CeilingConfig: `rank` must be one of {list(RANKS)}; got {self.rank!r}")
        require_int("CeilingConfig", low=1, beam=self.beam, screened=self.screened, siblings=self.siblings)
        require_positive("CeilingConfig", branch_period=self.branch_period, cell_x=self.cell[0], cell_y=self.cell[1],
                         cell_speed=self.cell[2])
        if self.driver is not None:
            check_spec(self.driver)

    @property
    def driver_spec(self) -> str:
        """The bounded driver's spec."""
        return self.driver or ("verified:mpc" if self.verify else "mpc")


class SeedCeiling(NamedTuple):
    """The search on one seed: its best episode and the bounded driver's.

    Fields:
        seed: the episode seed.
        score: the best node's score (higher is better: distance [m] at high speed, minus the
            meta cost's mean in cruise; with ``rank="task_return"`` the task return, with
            ``"distance"`` the distance).
        mean_speed, meta_cost, distance: the best episode's mean speed [m/s] and meta-cost mean
            over its steps' states, and the distance travelled [m].
        task_return: its highway-env reward summed over the states after each step (the
            evaluation's ``task_return``).
        crashed: every node of the beam collided (no episode left; the figures are NaN).
        driver_score, driver_mean_speed, driver_meta_cost, driver_distance, driver_task_return: the same for the
            bounded driver's episode (up to its collision, if any).
        driver_crashed: the driver's episode ended in a collision.
        nodes_crashed: beam nodes that collided over the search (with ``verify``: a car left the
            assumptions the check rests on).
        commands: the best episode's commands, one (acceleration [m/s^2], steering [rad]) per
            control step: replayed from the seed they drive it again (empty where ``crashed``).
    """

    seed: int
    score: float
    mean_speed: float
    meta_cost: float
    distance: float
    task_return: float
    crashed: bool
    driver_score: float
    driver_mean_speed: float
    driver_meta_cost: float
    driver_distance: float
    driver_task_return: float
    driver_crashed: bool
    nodes_crashed: int
    commands: list[tuple[float, float]]


#: A node's mode between branchings: a goal index (>= 0) of the MPC's problem, or holding a fail-safe.
FAILSAFE = -1


class _Beam(NamedTuple):
    """The N = S x beam nodes, seed-major; every field (N,)."""

    seed: torch.Tensor  # long, which of the S seeds
    alive: torch.Tensor  # bool, not collided
    driver: torch.Tensor  # bool, the bounded driver's node
    distance: torch.Tensor  # float64 [m] since the start
    speed_sum: torch.Tensor  # float64, the states' speeds summed [m/s]
    cost_sum: torch.Tensor  # float64, the states' meta-cost terms summed
    reward_sum: torch.Tensor  # float64, the task rewards of the states after each step summed
    lane: torch.Tensor  # long, the fail-safe verified at the node's last step (-1: none)
    deceleration: torch.Tensor  # float64, its deceleration [m/s^2] (NaN: none)
    mode: torch.Tensor  # long, what the node drives until the next branching: a goal index or FAILSAFE
    hold_lane: torch.Tensor  # long, the held fail-safe's lane (mode FAILSAFE)
    hold_deceleration: torch.Tensor  # float64, its deceleration [m/s^2]
    commands: torch.Tensor  # (N, T, 2) float64, the commands driven so far (acceleration [m/s^2], steering [rad])


class _Children(NamedTuple):
    """(N, K) every node's children, K kinds of command in the guard's order of preference."""

    acceleration: torch.Tensor  # [m/s^2]
    steering: torch.Tensor  # [rad]
    usable: torch.Tensor  # bool, a command to try
    known: torch.Tensor  # bool, valid without a check: the bounded driver's own, the fail-safe verified last
    mode: torch.Tensor  # long, the child's mode (a goal index or FAILSAFE)
    hold_lane: torch.Tensor  # long
    hold_deceleration: torch.Tensor  # float64
    target: torch.Tensor  # long, the lane the child heads for (its goal's, its fail-safe's)


class _Checks(NamedTuple):
    """What is known of C flat children: valid (C,) bool (verified, or valid without a check), and
    where the check verified one, its first verified fail-safe's lane (C,) long (-1: not checked
    or not verified) and deceleration (C,) float64 [m/s^2]."""

    valid: torch.Tensor
    lane: torch.Tensor
    deceleration: torch.Tensor

    @classmethod
    def unchecked(cls, known: torch.Tensor) -> "_Checks":
        return cls(known.clone(), torch.full(known.shape, -1, dtype=torch.long),
                   torch.full(known.shape, float("nan"), dtype=torch.float64))

    def record(self, index: torch.Tensor, verdict) -> None:
        """Write a :class:`mmpc.verify.Verdict` of K = 1 for the flat children ``index`` (R,)."""
        now = verdict.verified[:, 0]
        self.valid[index] |= now
        self.lane[index[now]] = verdict.lane[now, 0]
        self.deceleration[index[now]] = verdict.deceleration[now, 0].double()


def search_ceiling(scenario: ScenarioConfig, seeds: Sequence[int], config: CeilingConfig = CeilingConfig(), *,
                   progress: Optional[Callable[[int, int, float], None]] = None) -> list[SeedCeiling]:
    """The ceiling of ``scenario`` on each seed (module docstring), all seeds searched together.

    Args:
        scenario: a scenario of the batched simulator (naturalistic or threatening traffic).
        seeds: S episode seeds (distinct).
        config: the search's settings.
        progress: called after each control step with (step, steps, seconds so far).

    Returns:
        One :class:`SeedCeiling` per seed, in the order of ``seeds``.
    """
    seeds = [int(seed) for seed in seeds]
    if not seeds or len(set(seeds)) != len(seeds):
        raise ValueError(f"`seeds` must hold at least one seed, each once; got {seeds}")
    steps = int(round(scenario.duration * scenario.frequency))
    search = _Search(scenario, seeds, config, steps)
    start = time.perf_counter()
    for step in range(steps):
        search.step()
        if progress is not None:
            progress(step + 1, steps, time.perf_counter() - start)
    return search.results(steps)


class _Search:
    """The beam search's state and its control step (:func:`search_ceiling`)."""

    def __init__(self, scenario: ScenarioConfig, seeds: list[int], config: CeilingConfig, steps: int) -> None:
        self.scenario, self.seeds, self.config = scenario, seeds, config
        count, width = len(seeds), config.beam
        self.sim = SimEpisodes(scenario, [seed for seed in seeds for _ in range(width)])
        self.mpc = build_mpc(scenario)
        self.verifier = Verifier.for_scenario(scenario)
        self.driver: Driver = make_driver(config.driver_spec, scenario)
        self.driver.reset(count)
        self.road = scenario.road
        self.cruise = isinstance(scenario.objective, CruiseObjective)
        self.reward = HighwayReward()
        self.branch_every = max(1, int(config.branch_period * scenario.frequency + 1e-9))
        nodes = count * width
        double = dict(dtype=torch.float64)
        first = torch.zeros(nodes, dtype=torch.bool)
        first[::width] = True  # at the start the nodes of a seed are one state: the others are copies
        self.beam = _Beam(
            seed=torch.arange(count).repeat_interleave(width), alive=first.clone(), driver=first.clone(),
            distance=torch.zeros(nodes, **double), speed_sum=torch.zeros(nodes, **double), cost_sum=torch.zeros(nodes, **double),
            reward_sum=torch.zeros(nodes, **double),
            lane=torch.full((nodes,), -1, dtype=torch.long), deceleration=torch.full((nodes,), float("nan"), **double),
            mode=torch.zeros(nodes, dtype=torch.long), hold_lane=torch.zeros(nodes, dtype=torch.long),
            hold_deceleration=torch.zeros(nodes, **double), commands=torch.zeros(nodes, steps, 2, **double))
        self.driver_final: dict[int, tuple[float, float, float, float]] = {}  # seed index -> a crashed driver's figures
        self.nodes_crashed = torch.zeros(count, dtype=torch.long)
        self.steps = 0

    def step(self) -> None:
        """One control step: branch every node and keep the beam (every ``branch_period``), or
        drive each node's mode behind the guard's order (between branchings)."""
        beam = self.beam
        ego, vehicles, mask = (field.cpu() for field in self.sim.road_state())
        speed, lateral = ego[:, EGO_V].double(), ego[:, EGO_Y].double()
        beam = beam._replace(speed_sum=beam.speed_sum + speed, cost_sum=beam.cost_sum + self._stage_cost(speed, lateral))
        asked = self._driver_commands(ego, vehicles, mask, beam)
        if self.steps % self.branch_every == 0:
            children = self._branches(ego, vehicles, mask, beam, asked)
            picked, kept, checks = self._keep(ego, vehicles, mask, beam, children)
        else:
            children = self._holds(ego, vehicles, mask, beam, asked)
            picked, kept, checks = self._hold(ego, vehicles, mask, beam, children)
        self._advance(beam, children, picked, kept, checks)

    def _driver_commands(self, ego: torch.Tensor, vehicles: torch.Tensor, mask: torch.Tensor, beam: _Beam) -> torch.Tensor:
        """(N, 2) the bounded driver's command on its nodes, NaN elsewhere."""
        drivers = beam.driver.nonzero().squeeze(1)
        asked = torch.full((ego.shape[0], 2), float("nan"), dtype=ego.dtype)
        if drivers.numel():
            observation = Observation(ego[drivers], vehicles[drivers], mask[drivers], None, env_ids=beam.seed[drivers])
            decision = self.driver.decide(observation)
            asked[drivers] = torch.stack([decision.acceleration, decision.steering], dim=1).cpu().to(ego.dtype)
        return asked

    def _branches(self, ego: torch.Tensor, vehicles: torch.Tensor, mask: torch.Tensor, beam: _Beam,
                  asked: torch.Tensor) -> _Children:
        """Every node's children at a branching: the driver's command, the MPC's chosen plan and
        every feasible goal, the chosen command braking harder, the fail-safes, the stored one."""
        device = self.mpc.optimizer.device
        plan = self.mpc.plan(ego.to(device), vehicles.to(device), mask.to(device))
        goal_acceleration, goal_steering = (field.cpu().to(ego.dtype) for field in
                                            self.mpc.candidate_commands(plan.problem.ego, plan.result.trajectories))
        feasible = plan.result.feasible.cpu()
        chosen = plan.selection.index.cpu()
        goals = torch.arange(feasible.shape[1]).expand_as(feasible)
        own = plan.acceleration.cpu().to(ego.dtype), plan.steering.cpu().to(ego.dtype)
        return self._assemble(ego, beam, asked, [(own, chosen[:, None], None), ((goal_acceleration, goal_steering), goals, feasible)],
                              self.road.lane_index(plan.problem.goals[..., 1]).cpu())

    def _holds(self, ego: torch.Tensor, vehicles: torch.Tensor, mask: torch.Tensor, beam: _Beam,
               asked: torch.Tensor) -> _Children:
        """Every node's children between branchings: the driver's command, the node's mode (its
        goal re-planned alone, or its fail-safe held), braking harder, the fail-safes, the stored one."""
        device = self.mpc.optimizer.device
        problem = self.mpc.build_problem(ego.to(device), vehicles.to(device), mask.to(device))
        goal = beam.mode.clamp_min(0).to(device)[:, None, None].expand(-1, 1, 2)
        plan = self.mpc.plan_problem(problem._replace(goals=problem.goals.gather(1, goal)))
        held = self.verifier.failsafe_command(ego, beam.hold_lane, beam.hold_deceleration)
        in_failsafe = beam.mode == FAILSAFE
        own = (torch.where(in_failsafe, held[0], plan.acceleration.cpu().to(ego.dtype)),
               torch.where(in_failsafe, held[1], plan.steering.cpu().to(ego.dtype)))
        return self._assemble(ego, beam, asked, [(own, beam.mode[:, None], None)], self.road.lane_index(problem.goals[..., 1]).cpu())

    def _assemble(self, ego: torch.Tensor, beam: _Beam, asked: torch.Tensor, planned: list,
                  goal_lanes: torch.Tensor) -> _Children:
        """The children: the driver's, ``planned`` ((acceleration, steering) (N, k), modes (N, k),
        usable (N, k) or None) in order, the first planned command braking harder, the fail-safes'
        first commands, the stored fail-safe's; ``goal_lanes`` (N, G) the lane of each goal."""
        nodes, dtype = ego.shape[0], ego.dtype
        braking = torch.tensor(BRAKING, dtype=dtype)
        (own_acceleration, own_steering), own_mode, _ = planned[0]
        body = self.verifier.body(ego)
        table_lanes, table_decelerations = failsafe_table(body, self.road, self.verifier.failsafes)
        failsafe_acceleration, failsafe_steering = self.verifier.failsafe_candidates(ego)
        has_stored = beam.lane >= 0
        stored_lane = beam.lane.clamp_min(0)
        stored_deceleration = beam.deceleration.nan_to_num(max(self.verifier.failsafes.decelerations))
        stored = self.verifier.failsafe_command(ego, stored_lane, stored_deceleration.to(dtype))
        ones = lambda width: torch.ones(nodes, width, dtype=torch.bool)  # noqa: E731
        columns = [  # (acceleration, steering, usable, mode, hold lane, hold deceleration), each (N, k)
            (asked[:, :1], asked[:, 1:], beam.driver[:, None], beam.mode[:, None], beam.hold_lane[:, None],
             beam.hold_deceleration[:, None]),
        ]
        for (acceleration, steering), mode, usable in planned:
            width = acceleration.shape[1] if acceleration.dim() == 2 else 1
            acceleration, steering = acceleration.view(nodes, width), steering.view(nodes, width)
            columns.append((acceleration, steering, ones(width) if usable is None else usable, mode.expand(nodes, width),
                            beam.hold_lane[:, None].expand(nodes, width), beam.hold_deceleration[:, None].expand(nodes, width)))
        columns.append((torch.minimum(own_acceleration[:, None], -braking), own_steering[:, None].expand(-1, braking.numel()),
                        ones(braking.numel()), own_mode.expand(nodes, braking.numel()),
                        beam.hold_lane[:, None].expand(nodes, braking.numel()),
                        beam.hold_deceleration[:, None].expand(nodes, braking.numel())))
        columns.append((failsafe_acceleration, failsafe_steering, ones(table_lanes.shape[1]),
                        torch.full(table_lanes.shape, FAILSAFE), table_lanes, table_decelerations.double()))
        columns.append((stored[0][:, None], stored[1][:, None], has_stored[:, None], torch.full((nodes, 1), FAILSAFE),
                        stored_lane[:, None], stored_deceleration[:, None]))
        acceleration, steering, usable, mode, hold_lane, hold_deceleration = (torch.cat(parts, dim=1) for parts in zip(*columns))
        usable = usable & beam.alive[:, None] & acceleration.isfinite() & steering.isfinite()
        known = torch.zeros_like(usable)
        known[:, 0] = beam.driver
        known[:, -1] = has_stored
        if not self.config.verify:
            known = usable.clone()
        goal_lane = goal_lanes.gather(1, mode.clamp(0, goal_lanes.shape[1] - 1))
        target = torch.where(mode == FAILSAFE, hold_lane, goal_lane)
        target[:, 0] = self.road.lane_index(ego[:, EGO_Y])
        return _Children(acceleration.nan_to_num(0.0), steering.nan_to_num(0.0), usable, known & usable, mode, hold_lane,
                         hold_deceleration, target)

    def _keep(self, ego: torch.Tensor, vehicles: torch.Tensor, mask: torch.Tensor, beam: _Beam, children: _Children):
        """At a branching: the kept children (N,) (flat indices into (N, K)), whether each is alive
        (N,) and the check's (lane, deceleration) per flat child where it verified."""
        config = self.config
        nodes, kinds = children.acceleration.shape
        parent = torch.arange(nodes)[:, None].expand(nodes, kinds).reshape(-1)
        acceleration, steering, usable, known = (field.reshape(-1) for field in children[:4])
        body = Body(*(field[parent] for field in self.verifier.body(ego)))
        end = drive(body, acceleration, steering, self.verifier.length, self.verifier.sim)
        score = self._score(beam, parent, ego[parent], end)
        forced = known & beam.driver[parent] & (torch.arange(parent.numel()) % kinds == 0)
        target = children.target.reshape(-1)
        kept = _distinct(self._cells(beam.seed[parent], end), score, forced) & usable
        checks = _Checks.unchecked(known)
        if config.verify:
            screened = _select(beam.seed[parent], target, parent, score, forced, kept, config.screened * config.beam,
                               self.road.num_lanes, config.siblings)
            asked = screened.nonzero().squeeze(1)
            rows = parent[asked]
            check = self.verifier.check(ego[rows], vehicles[rows], mask[rows], acceleration[asked, None],
                                        steering[asked, None])
            checks.record(asked, check)
            kept = screened & checks.valid
        chosen = _select(beam.seed[parent], target, parent, score, forced, kept, config.beam, self.road.num_lanes,
                         config.siblings)
        picked = self._fill(chosen, beam.seed[parent], score)
        return picked, chosen[picked], checks

    def _hold(self, ego: torch.Tensor, vehicles: torch.Tensor, mask: torch.Tensor, beam: _Beam, children: _Children):
        """Between branchings: each node's first valid child in the guard's order (unprotected: its
        mode's command), as :meth:`_keep` returns them."""
        nodes, kinds = children.acceleration.shape
        checks = _Checks.unchecked(children.known.reshape(-1))
        rows = torch.arange(nodes)
        if self.config.verify:
            own = rows[children.usable[:, 1] & ~beam.driver]
            first = self.verifier.check(ego[own], vehicles[own], mask[own], children.acceleration[own, 1:2],
                                        children.steering[own, 1:2])
            checks.record(own * kinds + 1, first)
            rest = rows[~checks.valid.view(nodes, kinds)[:, 1] & ~beam.driver & beam.alive]  # braking before the stored fail-safe
            if rest.numel():
                later = self.verifier.check(ego[rest], vehicles[rest], mask[rest], children.acceleration[rest, 2:],
                                            children.steering[rest, 2:])
                index = (rest[:, None] * kinds + torch.arange(2, kinds)).reshape(-1)
                checks.record(index, later._replace(crowded=later.crowded.repeat_interleave(kinds - 2), **{
                    name: getattr(later, name).reshape(-1, 1) for name in ("verified", "lane", "deceleration")}))
            valid = checks.valid.view(nodes, kinds).clone()
        else:
            valid = children.known & (torch.arange(kinds) <= 1)  # the driver's command or the node's mode
        valid &= children.usable
        found = valid.any(dim=1)
        kind = valid.int().argmax(dim=1)
        return rows * kinds + kind, found & beam.alive, checks

    def _advance(self, beam: _Beam, children: _Children, picked: torch.Tensor, kept: torch.Tensor, checks: _Checks) -> None:
        """Clone the picked children's parents, step each with its command, update the beam."""
        kinds = children.acceleration.shape[1]
        rows = picked // kinds
        flat = [field.reshape(-1)[picked] for field in children]
        self.sim = self.sim.take(rows)
        command = torch.stack([flat[0], flat[1]], dim=1).to(self.sim.state.x.dtype)
        x_before = self.sim.state.x[:, 0].double().cpu()
        self.sim.step(command)
        crashed = self.sim.state.crashed[:, 0].cpu()
        first = _first_of_each(picked)
        is_driver = beam.driver[rows] & (picked % kinds == 0) & first
        alive = beam.alive[rows] & kept & ~crashed
        self.nodes_crashed += torch.bincount(beam.seed[rows][crashed & beam.alive[rows] & kept & first],
                                             minlength=len(self.seeds))
        distance = beam.distance[rows] + (self.sim.state.x[:, 0].double().cpu() - x_before)
        reward_sum = beam.reward_sum[rows] + highway_reward(self.sim.state, self.sim.config, self.reward).double().cpu()
        steps = self.steps + 1
        for node in (is_driver & crashed).nonzero().squeeze(1).tolist():
            self.driver_final[int(beam.seed[rows[node]])] = (float(distance[node]), float(beam.speed_sum[rows[node]]) / steps,
                                                             float(beam.cost_sum[rows[node]]) / steps, float(reward_sum[node]))
        checked = checks.lane[picked] >= 0
        lane = torch.where(checked, checks.lane[picked], beam.lane[rows])
        deceleration = torch.where(checked, checks.deceleration[picked], beam.deceleration[rows])
        commands = beam.commands[rows]
        commands[:, self.steps] = command.double().cpu()
        self.beam = _Beam(beam.seed[rows], alive, is_driver & ~crashed, distance, beam.speed_sum[rows], beam.cost_sum[rows],
                          reward_sum, lane, deceleration, flat[4], flat[5], flat[6], commands)
        self.steps = steps

    def _stage_cost(self, speed: torch.Tensor, lateral: torch.Tensor) -> torch.Tensor:
        """The scenario's meta-cost term at driven states, as the evaluation scores them."""
        return self.scenario.objective.stage_cost(speed, lateral, self.road)

    def _score(self, beam: _Beam, parent: torch.Tensor, ego: torch.Tensor, end: Body) -> torch.Tensor:
        """(C,) the children's scores, higher better: distance at high speed, minus the meta cost
        summed over the states so far and the child's next one in cruise; with ``rank="task_return"``
        the task rewards so far plus the child's next state's."""
        if self.config.rank == "task_return":
            y = end.y.double()
            on = on_road(y, self.sim.config)
            reward = self.reward(end.speed.double() * torch.cos(end.heading.double()), lane_of(y, self.sim.config),
                                 self.road.num_lanes, torch.zeros_like(on), on)
            return beam.reward_sum[parent] + reward
        if self.cruise and self.config.rank == "scenario":
            return -(beam.cost_sum[parent] + self._stage_cost(end.speed.double(), end.y.double()))
        return beam.distance[parent] + (end.x.double() - ego[:, EGO_X].double())

    def _cells(self, seed: torch.Tensor, end: Body) -> torch.Tensor:
        """(C,) long: one id per (seed, cell of the ego's state after the step)."""
        size_x, size_y, size_v = self.config.cell
        cells = [seed, torch.floor(end.x.double() / size_x).long(), torch.floor(end.y.double() / size_y).long(),
                 torch.floor(end.speed.double() / size_v).long()]
        return torch.unique(torch.stack(cells, dim=1), dim=0, return_inverse=True)[1]

    def _fill(self, chosen: torch.Tensor, seed: torch.Tensor, score: torch.Tensor) -> torch.Tensor:
        """(N,) child indices: each seed's chosen children, its slots left over filled with
        copies of its best chosen child (the copies step as their original and die as it does)."""
        width = self.config.beam
        picked = []
        for index in range(len(self.seeds)):
            mine = (chosen & (seed == index)).nonzero().squeeze(1)
            if mine.numel() == 0:  # every node collided: carry a dead one on
                mine = (seed == index).nonzero().squeeze(1)[:1]
            order = mine[torch.argsort(-score[mine], stable=True)]
            picked.append(torch.cat([mine, order[:1].expand(width - mine.numel())]))
        return torch.cat(picked)

    def _final_score(self, distance: float | torch.Tensor, cost_mean: float | torch.Tensor,
                     reward_sum: float | torch.Tensor) -> float | torch.Tensor:
        """The score episodes are ranked by at the end (:attr:`CeilingConfig.rank`), from their
        distance [m], meta-cost mean and task return (tensors of one shape, or floats)."""
        if self.config.rank == "task_return":
            return reward_sum
        return -cost_mean if self.cruise and self.config.rank == "scenario" else distance

    def results(self, steps: int) -> list[SeedCeiling]:
        """Each seed's best episode and the bounded driver's."""
        beam = self.beam
        found = []
        for index, seed in enumerate(self.seeds):
            mine = (beam.seed == index) & beam.alive
            if bool(mine.any()):
                nodes = mine.nonzero().squeeze(1)
                score = self._final_score(beam.distance[nodes], beam.cost_sum[nodes] / steps, beam.reward_sum[nodes])
                best = nodes[int(torch.argmax(score))]
                figures = (float(score.max()), float(beam.speed_sum[best]) / steps, float(beam.cost_sum[best]) / steps,
                           float(beam.distance[best]), float(beam.reward_sum[best]), False)
                commands = [tuple(command) for command in beam.commands[best].tolist()]
            else:
                figures, commands = (float("nan"),) * 5 + (True,), []
            if index in self.driver_final:
                (distance, speed, cost, reward), crashed = self.driver_final[index], True
            else:
                node = int(((beam.seed == index) & beam.driver).nonzero()[0, 0])
                distance, speed, cost, reward, crashed = (float(beam.distance[node]), float(beam.speed_sum[node]) / steps,
                                                          float(beam.cost_sum[node]) / steps, float(beam.reward_sum[node]), False)
            found.append(SeedCeiling(seed, *figures, self._final_score(distance, cost, reward), speed, cost, distance, reward,
                                     crashed, int(self.nodes_crashed[index]), commands))
        return found


def _first_of_each(picked: torch.Tensor) -> torch.Tensor:
    """(N,) bool: the first occurrence of each child index in ``picked`` (copies are not)."""
    first = torch.zeros(picked.numel(), dtype=torch.bool)
    _, inverse = torch.unique(picked, return_inverse=True)
    seen = torch.full((int(inverse.max()) + 1,), picked.numel(), dtype=torch.long)
    seen.scatter_reduce_(0, inverse, torch.arange(picked.numel()), reduce="amin")
    first[seen] = True
    return first


def _distinct(cell: torch.Tensor, score: torch.Tensor, forced: torch.Tensor) -> torch.Tensor:
    """(C,) bool: the best-scored child of each cell (a forced child always)."""
    order = torch.argsort(-score, stable=True)
    rank = torch.empty_like(order)
    rank[order] = torch.arange(order.numel())
    best = torch.full((int(cell.max()) + 1,), order.numel(), dtype=torch.long).scatter_reduce(0, cell, rank, reduce="amin")
    return (rank == best[cell]) | forced


def _select(seed: torch.Tensor, lane: torch.Tensor, parent: torch.Tensor, score: torch.Tensor, forced: torch.Tensor,
            allowed: torch.Tensor, limit: int, lanes: int, siblings: int) -> torch.Tensor:
    """(C,) bool: per seed at most ``limit`` of the ``allowed`` children: the forced ones; then,
    best-scored first, those within ``ceil(limit / lanes)`` of their target ``lane`` and
    ``siblings`` of their ``parent``; then those within ``siblings``; then the rest."""
    quota = math.ceil(limit / lanes)
    candidates = allowed.nonzero().squeeze(1)
    if candidates.numel() == 0:
        return torch.zeros_like(allowed)
    s = seed[candidates]
    by_score = torch.argsort(-score[candidates], stable=True)
    in_lane = _rank_within((s * lanes + lane[candidates])[by_score])
    in_family = _rank_within(parent[candidates][by_score])
    tier = torch.where(in_family < siblings, torch.where(in_lane < quota, 1, 2), 3)
    tier = torch.where(forced[candidates][by_score], 0, tier)
    order = by_score[torch.argsort(tier, stable=True)]
    order = order[torch.argsort(s[order], stable=True)]
    in_seed = _rank_within(s[order])
    chosen = torch.zeros_like(allowed)
    chosen[candidates[order[in_seed < limit]]] = True
    return chosen


def _rank_within(group: torch.Tensor) -> torch.Tensor:
    """(C,) each element's rank among the earlier elements of its group (a stable order's position)."""
    order = torch.argsort(group, stable=True)
    sorted_group = group[order]
    start = torch.ones_like(sorted_group, dtype=torch.bool)
    start[1:] = sorted_group[1:] != sorted_group[:-1]
    position = torch.arange(group.numel())
    first = torch.cummax(torch.where(start, position, 0), dim=0).values
    rank = torch.empty_like(position)
    rank[order] = position - first
    return rank
