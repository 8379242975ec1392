"""Closed-loop scenarios: what the ego wants, the road, the traffic, the MPC settings.

A scenario is a frozen, validated :class:`ScenarioConfig`, normally loaded from YAML in
``configs/scenarios/`` (:func:`load_scenario`). Every section rejects unknown keys. The two
sections with variants, ``objective`` and ``traffic``, pick theirs with a ``type`` key::

    objective: {type: cruise, v_cruise: 15.0}
    traffic: {type: idm, vehicles_count: 18, vehicles_density: 1.5, target_speeds: [7.0, 12.0]}

This module does not import highway-env; :mod:`mmpc.highway` turns a scenario into an
environment.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Mapping, Optional, Union

import torch

from mmpc.config import load_config, require, require_field_types, require_int, require_non_negative, require_positive
from mmpc.configs import shipped_config_dir
from mmpc.device import run_device
from mmpc.goals import CruiseGoals, GoalSampler, HighSpeedGoals, NearLaneGoals
from mmpc.meta_costs import CruiseCost, HighSpeedCost, LaneChangeCost, MetaCost, TaskRewardCost
from mmpc.mpc import MPC, MPCConfig
from mmpc.obstacles.shape import HIGHWAY_VEHICLE, ellipse_coverage, smallest_covering_axis
from mmpc.road import Road
from mmpc.solver.config import OptimizerConfig
from mmpc.solver.execution import COMPILE_ENV
from mmpc.solver.optimizer import BatchOptimizer
from mmpc.traffic_config import THREATS_MIN_FREQUENCY, IDMTraffic, NGSIMTraffic, ScriptedTraffic, Traffic

logger = logging.getLogger(__name__)

#: Obstacle ellipse semi-axes for highway-env [m] (the default cruise scenario's): it must hold the
#: Minkowski sum of two 5 m x 2 m cars with the ego turned over its heading band
#: (:func:`mmpc.obstacles.shape.ellipse_coverage` <= 1; the authors' (5.6, 3.0) does not). Figures:
#: docs/experiments/2026-11-21-differences-from-paper.md.
HIGHWAY_ELLIPSE = (8.0, 3.3)
#: Heading band [deg], the paper's 13 (the high-speed scenario keeps 8, which drove it better).
HIGHWAY_MAX_HEADING_DEG = 13.0
#: Band [deg] the heading step's targets are clipped to, 0.9 x the band above: the iterations
#: then stay inside the band (the heading polynomial overshoots clipped targets slightly).
HIGHWAY_HEADING_TARGET_DEG = 11.7
#: Back-offs of the iterations' projections (:attr:`mmpc.OptimizerConfig.obstacle_backoff`,
#: ``acceleration_backoff`` [m/s^2]): on the held-out problem corpus they find 8 % more
#: high-speed goals feasible at the same iteration count, and closed-loop fallbacks fell 2.5-9x
#: (docs/experiments/2026-11-24-expert-quality.md).
HIGHWAY_OBSTACLE_BACKOFF = 0.05
HIGHWAY_ACCELERATION_BACKOFF = 0.16
#: Obstacle ellipses widened to cover each car at its heading (:attr:`mmpc.MPCConfig.obstacle_shape`):
#: side impacts with cars changing lanes were most of the expert's crashes
#: (docs/experiments/2026-11-26-no-crash.md).
HIGHWAY_OBSTACLE_SHAPE = "heading"
#: Warm starts of the shipped scenarios (:attr:`mmpc.MPCConfig.warm_iterations`): 5-6x less solve per
#: step in closed loop; early exit on top saved nothing there (docs/experiments/2026-11-27-cheap-defaults.md).
HIGHWAY_WARM_ITERATIONS = 10
#: Overrides (:func:`load_scenario`) that give the paper's schedule instead: every step from the cold
#: start, all iterations; the paper's tables and the solver studies run it.
PAPER_SCHEDULE = {"mpc.warm_iterations": 0, "optimizer.exit_checks": []}
#: Folder of the scenarios that ship with mmpc (:attr:`ScenarioConfig.config_folder`).
SCENARIO_DIR = shipped_config_dir("scenarios")


def _speeds(where: str, name: str, values: tuple[float, ...]) -> None:
    for value in values:
        require_positive(where, **{name: value})


# ----------------------------------------------------------------------------------- objectives


def _near_lane_goals(where: str, speeds: tuple[float, ...], lanes: Optional[int]) -> None:
    _speeds(where, "near_lane_speeds", speeds)
    require(lanes is None or lanes >= 0,
             f"{where}: `near_lanes` must be null (every lane) or an int >= 0; got {lanes!r}")


@dataclass(frozen=True)
class CruiseObjective:
    """Cruise at ``v_cruise``: one goal per lane centre at ``v_cruise * horizon`` ahead plus
    goals on the lanes around the ego at other speeds (:class:`mmpc.NearLaneGoals`); meta cost
    ``sum_t (v - v_cruise)^2`` (:class:`mmpc.CruiseCost`).

    Attributes:
        v_cruise: cruise speed [m/s].
        near_lane_speeds: average speeds of the goals on the lanes around the ego [m/s]; empty
            for the lane-centre goals only.
        near_lanes: those goals sit on the ego's lane and this many lanes either side;
            ``None``: on every lane. (2: behind a wall of slow cars the way out can be two
            lanes over.)
        lane_change_cost: added to a candidate's meta cost per lane it changes
            (:class:`mmpc.meta_costs.LaneChangeCost`, hysteresis on the lane) [(m/s)^2 summed
            over the horizon]; 0: the paper's meta cost.
        task_reward_weight: re-weights the ranking by highway-env's reward
            (:class:`mmpc.meta_costs.TaskRewardCost`) [(m/s)^2 per sample of lost reward]; 0: the paper's.
    """

    kind: ClassVar[str] = "cruise"
    v_cruise: float = 15.0
    near_lane_speeds: tuple[float, ...] = (3.0, 6.0, 9.0, 12.0)
    near_lanes: Optional[int] = 2
    lane_change_cost: float = 0.0
    task_reward_weight: float = 0.0

    def __post_init__(self) -> None:
        require_field_types(self)
        require_positive("objective cruise", v_cruise=self.v_cruise)
        _near_lane_goals("objective cruise", self.near_lane_speeds, self.near_lanes)
        require_non_negative("objective cruise", lane_change_cost=self.lane_change_cost, task_reward_weight=self.task_reward_weight)

    @property
    def reference_speed(self) -> float:
        """The speed the meta cost pulls towards [m/s]."""
        return self.v_cruise

    @property
    def top_speed(self) -> float:
        """Highest speed a goal asks for [m/s]."""
        return max((self.v_cruise, *self.near_lane_speeds))

    def goal_sampler(self, road: Road, horizon: float) -> GoalSampler:
        lanes = CruiseGoals(v_cruise=self.v_cruise, horizon=horizon, num_goals=road.num_lanes)
        if not self.near_lane_speeds:
            return lanes
        return NearLaneGoals(lanes, speeds=self.near_lane_speeds, horizon=horizon, lanes_around=self.near_lanes)

    def meta_cost(self) -> MetaCost:
        return _ranked(CruiseCost(self.v_cruise), self.lane_change_cost, self.task_reward_weight)

    def stage_cost(self, v: float, y: float, road: Road) -> float:
        """The meta cost's term at one driven state (speed ``v`` [m/s], lateral ``y`` [m])."""
        return (v - self.v_cruise) ** 2


