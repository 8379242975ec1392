"""Run one closed-loop episode of a scenario and write its outputs.

``run_episode`` drives highway-env with the MPC for the scenario's duration (or until the
first collision) and returns the per-step records and the episode metrics; ``write_outputs``
writes ``metrics.json``, ``steps.csv`` and the top-down plot ``topdown.png`` (the video is
written while driving, when asked for).
"""

from __future__ import annotations

import csv
import json
import logging
from pathlib import Path
from typing import Callable, NamedTuple, Optional

import torch

from mmpc.highway import HighwayDriver, RoadState
from mmpc.metrics import StepRecord, episode_metrics
from mmpc.mpc import MPC, Plan
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


def _clearance(state: RoadState, ellipse: tuple[float, float]) -> float:
    """Smallest normalised ellipse distance from the ego to another vehicle (inf without any)."""
    vehicles = state.vehicles[0]
    if vehicles.shape[0] == 0:
        return float("inf")
    ego = state.ego[0]
    dx = (vehicles[:, 0] - ego[EGO_X]) / ellipse[0]
    dy = (vehicles[:, 1] - ego[EGO_Y]) / ellipse[1]
    return float(torch.hypot(dx, dy).min())


def _record(step: int, time: float, state: RoadState, plan: Plan, driver: HighwayDriver) -> StepRecord:
    ego = state.ego[0]
    goal = int(plan.selection.index[0])
    cfg = driver.mpc.optimizer.config
    return StepRecord(
        step=step,
        time=time,
        x=float(ego[EGO_X]),
        y=float(ego[EGO_Y]),
        psi=float(ego[EGO_PSI]),
        v=float(ego[EGO_V]),
        acceleration=float(ego[EGO_A]),
        heading_rate=float(ego[EGO_PSIDOT]),
        lane=int(driver.mpc.road.lane_index(ego[EGO_Y])),
        command_acceleration=float(plan.acceleration[0]),
        command_steering=float(plan.steering[0]),
        goal_index=goal,
        goal_x=float(plan.problem.goals[0, goal, 0]),
        goal_y=float(plan.problem.goals[0, goal, 1]),
        feasible_goals=int(plan.result.feasible[0].sum()),
        fallback=not bool(plan.selection.feasible[0]),
        meta_cost=float(plan.selection.cost[0]),
        solve_ms=plan.solve_ms,
        clearance=_clearance(state, (cfg.ellipse_a, cfg.ellipse_b)),
        crashed=bool(driver.ego.crashed),
        on_road=bool(driver.ego.on_road),
    )


def run_episode(
    scenario: ScenarioConfig,
    seed: int,
    *,
    video: Optional[Path] = None,
    on_step: Optional[Callable[[StepRecord], None]] = None,
    mpc: Optional[MPC] = None,
) -> EpisodeResult:
    """Drive one episode.

    Args:
        scenario: the scenario (its ``duration`` sets the length).
        seed: the episode's seed (highway-env and the traffic controller).
        video: write the episode with the candidates drawn to this ``.mp4`` / ``.gif``.
        on_step: called with every record (e.g. a progress bar).
        mpc: reuse an MPC across episodes (default: built from the scenario).

    Returns:
        An :class:`EpisodeResult`; the episode ends early at the first collision.
    """
    driver = HighwayDriver(scenario, seed, render=video is not None, mpc=mpc)
    writer = None
    if video is not None:
        from mmpc.video import VideoWriter, render_plan  # pygame and imageio only when asked for

        writer = VideoWriter(video, fps=scenario.frequency)
    records: list[StepRecord] = []
    try:
        while not driver.done:
            time, state = driver.time, driver.observe()
            plan = driver.plan(state)
            if writer is not None:
                writer.add(render_plan(driver, plan))
            driver.apply(plan)
            records.append(_record(len(records), time, state, plan, driver))
            if on_step is not None:
                on_step(records[-1])
    finally:
        if writer is not None:
            writer.close()
        driver.close()
    v_cruise = scenario.objective.v_cruise if isinstance(scenario.objective, CruiseObjective) else None
    metrics = episode_metrics(records, dt=1.0 / scenario.frequency, right_lane_y=scenario.road.right_lane_y, v_cruise=v_cruise)
    if metrics["collisions"]:
        logger.warning("scenario %s seed %d: collision at t = %.1f s", scenario.name, seed, records[-1].time)
    return EpisodeResult(scenario, seed, records, {"scenario": scenario.name, "seed": seed, **metrics})


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
