"""Run closed-loop episodes of a scenario with a driver and write their outputs.

``run_episode`` drives highway-env with a driver (default: the multi-modal MPC) for the
scenario's duration (or until the first collision) and returns the per-step records and the
episode metrics; ``run_lockstep`` drives several seeds at once with one driver call per step;
``write_outputs`` writes ``metrics.json``, ``steps.csv`` and the top-down plot ``topdown.png``
(the video is written while driving, when asked for).
"""

from __future__ import annotations

import csv
import json
import logging
from pathlib import Path
from typing import Callable, NamedTuple, Optional, Sequence

import numpy as np
import torch

from mmpc.drivers import Decision, Driver, Observation, make_driver
from mmpc.highway.episode import HighwayEpisode
from mmpc.metrics import StepRecord, episode_metrics
from mmpc.plotting import plot_episode
from mmpc.problem import EGO_A, EGO_PSI, EGO_PSIDOT, EGO_V, EGO_X, EGO_Y
from mmpc.scenario import CruiseObjective, ScenarioConfig

logger = logging.getLogger(__name__)


class EpisodeResult(NamedTuple):
    """One episode.

    Fields:
        scenario: the scenario as run (duration included).
        seed: its seed.
        records: one :class:`mmpc.metrics.StepRecord` per control step.
        metrics: :func:`mmpc.metrics.episode_metrics` plus ``scenario`` and ``seed``.
    """

    scenario: ScenarioConfig
    seed: int
    records: list[StepRecord]
    metrics: dict


def _clearance(ego: torch.Tensor, vehicles: torch.Tensor, mask: Optional[torch.Tensor], ellipse: tuple[float, float]) -> float:
    """Smallest normalised ellipse distance from one ego (6,) to its vehicles (V, 4) (inf without any)."""
    if mask is not None:
        vehicles = vehicles[mask]
    if vehicles.shape[0] == 0:
        return float("inf")
    dx = (vehicles[:, 0] - ego[EGO_X]) / ellipse[0]
    dy = (vehicles[:, 1] - ego[EGO_Y]) / ellipse[1]
    return float(torch.hypot(dx, dy).min())


def _record(step: int, episode: HighwayEpisode, observation: Observation, decision: Decision, row: int) -> StepRecord:
    """The record of row ``row`` of a (lockstep) decision, after its episode applied the command."""
    scenario = episode.scenario
    ego = observation.ego[row]
    goal = int(decision.goal_index[row])
    goal_xy = (float("nan"), float("nan"))
    if decision.candidates is not None and decision.candidates.goals is not None and goal >= 0:
        goal_xy = tuple(float(c) for c in decision.candidates.goals[row, goal])
    mask = None if observation.vehicle_mask is None else observation.vehicle_mask[row]
    road = scenario.road
    return StepRecord(
        step=step,
        time=step / scenario.frequency,
        x=float(ego[EGO_X]),
        y=float(ego[EGO_Y]),
        psi=float(ego[EGO_PSI]),
        v=float(ego[EGO_V]),
        acceleration=float(ego[EGO_A]),
        heading_rate=float(ego[EGO_PSIDOT]),
        lane=int(road.lane_index(ego[EGO_Y])),
        command_acceleration=float(decision.acceleration[row]),
        command_steering=float(decision.steering[row]),
        goal_index=goal,
        goal_x=goal_xy[0],
        goal_y=goal_xy[1],
        feasible_goals=int(decision.feasible_goals[row]),
        fallback=bool(decision.fallback[row]),
        meta_cost=scenario.objective.stage_cost(float(ego[EGO_V]), float(ego[EGO_Y]), road),
        plan_cost=float(decision.plan_cost[row]),
        solve_ms=decision.solve_ms,
        clearance=_clearance(ego, observation.vehicles[row], mask, (scenario.optimizer.ellipse_a, scenario.optimizer.ellipse_b)),
        crashed=bool(episode.ego.crashed),
        on_road=bool(episode.ego.on_road),
    )