@dataclass(frozen=True)
class HighSpeedObjective:
    """High speed near the right lane: the authors' goal layout (:class:`mmpc.HighSpeedGoals`)
    plus goals on the lanes around the ego at several speeds (:class:`mmpc.NearLaneGoals`); meta
    cost ``sum_t w_speed (v - v_max)^2 + w_lane (y - y_right)^2`` (:class:`mmpc.HighSpeedCost`).

    Attributes:
        v_max: desired top speed [m/s].
        w_speed: weight of the speed term [s^2/m^2].
        w_lane: weight of the right-lane term [1/m^2].
        num_goals: goals of the authors' layout.
        right_lane_fraction: share of those on the right lane.
        right_lane_distances: (nearest, farthest) right-lane goal distance ahead [m].
        other_distance: distance ahead of the goals on the other lanes [m].
        near_lane_speeds: average speeds of the goals on the lanes around the ego [m/s]. Up to
            ``v_max``: the authors' goals lie 150-175 m ahead, an average of at most 21.9 m/s
            over 8 s, slower than the road allows.
        near_lanes: those goals sit on the ego's lane and this many lanes either side;
            ``None``: on every lane.
        lane_change_cost: added to a candidate's meta cost per lane it changes
            (:class:`mmpc.meta_costs.LaneChangeCost`); 0: the paper's meta cost.
        task_reward_weight: re-weights the ranking by highway-env's reward
            (:class:`mmpc.meta_costs.TaskRewardCost`) [meta-cost units per sample of lost reward]; 0: the paper's.
    """

    kind: ClassVar[str] = "high_speed"
    v_max: float = 24.0
    w_speed: float = 1.0
    w_lane: float = 0.1
    num_goals: int = 11
    right_lane_fraction: float = 0.6
    right_lane_distances: tuple[float, float] = (150.0, 175.0)
    other_distance: float = 160.0
    near_lane_speeds: tuple[float, ...] = (4.0, 8.0, 12.0, 16.0, 20.0, 22.0, 24.0)
    near_lanes: Optional[int] = 1
    lane_change_cost: float = 0.0
    task_reward_weight: float = 0.0

    def __post_init__(self) -> None:
        require_field_types(self)
        require_positive("objective high_speed", v_max=self.v_max, w_speed=self.w_speed, w_lane=self.w_lane)
        _near_lane_goals("objective high_speed", self.near_lane_speeds, self.near_lanes)
        require_non_negative("objective high_speed", lane_change_cost=self.lane_change_cost,
                             task_reward_weight=self.task_reward_weight)
        self._layout()  # validates the layout fields

    @property
    def reference_speed(self) -> float:
        return self.v_max

    @property
    def top_speed(self) -> float:
        return max((self.v_max, *self.near_lane_speeds))

    def _layout(self) -> HighSpeedGoals:
        return HighSpeedGoals(
            num_goals=self.num_goals, right_lane_fraction=self.right_lane_fraction,
            right_lane_distances=self.right_lane_distances, other_distance=self.other_distance,
        )

    def goal_sampler(self, road: Road, horizon: float) -> GoalSampler:
        if not self.near_lane_speeds:
            return self._layout()
        return NearLaneGoals(self._layout(), speeds=self.near_lane_speeds, horizon=horizon, lanes_around=self.near_lanes)

    def meta_cost(self) -> MetaCost:
        return _ranked(HighSpeedCost(self.v_max, self.w_speed, self.w_lane), self.lane_change_cost, self.task_reward_weight)

    def stage_cost(self, v: float, y: float, road: Road) -> float:
        """The meta cost's term at one driven state (speed ``v`` [m/s], lateral ``y`` [m])."""
        return self.w_speed * (v - self.v_max) ** 2 + self.w_lane * (y - road.right_lane_y) ** 2


