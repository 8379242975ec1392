"""Lockstep rollouts that record what an imitation learner needs: highway-env's kinematics
observation, the executed (acceleration, steering) command, the reward, the episode's end, the
deciding driver's diagnostics, and the road-frame state the cloned policy reads (the ego and
its nearest neighbours, :mod:`mmpc.imitation.features`).

The episodes run through mmpc's one episode loop, :func:`mmpc.highway.run_lockstep` (one
driver call per control step for every episode still running); :class:`RolloutRecorder` is its
observer, and hands each finished episode to a callback at once (so a generator can write it to
disk before the others end) as an :class:`Episode` of numpy arrays.

Alignment (Minari's): ``observations`` has T + 1 rows (the state after the last command
included), ``actions``, ``rewards``, ``terminations`` and ``truncations`` T rows; the info
arrays have T + 1 rows, row t describing the decision taken at ``observations[t]``; the last
row (no decision) holds -1 / NaN / False, its ``ego`` and ``neighbours`` the final state.
"""

from __future__ import annotations

import math
from typing import Callable, Mapping, NamedTuple, Optional, Sequence

import numpy as np
import torch

from mmpc.drivers import Decision, Driver, Observation
from mmpc.highway import ACCELERATION_RANGE, STEERING_RANGE, HighwayEpisode, Observer, Step, run_lockstep
from mmpc.imitation.features import STORED_NEIGHBOURS, nearest_neighbours
from mmpc.problem import EGO_V, EGO_Y
from mmpc.scenario import ScenarioConfig

#: Per-step info arrays of an :class:`Episode`: name -> (dtype, per-row shape, value of the final row).
INFO_FIELDS: dict[str, tuple[type, tuple[int, ...], float]] = {
    "goal_index": (np.int64, (), -1),           # chosen goal of the expert (-1: the driver has none)
    "feasible_goals": (np.int64, (), -1),       # number of feasible candidates (-1: not applicable)
    "fallback": (np.bool_, (), False),          # no candidate was feasible
    "plan_cost": (np.float64, (), math.nan),    # the chosen plan's meta cost as the MPC ranked it
    "meta_cost": (np.float64, (), math.nan),    # the scenario's meta-cost term at this state
    "residual_obstacle": (np.float64, (), math.nan),       # chosen plan's final residuals
    "residual_nonholonomic": (np.float64, (), math.nan),
    "residual_acceleration": (np.float64, (), math.nan),
    "solve_ms": (np.float64, (), math.nan),     # wall time of the decision (all lockstep rows) [ms]
    "ego": (np.float32, (6,), math.nan),        # road-frame ego state x, y, psi, v, a, psidot
    # the nearest other vehicles' road-frame x, y, vx, vy (nearest first, NaN rows: none)
    "neighbours": (np.float32, (STORED_NEIGHBOURS, 4), math.nan),
}


class Episode(NamedTuple):
    """One recorded episode (T control steps).

    Fields:
        seed: the episode's seed.
        observations: (T + 1, R, F) float32 highway-env kinematics observations.
        actions: (T, 2) float32 executed (acceleration [m/s^2], steering [rad]), clipped to
            highway-env's ranges as applied.
        rewards: (T,) float64 highway-env's reward after each command.
        terminations: (T,) bool, True on the step the ego crashed.
        truncations: (T,) bool, True on the last step of an episode that reached the duration.
        infos: :data:`INFO_FIELDS` name (and any extra field the recorder was given) -> (T + 1, ...) array.
    """

    seed: int
    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    terminations: np.ndarray
    truncations: np.ndarray
    infos: dict[str, np.ndarray]

    @property
    def steps(self) -> int:
        return int(self.actions.shape[0])


class Rollout(NamedTuple):
    """An episode and, when asked for, the driver's input at each of its T steps (E = 1 each),
    which an expert can label later (DAgger)."""

    episode: Episode
    states: Optional[list[Observation]]


