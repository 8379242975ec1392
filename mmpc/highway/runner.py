"""Run closed-loop episodes of a scenario with a driver and write their outputs.

:func:`run_lockstep` is mmpc's one episode loop: it drives one episode per seed in the
scenario's world (highway-env, or the batched simulator: :mod:`mmpc.highway.worlds`) with a
driver (default: the multi-modal MPC), one driver call per control step for all of them,
for the scenario's duration (or until the first collision), calls its :class:`Observer` hooks
and returns the per-step records and the episode metrics; :func:`run_episode` is one seed of it;
:func:`write_outputs` writes ``metrics.json``, ``steps.csv`` and the top-down plot ``topdown.png``
(the video is written while driving, when asked for).
"""

from __future__ import annotations

import csv
import json
import logging
from pathlib import Path
from typing import NamedTuple, Optional, Sequence

import torch

from mmpc.collisions import CRASH_COLUMNS, Crash, collider_index, crash_scene, is_ego_fault
from mmpc.drivers import Decision, Driver, Observation, make_driver
from mmpc.obstacles.shape import ellipse_distance_squared, smallest_distance
from mmpc.highway.episode import HighwayEpisode
from mmpc.highway.worlds import World, make_world
from mmpc.metrics import StepRecord, episode_metrics
from mmpc.plotting import plot_episode
from mmpc.problem import EGO_A, EGO_PSI, EGO_PSIDOT, EGO_V, EGO_X, EGO_Y
from mmpc.scenario import CruiseObjective, ScenarioConfig
from mmpc.verify import AssumptionMonitor, TrafficAssumptions

logger = logging.getLogger(__name__)


class EpisodeResult(NamedTuple):
    """One episode.

    Fields:
        scenario: the scenario as run (duration included).
        seed: its seed.
        records: one :class:`mmpc.metrics.StepRecord` per control step.
        metrics: :func:`mmpc.metrics.episode_metrics` plus ``scenario``, ``seed``,
            ``collision_part`` (what the collision struck of the ego, :mod:`mmpc.collisions`;
            ``None`` without one), ``ego_fault_collisions`` (1: it struck the front or a side,
            or no other car was found to tell) and the crash's scene (:data:`mmpc.collisions.CRASH_COLUMNS`,
            ``None`` without a collision).
    """

    scenario: ScenarioConfig
    seed: int
    records: list[StepRecord]
    metrics: dict


def _clearances(ego: torch.Tensor, vehicles: torch.Tensor, mask: Optional[torch.Tensor],
                ellipse: tuple[float, float]) -> torch.Tensor:
    """(A,) smallest normalised ellipse distance from each ego (A, 6) to its vehicles (A, V, 4) (inf without any)."""
    squared = ellipse_distance_squared(vehicles[..., :2], ego[:, None, EGO_X:EGO_Y + 1], ellipse)  # (A, V)
    return smallest_distance(squared, mask, 1)


#: A car moving across the road faster than this is changing lane [m/s] (:class:`mmpc.verify.TrafficAssumptions`).
CHANGING_SPEED = 0.5
#: How near the ego along the road a lane change counts in :attr:`mmpc.metrics.StepRecord.lane_changes_near` [m].
NEAR_ALONG = 30.0