def _ranked(cost: MetaCost, per_lane: float, task_reward_weight: float) -> MetaCost:
    """``cost`` with :class:`mmpc.meta_costs.LaneChangeCost` where ``per_lane`` > 0, then
    :class:`mmpc.meta_costs.TaskRewardCost` where ``task_reward_weight`` > 0."""
    cost = LaneChangeCost(cost, per_lane) if per_lane > 0 else cost
    return TaskRewardCost(cost, task_reward_weight) if task_reward_weight > 0 else cost


Objective = Union[CruiseObjective, HighSpeedObjective]


# ----------------------------------------------------------------------------------- scenario


@dataclass(frozen=True)
class EgoConfig:
    """The controlled vehicle at the start.

    Attributes:
        speed: initial speed [m/s].
        lane: initial lane (0 = leftmost); ``None`` draws it from the episode's seed.
    """

    speed: float = 14.0
    lane: Optional[int] = None

    def __post_init__(self) -> None:
        require_field_types(self)
        require(self.speed >= 0, f"ego: `speed` must be >= 0 m/s; got {self.speed!r}")
        require(self.lane is None or self.lane >= 0,
                 f"ego: `lane` must be null or an int >= 0; got {self.lane!r}")


#: The worlds a scenario runs in (``ScenarioConfig.sim``), and the highway-env environments the
#: batched simulator reproduces.
SIMULATORS = ("highway-env", "batched")
BATCHED_ENV_IDS = ("highway-v0", "highway-fast-v0")


def batched_unsupported(scenario: "ScenarioConfig") -> Optional[str]:
    """Why the batched simulator cannot run ``scenario`` (``None``: it can): it runs IDM traffic
    on the straight highways of :data:`BATCHED_ENV_IDS`."""
    if not isinstance(scenario.traffic, IDMTraffic):
        return (f"the batched simulator runs IDM traffic only, not {scenario.traffic.kind!r} traffic: "
                "run it with --sim highway-env")
    if scenario.env_id not in BATCHED_ENV_IDS:
        return (f"the batched simulator reproduces {list(BATCHED_ENV_IDS)}, not env_id {scenario.env_id!r}: "
                "run it with --sim highway-env")
    return None