def executed_command(acceleration: float, steering: float) -> tuple[float, float]:
    """The command highway-env applies: clipped to :data:`ACCELERATION_RANGE` / :data:`STEERING_RANGE`."""
    return (min(max(acceleration, ACCELERATION_RANGE[0]), ACCELERATION_RANGE[1]),
            min(max(steering, STEERING_RANGE[0]), STEERING_RANGE[1]))


def observation_neighbours(observation: Observation, ellipse: tuple[float, float]) -> np.ndarray:
    """(E, :data:`STORED_NEIGHBOURS`, 4) nearest other vehicles of each row (:func:`nearest_neighbours`
    in the scenario's obstacle ``ellipse``)."""
    mask = None if observation.vehicle_mask is None else observation.vehicle_mask.numpy()
    return nearest_neighbours(observation.ego.numpy(), observation.vehicles.numpy(), mask, ellipse=ellipse)


def decision_infos(decision: Decision, observation: Observation, scenario: ScenarioConfig) -> dict[str, np.ndarray]:
    """The :data:`INFO_FIELDS` of each of the E rows of a decision, as (E, ...) arrays."""
    count = observation.num_envs
    infos = {
        "goal_index": decision.goal_index.numpy().astype(np.int64),
        "feasible_goals": decision.feasible_goals.numpy().astype(np.int64),
        "fallback": decision.fallback.numpy().astype(np.bool_),
        "plan_cost": decision.plan_cost.double().numpy(),
        "meta_cost": np.array([scenario.objective.stage_cost(float(e[EGO_V]), float(e[EGO_Y]), scenario.road)
                               for e in observation.ego], dtype=np.float64),
        "solve_ms": np.full(count, decision.solve_ms, dtype=np.float64),
        "ego": observation.ego.float().numpy(),
        "neighbours": observation_neighbours(observation, scenario.optimizer.ellipse),
    }
    for name in ("residual_obstacle", "residual_nonholonomic", "residual_acceleration"):
        if decision.plan is None:
            infos[name] = np.full(count, math.nan)
        else:
            residual = getattr(decision.plan.result, name)  # where the driver computed it
            index = decision.goal_index.to(residual.device)
            infos[name] = residual[torch.arange(count, device=residual.device), index].double().cpu().numpy()
    return infos


class RolloutRecorder(Observer):
    """Records :class:`Rollout` s from :func:`mmpc.highway.run_lockstep` (an observer).

    Args:
        scenario: the scenario driven.
        seeds: the seeds given to the runner, in its order.
        keep_states: also keep the driver's input of every step (:attr:`Rollout.states`).
        on_finished: called with each episode as soon as it ends.
        extra_fields: more per-step infos, declared as :data:`INFO_FIELDS` are (e.g. the expert's
            ranking of every goal, :mod:`mmpc.imitation.labels`), and ``extra_infos()``, called
            after every decision, returns them as (E, ...) arrays, one row per deciding environment.
    """

    def __init__(self, scenario: ScenarioConfig, seeds: Sequence[int], *, keep_states: bool = False,
                 on_finished: Optional[Callable[[Rollout], None]] = None,
                 extra_fields: Mapping[str, tuple[type, tuple[int, ...], float]] = {},
                 extra_infos: Optional[Callable[[], dict[str, np.ndarray]]] = None) -> None:
        clash = sorted(set(extra_fields) & set(INFO_FIELDS))
        if clash or bool(extra_fields) != (extra_infos is not None):
            raise ValueError(f"`extra_fields` must name new infos ({clash} exist already) and come with `extra_infos`")
        self.scenario = scenario
        self.seeds = list(seeds)
        self.on_finished = on_finished
        self.fields = {**INFO_FIELDS, **extra_fields}
        self.extra_infos = extra_infos
        self.rollouts: list[Optional[Rollout]] = [None] * len(self.seeds)
        self._rows = [_Rows(keep_states) for _ in self.seeds]
        self._infos: dict[str, np.ndarray] = {}

    def decided(self, observation: Observation, decision: Decision, active: Sequence[int]) -> None:
        self._infos = decision_infos(decision, observation, self.scenario)
        if self.extra_infos is not None:
            self._infos.update(self.extra_infos())

    def applied(self, step: Step) -> None:
        rows = self._rows[step.index]
        rows.observations.append(step.batch.kinematics[step.row])
        rows.infos.append({name: values[step.row] for name, values in self._infos.items()})
        if rows.states is not None:
            rows.states.append(step.observation)
        rows.actions.append(executed_command(float(step.decision.acceleration[step.row]),
                                             float(step.decision.steering[step.row])))
        rows.rewards.append(step.episode.reward)

    def finished(self, index: int, episode: HighwayEpisode) -> None:
        self.rollouts[index] = self._rows[index].finish(self.seeds[index], episode, self.fields)
        if self.on_finished is not None:
            self.on_finished(self.rollouts[index])