def traffic_near(ego: torch.Tensor, vehicles: torch.Tensor, mask: Optional[torch.Tensor], scenario: ScenarioConfig
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """For each ego (A, 6) among its vehicles (A, V, 4): (A,) the time to collision with the nearest
    car ahead whose body overlaps the ego's across the road (0 where they touch, inf where none
    closes in) [s], and (A,) the cars changing lane within :data:`NEAR_ALONG` and one lane of it."""
    length, width = scenario.vehicle
    lane_width = scenario.road.lane_width
    present = torch.ones(vehicles.shape[:2], dtype=torch.bool) if mask is None else mask
    along = vehicles[..., 0] - ego[:, None, EGO_X]
    across = (vehicles[..., 1] - ego[:, None, EGO_Y]).abs()
    gap = along - length
    closing = ego[:, None, EGO_V] * torch.cos(ego[:, None, EGO_PSI]) - vehicles[..., 2]
    ahead = present & (along > 0) & (across < width)
    ttc = torch.where(gap > 0, gap / closing.clamp_min(1e-9), torch.zeros_like(gap))
    ttc = torch.where(ahead & ((closing > 0) | (gap <= 0)), ttc, torch.full_like(ttc, float("inf")))
    nearest = ttc.amin(dim=1) if ttc.shape[1] else ttc.new_full((ttc.shape[0],), float("inf"))
    changing = present & (vehicles[..., 3].abs() > CHANGING_SPEED) & (along.abs() < NEAR_ALONG) & (across < 1.5 * lane_width)
    return nearest, changing.sum(dim=1)


def _step_records(steps: Sequence[int], episodes: Sequence, observation: Observation, decision: Decision,
                  scenario: ScenarioConfig) -> list[StepRecord]:
    """The records of one lockstep step, row ``r`` for ``episodes[r]`` at its step ``steps[r]``,
    after the commands were applied; ``observation`` and ``decision`` on the host. Every column is
    computed for the whole batch at once."""
    ego = observation.ego
    rows = len(steps)
    goal = decision.goal_index
    goal_xy = ego.new_full((rows, 2), float("nan"))
    if decision.candidates is not None and decision.candidates.goals is not None:
        chosen = decision.candidates.goals[torch.arange(rows), goal.clamp_min(0)].to(goal_xy.dtype)
        goal_xy = torch.where((goal >= 0)[:, None], chosen, goal_xy)
    road = scenario.road
    speed, lateral = ego[:, EGO_V].double(), ego[:, EGO_Y].double()
    ellipse = scenario.optimizer.ellipse
    columns = zip(
        ego[:, EGO_X].tolist(), ego[:, EGO_Y].tolist(), ego[:, EGO_PSI].tolist(), ego[:, EGO_V].tolist(),
        ego[:, EGO_A].tolist(), ego[:, EGO_PSIDOT].tolist(), road.lane_index(ego[:, EGO_Y]).tolist(),
        decision.acceleration.tolist(), decision.steering.tolist(), goal.tolist(), goal_xy.tolist(),
        decision.feasible_goals.tolist(), decision.fallback.tolist(),
        [-1] * rows if decision.iterations is None else decision.iterations.tolist(),
        scenario.objective.stage_cost(speed, lateral, road).tolist(), decision.plan_cost.tolist(),
        _clearances(ego, observation.vehicles, observation.vehicle_mask, ellipse).tolist(),
        [None] * rows if decision.verified is None else decision.verified.tolist(),
        [False] * rows if decision.failsafe is None else decision.failsafe.tolist(),
        *(column.tolist() for column in traffic_near(ego, observation.vehicles, observation.vehicle_mask, scenario)),
    )
    frequency = scenario.frequency
    return [
        StepRecord(
            step=step, time=step / frequency, x=x, y=y, psi=psi, v=v, acceleration=a, heading_rate=psidot, lane=lane,
            command_acceleration=command_a, command_steering=command_steering, goal_index=goal_index, goal_x=xy[0],
            goal_y=xy[1], feasible_goals=feasible, fallback=fallback, meta_cost=meta, plan_cost=plan_cost,
            solve_ms=decision.solve_ms, iterations=iterations, clearance=clearance, crashed=bool(episode.ego.crashed),
            on_road=bool(episode.ego.on_road), task_reward=float(episode.reward), verified=verified, failsafe=failsafe,
            ttc=ttc, lane_changes_near=changing,
        )
        for step, episode, (x, y, psi, v, a, psidot, lane, command_a, command_steering, goal_index, xy, feasible, fallback,
                            iterations, meta, plan_cost, clearance, verified, failsafe, ttc, changing)
        in zip(steps, episodes, columns)
    ]


def _crash_scene(impact: Observation, scenario: ScenarioConfig) -> tuple[Optional[Crash], Optional[int]]:
    """The scene of a collision (:func:`mmpc.collisions.crash_scene`), from the state at its impact (E = 1,
    :meth:`mmpc.highway.worlds.World.observe_impact`), and the collider's slot in the observation (``None``: no car)."""
    ego = impact.ego[0]
    slots = torch.arange(impact.vehicles.shape[1]) if impact.vehicle_mask is None else impact.vehicle_mask[0].nonzero().squeeze(1)
    vehicles = impact.vehicles[0][slots].tolist()
    pose = (float(ego[EGO_X]), float(ego[EGO_Y]), float(ego[EGO_PSI]))
    crash = crash_scene((*pose, float(ego[EGO_V])), vehicles, scenario.vehicle, scenario.road.lane_width)
    index = collider_index(pose, vehicles, scenario.vehicle)
    return crash, None if index is None else int(slots[index])


def _crash_metrics(crash: Optional[Crash], records: list[StepRecord], frequency: float) -> dict:
    """:data:`CRASH_COLUMNS` of an episode that ended in ``crash`` (all ``None`` without one)."""
    if crash is None:
        return dict.fromkeys(CRASH_COLUMNS)
    last_second = records[-max(1, round(frequency)):]
    return {
        "crash_time": records[-1].time, "crash_along": crash.along, "crash_across": crash.across,
        "crash_other_heading_deg": crash.other_heading_deg, "crash_other_speed": crash.other_speed,
        "crash_closing_speed": crash.closing_speed, "crash_ego_offset": crash.ego_offset, "crash_ego_speed": crash.ego_speed,
        "crash_fallback_steps": sum(record.fallback for record in last_second),
    }


def _result(scenario: ScenarioConfig, seed: int, records: list[StepRecord], crash: Optional[Crash],
            monitored: "_Monitored") -> EpisodeResult:
    """The episode's result; ``crash``: its collision's scene (``None``: no collision, or no car found);
    ``monitored``: what the assumption monitor found in it."""
    v_cruise = scenario.objective.v_cruise if isinstance(scenario.objective, CruiseObjective) else None
    metrics = episode_metrics(records, dt=scenario.period, right_lane_y=scenario.road.right_lane_y, v_cruise=v_cruise,
                              lane_width=scenario.road.lane_width)
    crashed = bool(metrics["collisions"])
    part = crash.part if crashed and crash is not None else None
    metrics["collision_part"] = part
    metrics["ego_fault_collisions"] = int(crashed and (part is None or is_ego_fault(part)))  # unknown: the ego's
    metrics.update(_crash_metrics(crash if crashed else None, records, scenario.frequency))
    metrics["assumption_violations"] = monitored.violations
    metrics["crash_collider_outside"] = monitored.collider_outside if crashed else None
    if crashed:
        logger.warning("scenario %s seed %d: collision at t = %.1f s (%s struck)", scenario.name, seed, records[-1].time,
                       part or "no car found")
    return EpisodeResult(scenario, seed, records, {"scenario": scenario.name, "seed": seed, **metrics})


class _Monitored:
    """What :class:`mmpc.verify.AssumptionMonitor` found in one episode: how many times a car left
    its set, which cars did in the last second, and whether the collider was one of them."""

    def __init__(self, frequency: float) -> None:
        self.violations = 0
        self.recent: list[torch.Tensor] = []  # (M,) bool per step of the last second
        self.window = max(1, round(frequency))
        self.collider_outside: Optional[int] = None

    def add(self, count: int, broke: torch.Tensor) -> None:
        """A step's (M,) bool cars outside their sets, ``count`` of them."""
        self.violations += count
        self.recent = (self.recent + [broke])[-self.window:]

    def crashed_with(self, slot: Optional[int]) -> None:
        """The collider is car ``slot`` (``None``: unknown): 1 if it left its set in the last second, else 0."""
        if slot is not None:
            self.collider_outside = int(any(slot < len(broke) and bool(broke[slot]) for broke in self.recent))


class Step(NamedTuple):
    """One environment's control step, as :meth:`Observer.applied` sees it.

    Fields:
        index: the environment's position in the runner's ``seeds``.
        episode: its episode, after the command was applied (a :class:`HighwayEpisode`, or on
            the batched simulator a view of its environment with the same ``scenario``, ``seed``,
            ``ego.crashed``, ``ego.on_road``, ``done`` and ``observe()``).
        batch: the lockstep observation the driver decided from (one row per running environment).
        rows: each row of ``batch`` alone (E = 1), as the world made them (made when read).
        decision: the driver's decision for ``batch``.
        row: this environment's row in ``batch`` and ``decision``.
        record: the step's :class:`mmpc.metrics.StepRecord`.
    """

    index: int
    episode: HighwayEpisode
    batch: Observation
    rows: Sequence[Observation]
    decision: Decision
    row: int
    record: StepRecord

    @property
    def observation(self) -> Observation:
        """What this environment observed before the command (E = 1)."""
        return self.rows[self.row]


class Observer:
    """Per-step hooks of :func:`run_lockstep`: what a caller records beyond the step records
    (demonstrations, DAgger's states, a video, a progress bar). Every hook is optional.

    Environments are numbered by their position ``index`` in the ``seeds`` given; at a control
    step, ``observation`` and ``decision`` hold one row per environment still running (``active``).
    """

    def start(self, episodes: Sequence[HighwayEpisode]) -> None:
        """The episodes were reset and are about to be driven."""

    def decided(self, observation: Observation, decision: Decision, active: Sequence[int]) -> None:
        """One driver call decided for the environments ``active`` (before the commands are applied)."""

    def applied(self, step: Step) -> None:
        """An environment applied its command."""

    def finished(self, index: int, episode: HighwayEpisode) -> None:
        """Environment ``index``'s episode ended (duration reached or collision)."""

    def close(self) -> None:
        """The run ends (also when it raised)."""


class _VideoObserver(Observer):
    """Writes the (single) episode's frames with the driver's candidates drawn."""

    def __init__(self, path: Path, fps: float) -> None:
        from mmpc.highway.video import VideoWriter  # pygame and imageio only when asked for

        self.writer = VideoWriter(path, fps=fps)
        self.episode: Optional[HighwayEpisode] = None

    def start(self, episodes: Sequence[HighwayEpisode]) -> None:
        self.episode = episodes[0]

    def decided(self, observation: Observation, decision: Decision, active: Sequence[int]) -> None:
        from mmpc.highway.video import render_candidates

        self.writer.add(render_candidates(self.episode, decision.candidates))

    def close(self) -> None:
        self.writer.close()


def run_episode(
    scenario: ScenarioConfig,
    seed: int,
    *,
    driver: Optional[Driver] = None,
    video: Optional[Path] = None,
    observers: Sequence[Observer] = (),
) -> EpisodeResult:
    """Drive one episode (:func:`run_lockstep` with one seed).

    Args:
        scenario: the scenario (its ``duration`` sets the length).
        seed: the episode's seed (the traffic, the ego's lane).
        driver: who drives (default: the scenario's multi-modal MPC, ``make_driver("mpc")``).
        video: write the episode, with the driver's candidates drawn, to this ``.mp4`` / ``.gif``.
        observers: per-step hooks (:class:`Observer`).

    Returns:
        An :class:`EpisodeResult`; the episode ends early at the first collision.
    """
    return run_lockstep(scenario, [seed], driver=driver, video=video, observers=observers)[0]


def run_lockstep(
    scenario: ScenarioConfig,
    seeds: Sequence[int],
    *,
    driver: Optional[Driver] = None,
    video: Optional[Path] = None,
    observers: Sequence[Observer] = (),
) -> list[EpisodeResult]:
    """Drive one episode per seed in lockstep: every control step, ONE driver call decides for
    all episodes still running (for the MPC: one optimizer call over all their goal batches).

    This is mmpc's one episode loop: the evaluation, the demonstrations, DAgger and the
    benchmarks drive through it and record what they need with :class:`Observer` hooks.

    A driver's decision for one environment does not depend on the others in the batch, so each
    episode is the one it would be alone, up to floating-point rounding (batched matrix
    products may round differently, and a closed loop can amplify that over many steps).

    Args:
        scenario: the scenario; ``scenario.sim`` chooses the world (:func:`mmpc.highway.worlds.make_world`).
        seeds: one episode per seed (distinct, at least one).
        driver: who drives (default: the scenario's multi-modal MPC).
        video: with a single seed only: write the episode's video here.
        observers: per-step hooks, called in order.

    Returns:
        One :class:`EpisodeResult` per seed, in the order of ``seeds``.
    """
    seeds = list(seeds)
    if not seeds or len(set(seeds)) != len(seeds):
        raise ValueError(f"`seeds` must be distinct and at least one; got {seeds}")
    if video is not None and len(seeds) != 1:
        raise ValueError(f"a video needs a single seed; got {len(seeds)} seeds")
    if driver is None:
        driver = make_driver("mpc", scenario)
    observers = list(observers)
    world: Optional[World] = None
    records: list[list[StepRecord]] = [[] for _ in seeds]
    crashes: dict[int, Optional[Crash]] = {}  # environment -> its collision's scene
    monitor = AssumptionMonitor(scenario.road, scenario.period, TrafficAssumptions.for_scenario(scenario))
    monitored = [_Monitored(scenario.frequency) for _ in seeds]
    try:
        if video is not None:
            observers.insert(0, _VideoObserver(video, scenario.frequency))
        world = make_world(scenario, seeds, render=video is not None)
        episodes = world.episodes
        for observer in observers:
            observer.start(episodes)
        driver.reset(len(episodes))
        ended = world.done().tolist()
        active = [i for i in range(len(episodes)) if not ended[i]]
        for i in sorted(set(range(len(episodes))) - set(active)):  # ended at reset (e.g. a crash on spawning)
            for observer in observers:
                observer.finished(i, episodes[i])
        while active:
            observation, singles = world.observe(active)
            decision = driver.decide(observation.to(driver.device))
            # Records and observers read the host: one copy of each per-environment field per step.
            observation, decision = observation.to("cpu"), decision.commands_to("cpu")
            broke = monitor.observe(torch.tensor(active), observation.ego, observation.vehicles, observation.vehicle_mask)
            for i, count, cars in zip(active, broke.sum(dim=1).tolist(), broke):
                monitored[i].add(count, cars)
            for observer in observers:
                observer.decided(observation, decision, active)
            world.apply(active, decision.acceleration, decision.steering)
            ended = world.done().tolist()
            step_records = _step_records([len(records[i]) for i in active], [episodes[i] for i in active], observation,
                                         decision, scenario)
            for row, (i, record) in enumerate(zip(active, step_records)):
                records[i].append(record)
                if observers:
                    step = Step(i, episodes[i], observation, singles, decision, row, record)
                    for observer in observers:
                        observer.applied(step)
                if ended[i]:
                    if episodes[i].ego.crashed:
                        crashes[i], collider = _crash_scene(world.observe_impact(i), scenario)
                        monitored[i].crashed_with(collider)
                    for observer in observers:
                        observer.finished(i, episodes[i])
            active = [i for i in active if not ended[i]]
    finally:
        for observer in observers:
            observer.close()
        if world is not None:
            world.close()
    return [_result(scenario, seed, rows, crashes.get(i), monitored[i]) for i, (seed, rows) in enumerate(zip(seeds, records))]


def write_outputs(result: EpisodeResult, out: Path) -> list[Path]:
    """Write ``metrics.json``, ``steps.csv`` and ``topdown.png`` into ``out``; returns the paths."""
    out.mkdir(parents=True, exist_ok=True)
    metrics_path = out / "metrics.json"
    metrics_path.write_text(json.dumps(result.metrics, indent=2) + "\n")
    steps_path = out / "steps.csv"
    with open(steps_path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(StepRecord._fields)
        writer.writerows(result.records)
    plot_path = plot_episode(
        out / "topdown.png", result.records, result.scenario.road,
        v_ref=result.scenario.objective.reference_speed, title=f"{result.scenario.name}, seed {result.seed}",
    )
    return [metrics_path, steps_path, plot_path]
