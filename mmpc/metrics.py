"""Per-step records of a closed-loop episode and the paper's episode metrics.

Pure Python over the records; no simulator import. The metrics follow the paper's tables:
meta cost, linear and angular acceleration, speed (cruise: residual to the cruise speed; high
speed: mean speed and distance to the right lane), computation time, plus safety counts.
"""

from __future__ import annotations

import math

from typing import NamedTuple, Optional, Sequence


class StepRecord(NamedTuple):
    """One control step: the state planned from, the plan, and what happened after the frame.

    Fields (road frame; SI units):
        step: index of the step.
        time: simulated time of the state [s].
        x, y: ego position [m].
        psi: direction of motion [rad].
        v: speed [m/s].
        acceleration: acceleration being applied at the state (the previous command) [m/s^2].
        heading_rate: turn rate being applied at the state [rad/s].
        lane: nearest lane index (0 = leftmost).
        command_acceleration: the new command's acceleration [m/s^2].
        command_steering: the new command's steering angle [rad].
        goal_index: index of the chosen goal.
        goal_x, goal_y: the chosen goal [m].
        feasible_goals: number of feasible candidates (-1: the driver has none).
        fallback: no candidate was feasible (the driver executed its fallback, see :meth:`mmpc.MPC.plan`).
        meta_cost: the scenario's meta cost term at this driven state (its ``stage_cost``;
            cruise ``(v - v_cruise)^2``): the same yardstick for every driver.
        plan_cost: meta cost of the chosen plan as the driver ranked it (NaN: no plan).
        solve_ms: wall time of the driver's decision [ms].
        iterations: optimizer iterations of this environment's solve (-1: not reported).
        clearance: smallest normalised ellipse distance ``sqrt((dx/a)^2 + (dy/b)^2)`` from the
            ego to another vehicle (inf without vehicles); < 1 is inside the safety ellipse.
        crashed: the ego had collided after this step's frame.
        on_road: the ego was on the road after this step's frame.
        task_reward: highway-env's reward after this step's frame (``HighwayEnv``'s defaults:
            collision -1, right lane 0.1, 0.4 over 20-30 m/s forward speed, normalised onto [0, 1]),
            a task reward no driver's meta cost encodes (:func:`mmpc.sim.reward.highway_reward`).
        verified: the command kept a verified way out (``None``: the driver is not verified, :mod:`mmpc.verify`).
        failsafe: no candidate verified and a fail-safe drove.
        ttc: time to collision with the nearest car ahead whose body overlaps the ego's across
            the road, both at their speeds along the road [s] (0: touching; inf: none closing).
        lane_changes_near: cars changing lane near the ego: moving across the road faster than
            0.5 m/s, within 30 m along the road and one lane of the ego's.
    """

    step: int
    time: float
    x: float
    y: float
    psi: float
    v: float
    acceleration: float
    heading_rate: float
    lane: int
    command_acceleration: float
    command_steering: float
    goal_index: int
    goal_x: float
    goal_y: float
    feasible_goals: int
    fallback: bool
    meta_cost: float
    plan_cost: float
    solve_ms: float
    iterations: int
    clearance: float
    crashed: bool
    on_road: bool
    task_reward: float
    verified: Optional[bool] = None
    failsafe: bool = False
    ttc: float = math.inf
    lane_changes_near: int = 0


#: Lane discipline: an ego farther than OFF_CENTRE from its nearest lane's centre is off-centre
#: [m]; a lane change lasts from the last step within CENTRED of the old lane's centre to the
#: first step within CENTRED of the new lane's [m].
OFF_CENTRE = 1.0
CENTRED = 0.5
#: A step whose :attr:`StepRecord.ttc` is below this counts in ``short_ttc_steps`` [s].
SHORT_TTC = 2.0


def _mean(values: Sequence[float]) -> float:
    return sum(values) / len(values) if values else float("nan")


def lane_change_durations(records: Sequence[StepRecord], lane_width: float, dt: float) -> list[float]:
    """Durations [s] of the completed lane changes: from leaving one lane's centre (the last
    step within :data:`CENTRED` of it) to reaching another's (the first step within it)."""
    durations = []
    settled: Optional[tuple[int, int]] = None  # (lane, step) of the last centred step
    for record in records:
        if abs(record.y - record.lane * lane_width) > CENTRED:
            continue
        if settled is not None and record.lane != settled[0]:
            durations.append((record.step - settled[1]) * dt)
        settled = (record.lane, record.step)
    return durations