class _Rows:
    """Rows of one episode while it runs."""

    def __init__(self, keep_states: bool) -> None:
        self.observations: list[np.ndarray] = []
        self.actions: list[tuple[float, float]] = []
        self.rewards: list[float] = []
        self.infos: list[dict[str, np.ndarray]] = []
        self.states: Optional[list[Observation]] = [] if keep_states else None

    def finish(self, seed: int, episode: HighwayEpisode, fields: Mapping[str, tuple[type, tuple[int, ...], float]]) -> Rollout:
        final = episode.observe()
        self.observations.append(final.kinematics[0])
        steps = len(self.actions)
        infos = {}
        for name, (dtype, shape, fill) in fields.items():
            column = np.full((steps + 1, *shape), fill, dtype=dtype)
            for t, row in enumerate(self.infos):
                column[t] = row[name]
            infos[name] = column
        infos["ego"][steps] = final.ego[0].float().numpy()
        infos["neighbours"][steps] = observation_neighbours(final, episode.scenario.optimizer.ellipse)[0]
        infos["meta_cost"][steps] = episode.scenario.objective.stage_cost(
            float(final.ego[0, EGO_V]), float(final.ego[0, EGO_Y]), episode.scenario.road)
        terminations = np.zeros(steps, dtype=np.bool_)
        truncations = np.zeros(steps, dtype=np.bool_)
        if steps:
            crashed = bool(episode.ego.crashed)
            terminations[-1] = crashed
            truncations[-1] = not crashed
        recorded = Episode(
            seed=seed,
            observations=np.stack(self.observations).astype(np.float32),
            actions=np.asarray(self.actions, dtype=np.float32).reshape(steps, 2),
            rewards=np.asarray(self.rewards, dtype=np.float64),
            terminations=terminations,
            truncations=truncations,
            infos=infos,
        )
        return Rollout(recorded, self.states)


def rollout_lockstep(
    scenario: ScenarioConfig,
    seeds: Sequence[int],
    driver: Driver,
    *,
    keep_states: bool = False,
    on_finished: Optional[Callable[[Rollout], None]] = None,
    extra_fields: Mapping[str, tuple[type, tuple[int, ...], float]] = {},
    extra_infos: Optional[Callable[[], dict[str, np.ndarray]]] = None,
) -> list[Rollout]:
    """Drive one episode per seed in lockstep with ``driver`` (:func:`mmpc.highway.run_lockstep`)
    and record every step (:class:`RolloutRecorder`).

    Args:
        scenario: the scenario (its ``duration`` sets the length; an episode ends early at a
            collision).
        seeds: distinct seeds, at least one.
        driver: who drives (the MPC expert for demonstrations, a learner for DAgger).
        keep_states: also keep the driver's input of every step (:attr:`Rollout.states`).
        on_finished: called with each episode as soon as it ends.
        extra_fields, extra_infos: more per-step infos (:class:`RolloutRecorder`).

    Returns:
        One :class:`Rollout` per seed, in the order of ``seeds``.
    """
    recorder = RolloutRecorder(scenario, seeds, keep_states=keep_states, on_finished=on_finished,
                               extra_fields=extra_fields, extra_infos=extra_infos)
    run_lockstep(scenario, seeds, driver=driver, observers=[recorder])
    return [rollout for rollout in recorder.rollouts if rollout is not None]