@dataclass(frozen=True)
class ScenarioConfig:
    """One closed-loop scenario. Defaults: the paper's cruise scenario in dense slow traffic.

    Attributes:
        name: short name (output folders, tables).
        objective: what the ego wants (goal sampler + meta cost).
        lanes: number of lanes (4 m wide; lane 0 leftmost).
        duration: episode length [s].
        frequency: MPC rate = simulation rate [Hz]; highway-env applies an action only on the
            first frame of a step, so the two are equal and the MPC commands every frame.
        seeds: evaluation seeds.
        env_id: highway-env environment (``highway-v0`` checks collisions between all vehicles).
        sim: the world the episodes run in: ``highway-env`` (the reference, with video) or
            ``batched`` (:mod:`mmpc.sim`, thousands of environments stepped at once; IDM
            traffic on ``highway-v0`` or ``highway-fast-v0`` only, see :func:`batched_unsupported`).
        ego: the controlled vehicle at the start.
        traffic: the other vehicles.
        vehicle_size: (length, width) of every vehicle, the ego included [m]; ``None`` keeps
            highway-env's 5 m x 2 m (:data:`mmpc.obstacles.shape.HIGHWAY_VEHICLE`). highway-env's
            bicycle model turns with the length as wheelbase, and so does the MPC's steering
            (:func:`build_mpc`). Not with NGSIM traffic (recorded vehicles keep their recorded size).
        optimizer: batch optimizer settings (default: the authors' with :data:`HIGHWAY_ELLIPSE`,
            :data:`HIGHWAY_MAX_HEADING_DEG`, :data:`HIGHWAY_HEADING_TARGET_DEG` and the
            back-offs :data:`HIGHWAY_OBSTACLE_BACKOFF`, :data:`HIGHWAY_ACCELERATION_BACKOFF`). Its obstacle
            ellipse must cover two of the scenario's vehicles with the ego anywhere in the
            heading band and the other along the road (:func:`mmpc.obstacles.shape.ellipse_coverage`
            <= 1), else the scenario is refused: the ego could touch a car it plans to clear.
        mpc: receding-horizon settings (default: :class:`mmpc.MPCConfig`'s with
            :data:`HIGHWAY_OBSTACLE_SHAPE` and the warm starts :data:`HIGHWAY_WARM_ITERATIONS`;
            :data:`PAPER_SCHEDULE` turns them off).

    Scenarios written before mmpc derived the wheelbase and made compiling a run option may
    hold ``mpc.wheelbase`` and ``mpc.compile``; :meth:`upgrade` reads them.
    """

    config_folder: ClassVar[str] = "scenarios"
    name: str = "cruise"
    objective: Objective = field(default_factory=CruiseObjective)
    lanes: int = 6
    duration: float = 40.0
    frequency: float = 10.0
    seeds: tuple[int, ...] = tuple(range(20))
    env_id: str = "highway-v0"
    sim: str = "highway-env"
    ego: EgoConfig = field(default_factory=EgoConfig)
    traffic: Traffic = field(default_factory=IDMTraffic)
    vehicle_size: Optional[tuple[float, float]] = None
    optimizer: OptimizerConfig = field(
        default_factory=lambda: OptimizerConfig(
            ellipse_a=HIGHWAY_ELLIPSE[0],
            ellipse_b=HIGHWAY_ELLIPSE[1],
            max_heading_deg=HIGHWAY_MAX_HEADING_DEG,
            heading_target_deg=HIGHWAY_HEADING_TARGET_DEG,
            obstacle_backoff=HIGHWAY_OBSTACLE_BACKOFF,
            acceleration_backoff=HIGHWAY_ACCELERATION_BACKOFF,
        )
    )
    mpc: MPCConfig = field(default_factory=lambda: MPCConfig(obstacle_shape=HIGHWAY_OBSTACLE_SHAPE,
                                                             warm_iterations=HIGHWAY_WARM_ITERATIONS))

    def __post_init__(self) -> None:
        require_field_types(self)
        where = f"scenario {self.name!r}"
        require_int(where, low=1, lanes=self.lanes)
        require_positive(where, duration=self.duration, frequency=self.frequency)
        require(len(self.seeds) > 0 and all(s >= 0 for s in self.seeds),
                 f"{where}: `seeds` must be a non-empty list of ints >= 0; got {self.seeds!r}")
        require(self.sim in SIMULATORS, f"{where}: `sim` must be one of {list(SIMULATORS)}; got {self.sim!r}")
        if self.sim == "batched":
            reason = batched_unsupported(self)
            require(reason is None, f"{where}: {reason}")
        require(self.sim == "batched" or getattr(self.traffic, "threats", None) is None,
                f"{where}: threatening traffic (`traffic.threats`) runs on the batched simulator only; got sim "
                f"{self.sim!r}: set `sim: batched` (--sim batched)")
        require(getattr(self.traffic, "threats", None) is None or self.frequency >= THREATS_MIN_FREQUENCY,
                f"{where}: threatening traffic keeps its cars within the verification's assumptions only at "
                f"`frequency` >= {THREATS_MIN_FREQUENCY:g} Hz (longer frames make the lane-keeping controller "
                f"overshoot); got {self.frequency:g} Hz")
        require(self.ego.lane is None or self.ego.lane < self.lanes,
                 f"{where}: `ego.lane` must be < lanes={self.lanes}; got {self.ego.lane}")
        if isinstance(self.traffic, ScriptedTraffic):
            for vehicle in self.traffic.vehicles:
                for lane in (vehicle.lane, vehicle.cut_in_lane):
                    require(lane is None or lane < self.lanes, f"{where}: scripted vehicle lane {lane} must be < lanes={self.lanes}")
        if self.vehicle_size is not None:
            require_positive(where, vehicle_length=self.vehicle_size[0], vehicle_width=self.vehicle_size[1])
            require(not isinstance(self.traffic, NGSIMTraffic),
                     f"{where}: `vehicle_size` does not apply to NGSIM traffic (recorded vehicles keep their size)")
        self._check_ellipse(where)
        require(
            self.optimizer.v_max >= self.objective.top_speed,
            f"{where}: `optimizer.v_max` ({self.optimizer.v_max} m/s) must be >= the objective's speed "
            f"({self.objective.top_speed} m/s)",
        )
        require(
            self.mpc.num_obstacles <= self.optimizer.max_obstacles,
            f"{where}: `mpc.num_obstacles` ({self.mpc.num_obstacles}) must be <= `optimizer.max_obstacles` "
            f"({self.optimizer.max_obstacles})",
        )
        require(
            self.mpc.warm_iterations <= self.optimizer.iterations,
            f"{where}: `mpc.warm_iterations` ({self.mpc.warm_iterations}) must be <= `optimizer.iterations` "
            f"({self.optimizer.iterations}): a warm solve runs the last warm_iterations of the schedule",
        )

    def missing_data(self) -> Optional[str]:
        """What the scenario reads that this machine lacks (``None``: nothing): the NGSIM recording
        of NGSIM traffic, which mmpc does not ship (README, "NGSIM replay")."""
        if isinstance(self.traffic, NGSIMTraffic) and not Path(self.traffic.path).is_file():
            return (f"`traffic.path` {self.traffic.path} is not a file: the NGSIM recording is not shipped; "
                    "README, 'NGSIM replay', says where to download it and where to put it")
        return None

    @property
    def period(self) -> float:
        """The control period [s]: ``1 / frequency``."""
        return 1.0 / self.frequency

    def _check_ellipse(self, where: str) -> None:
        """Refuse an obstacle ellipse that does not cover two vehicles over the heading band."""
        axes, band, vehicle = self.optimizer.ellipse, self.optimizer.max_heading_deg, self.vehicle
        coverage = max(ellipse_coverage(axes, heading, vehicle=vehicle) for heading in (-band, band))
        if coverage <= 1.0:
            return
        smallest_b = smallest_covering_axis(axes[0], "a", (-band, band), vehicle)
        smallest_a = smallest_covering_axis(axes[1], "b", (-band, band), vehicle)
        options = [f"`optimizer.ellipse_b` >= {math.ceil(smallest_b * 100) / 100} m with a = {axes[0]} m"
                   if math.isfinite(smallest_b) else f"no b covers them with a = {axes[0]} m"]
        if math.isfinite(smallest_a):
            options.append(f"`optimizer.ellipse_a` >= {math.ceil(smallest_a * 100) / 100} m with b = {axes[1]} m")
        raise ValueError(
            f"{where}: the obstacle ellipse (a = {axes[0]} m, b = {axes[1]} m) does not cover two {vehicle[0]} m x "
            f"{vehicle[1]} m vehicles with the ego turned up to `optimizer.max_heading_deg` = {band} deg "
            f"(mmpc.obstacles.shape.ellipse_coverage {coverage:.3f} > 1): the ego could touch a car it plans to clear. "
            f"The smallest covering ellipse: {' or '.join(options)} (or a narrower heading band)"
        )

    @classmethod
    def upgrade(cls, values: dict, where: str) -> dict:
        """Read a scenario mapping written before the wheelbase was derived and compiling became
        a run option (:func:`mmpc.config.from_dict` calls this first).

        ``mpc.compile`` is dropped with a warning: compiling is chosen per run (``--compile``,
        :data:`mmpc.solver.execution.COMPILE_ENV`). ``mpc.wheelbase`` equal to the vehicle length is
        dropped with a warning; another value is refused, as the MPC now steers with the length.
        """
        mpc = values.get("mpc")
        if not isinstance(mpc, Mapping) or not {"compile", "wheelbase"} & set(mpc):
            return values
        mpc = dict(mpc)
        if "compile" in mpc:
            logger.warning("%s: `mpc.compile: %s` is ignored: compiling is a run option now (--compile auto|on|off, "
                           "or the environment variable %s=0/1); remove the key", where, mpc.pop("compile"), COMPILE_ENV)
        if "wheelbase" in mpc:
            wheelbase = mpc.pop("wheelbase")
            size = values.get("vehicle_size")
            length = size[0] if isinstance(size, (list, tuple)) and size else HIGHWAY_VEHICLE[0]
            if wheelbase != length:
                raise ValueError(
                    f"{where}: `mpc.wheelbase` is {wheelbase} m but the vehicles are {length} m long; the MPC steers with "
                    f"the vehicle length now (highway-env's bicycle turns with it): remove `mpc.wheelbase`, and set "
                    f"`vehicle_size: [{wheelbase}, WIDTH]` if the cars are {wheelbase} m long")
            logger.warning("%s: `mpc.wheelbase` is ignored: the MPC takes the vehicle length (%s m); remove the key",
                           where, length)
        return {**values, "mpc": mpc}

    @property
    def vehicle(self) -> tuple[float, float]:
        """Every vehicle's (length, width) [m]: ``vehicle_size`` or highway-env's."""
        return self.vehicle_size if self.vehicle_size is not None else HIGHWAY_VEHICLE

    @property
    def road(self) -> Road:
        """The road the goals and meta cost refer to (4 m lanes, highway-env's layout)."""
        return Road(num_lanes=self.lanes)

    def replace(self, **changes: Any) -> "ScenarioConfig":
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)