def _result(scenario: ScenarioConfig, seed: int, records: list[StepRecord]) -> EpisodeResult:
    v_cruise = scenario.objective.v_cruise if isinstance(scenario.objective, CruiseObjective) else None
    metrics = episode_metrics(records, dt=1.0 / scenario.frequency, right_lane_y=scenario.road.right_lane_y, v_cruise=v_cruise)
    if metrics["collisions"]:
        logger.warning("scenario %s seed %d: collision at t = %.1f s", scenario.name, seed, records[-1].time)
    return EpisodeResult(scenario, seed, records, {"scenario": scenario.name, "seed": seed, **metrics})


def run_episode(
    scenario: ScenarioConfig,
    seed: int,
    *,
    driver: Optional[Driver] = None,
    video: Optional[Path] = None,
    on_step: Optional[Callable[[StepRecord], None]] = None,
) -> EpisodeResult:
    """Drive one episode.

    Args:
        scenario: the scenario (its ``duration`` sets the length).
        seed: the episode's seed (highway-env and the traffic controller).
        driver: who drives (default: the scenario's multi-modal MPC, ``make_driver("mpc")``).
        video: write the episode, with the driver's candidates drawn, to this ``.mp4`` / ``.gif``.
        on_step: called with every record (e.g. a progress bar).

    Returns:
        An :class:`EpisodeResult`; the episode ends early at the first collision.
    """
    return run_lockstep(scenario, [seed], driver=driver, video=video, on_step=on_step)[0]


def run_lockstep(
    scenario: ScenarioConfig,
    seeds: Sequence[int],
    *,
    driver: Optional[Driver] = None,
    video: Optional[Path] = None,
    on_step: Optional[Callable[[StepRecord], None]] = None,
) -> list[EpisodeResult]:
    """Drive one episode per seed in lockstep: every control step, ONE driver call decides for
    all episodes still running (for the MPC: one optimizer call over all their goal batches).

    A driver's decision for one environment does not depend on the others in the batch, so each
    episode is the one it would be alone, up to floating-point rounding (batched matrix
    products may round differently, and a closed loop can amplify that over many steps).

    Args:
        scenario: the scenario.
        seeds: one episode per seed (distinct, at least one).
        driver: who drives (default: the scenario's multi-modal MPC).
        video: with a single seed only: write the episode's video here.
        on_step: called with every record of every episode.

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
    episodes = [HighwayEpisode(scenario, seed, render=video is not None) for seed in seeds]
    records: list[list[StepRecord]] = [[] for _ in seeds]
    writer = None
    if video is not None:
        from mmpc.highway.video import VideoWriter, render_candidates  # pygame and imageio only when asked for

        writer = VideoWriter(video, fps=scenario.frequency)
    try:
        driver.reset(len(episodes))
        while True:
            active = [i for i, episode in enumerate(episodes) if not episode.done]
            if not active:
                break
            observation = stack_observations([episodes[i].observe() for i in active], active)
            decision = driver.decide(observation)
            if writer is not None:
                writer.add(render_candidates(episodes[0], decision.candidates))
            for row, i in enumerate(active):
                episodes[i].apply(float(decision.acceleration[row]), float(decision.steering[row]))
                records[i].append(_record(len(records[i]), episodes[i], observation, decision, row))
                if on_step is not None:
                    on_step(records[i][-1])
    finally:
        if writer is not None:
            writer.close()
        for episode in episodes:
            episode.close()
    return [_result(scenario, seed, rows) for seed, rows in zip(seeds, records)]


def stack_observations(observations: Sequence[Observation], env_ids: Sequence[int]) -> Observation:
    """Single-environment observations -> one batch; vehicle rows padded to the largest count
    (padding masked out)."""
    count = max(o.vehicles.shape[1] for o in observations)
    vehicles = observations[0].vehicles.new_zeros(len(observations), count, 4)
    mask = torch.zeros(len(observations), count, dtype=torch.bool)
    for row, o in enumerate(observations):
        present = o.vehicles.shape[1]
        vehicles[row, :present] = o.vehicles[0]
        mask[row, :present] = True if o.vehicle_mask is None else o.vehicle_mask[0]
    kinematics = None
    if all(o.kinematics is not None for o in observations):
        kinematics = np.concatenate([o.kinematics for o in observations], axis=0)
    return Observation(
        torch.cat([o.ego for o in observations], dim=0), vehicles, mask, kinematics,
        torch.as_tensor(list(env_ids), dtype=torch.long),
    )


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