def episode_metrics(
    records: Sequence[StepRecord],
    *,
    dt: float,
    right_lane_y: float,
    v_cruise: Optional[float] = None,
    lane_width: float = 4.0,
) -> dict[str, Optional[float | int]]:
    """Metrics of one episode.

    Args:
        records: the steps, in order (at least one).
        dt: control period [s], for the angular acceleration.
        right_lane_y: lateral position of the right lane's centre [m].
        v_cruise: cruise speed [m/s]; adds ``speed_residual_mean`` when given.
        lane_width: [m]; lane k's centre is at ``y = k * lane_width``.

    Returns:
        ``collisions`` (0 or 1: an episode ends at the first one), ``offroad`` (steps off the
        road), ``steps``, ``duration`` [s], ``mean_speed`` [m/s], ``meta_cost_mean`` / ``_max``
        (over the driven states' meta cost terms),
        ``plan_cost_mean`` (over the steps with a plan), ``task_return`` (the sum of the steps'
        ``task_reward``: an episode a collision ends earns no more), ``speed_residual_mean`` (mean (v - v_cruise)^2 [m^2/s^2], cruise only),
        ``right_lane_distance_mean`` (mean |y - y_right| [m]), ``lin_acc_mean`` (mean |a|
        [m/s^2]), ``ang_acc_mean`` (mean |d psidot / dt| [rad/s^2]), ``solve_ms_mean`` / ``_max``, ``iterations_mean`` (optimizer
        iterations per step; ``None`` where the driver reports none),
        ``lane_changes`` (changes of the nearest lane), ``fallback_steps``, ``verified_share`` (share
        of steps whose command verified; ``None`` for a driver not verified), ``first_verified_step`` (the
        first step whose command verified: from there on the ego keeps a way out; ``None`` where none did, or
        for a driver not verified: a collision then is no defect of the check), ``failsafe_steps``, ``min_clearance``,
        ``off_centre_share`` (share of steps farther than :data:`OFF_CENTRE` from the nearest
        lane centre), ``lane_change_s_mean`` (mean of :func:`lane_change_durations`; ``None`` without one),
        ``min_ttc`` (smallest :attr:`StepRecord.ttc` [s]; ``None`` where no car ahead was ever closing),
        ``short_ttc_steps`` (steps with a ttc below :data:`SHORT_TTC`), ``near_lane_change_steps``
        (the steps' :attr:`StepRecord.lane_changes_near`, summed: car-steps of lane changes near the ego).
    """
    if not records:
        raise ValueError("`records` must hold at least one step")
    if not dt > 0:
        raise ValueError(f"`dt` must be > 0 s; got {dt}")
    speeds = [r.v for r in records]
    rates = [r.heading_rate for r in records]
    metrics: dict[str, Optional[float | int]] = {
        "collisions": int(any(r.crashed for r in records)),
        "offroad": sum(not r.on_road for r in records),
        "steps": len(records),
        "duration": len(records) * dt,
        "mean_speed": _mean(speeds),
        "meta_cost_mean": _mean([r.meta_cost for r in records]),
        "meta_cost_max": max(r.meta_cost for r in records),
        "plan_cost_mean": _mean([r.plan_cost for r in records if not math.isnan(r.plan_cost)]),  # steps with a plan
        "task_return": sum(r.task_reward for r in records),
    }
    if v_cruise is not None:
        metrics["speed_residual_mean"] = _mean([(v - v_cruise) ** 2 for v in speeds])
    metrics.update(
        right_lane_distance_mean=_mean([abs(r.y - right_lane_y) for r in records]),
        lin_acc_mean=_mean([abs(r.acceleration) for r in records]),
        ang_acc_mean=_mean([abs(b - a) / dt for a, b in zip(rates, rates[1:])]) if len(rates) > 1 else 0.0,
        solve_ms_mean=_mean([r.solve_ms for r in records]),
        solve_ms_max=max(r.solve_ms for r in records),
        iterations_mean=_mean(iterations) if (iterations := [r.iterations for r in records if r.iterations >= 0]) else None,
        lane_changes=sum(a.lane != b.lane for a, b in zip(records, records[1:])),
        fallback_steps=sum(r.fallback for r in records),
        verified_share=_mean([float(r.verified) for r in records]) if records[0].verified is not None else None,
        first_verified_step=(next((i for i, r in enumerate(records) if r.verified), None)
                             if records[0].verified is not None else None),
        failsafe_steps=sum(r.failsafe for r in records),
        min_clearance=min(r.clearance for r in records),
        off_centre_share=_mean([float(abs(r.y - r.lane * lane_width) > OFF_CENTRE) for r in records]),
    )
    durations = lane_change_durations(records, lane_width, dt)
    metrics["lane_change_s_mean"] = _mean(durations) if durations else None  # None: an empty cell, as NaN != NaN
    ttc = min(r.ttc for r in records)
    metrics.update(min_ttc=ttc if math.isfinite(ttc) else None, short_ttc_steps=sum(r.ttc < SHORT_TTC for r in records),
                   near_lane_change_steps=sum(r.lane_changes_near for r in records))
    return metrics