def build_mpc(scenario: ScenarioConfig, *, compile: bool | str = "auto", device: torch.device | str | None = None,
              fixed_shapes: bool = False) -> MPC:
    """The scenario's MPC (float32): its optimizer, goals, meta cost and loop settings, the
    vehicle length as wheelbase and the scenario's period as its control period.

    Args:
        scenario: the scenario.
        compile: ``"auto"`` (default): compiled on the CPU when a C++ compiler is found, unless
            the environment variable :data:`mmpc.solver.execution.COMPILE_ENV` (``MMPC_COMPILE``) says
            0 (eager) or 1 (compiled); the command line's ``--compile auto|on|off`` sets that
            variable, so worker processes inherit it. ``True`` / ``False`` decide here. See
            :class:`mmpc.BatchOptimizer`.
        device: where it computes; ``None``: the run's device (:func:`mmpc.device.run_device`,
            the CPU unless ``--device`` / ``MMPC_DEVICE`` says otherwise).
        fixed_shapes: a step that reads nothing on the host (:class:`mmpc.mpc.MPC`'s ``fixed_shapes``).
    """
    road = scenario.road
    optimizer = BatchOptimizer(scenario.optimizer, device=run_device() if device is None else device, compile=compile)
    goals = scenario.objective.goal_sampler(road, optimizer.config.horizon)
    return MPC(optimizer, goals, scenario.objective.meta_cost(), road, scenario.mpc, wheelbase=scenario.vehicle[0],
               vehicle_width=scenario.vehicle[1], control_period=scenario.period, fixed_shapes=fixed_shapes)


def load_scenario(name_or_path: str | Path, overrides: Optional[Mapping[str, Any]] = None) -> ScenarioConfig:
    """:func:`mmpc.config.load_config` for scenarios: ``configs/scenarios/<name>.yaml`` or a YAML path.

    Args:
        name_or_path: a shipped scenario's name or a path.
        overrides: ``{"section.key": value}`` replacing values of the file before validation
            (e.g. ``{"traffic.lane_changes": True, "name": "cruise_mobil"}``); a key the
            scenario does not know is an error, as in the file.
    """
    return load_config(ScenarioConfig, name_or_path, overrides)
