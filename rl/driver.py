"""Trained stable-baselines3 agents as :class:`mmpc.drivers.Driver` s (``mmpc drive --driver sb3:MODEL.zip``).

:func:`make_sb3_driver` reads the run's ``config.yaml`` (written by ``mmpc rl train``) to know
what the model was trained on:

- a safe-layer agent (``--env safe``) picks a goal every ``decision_frames`` control steps from
  its observation (highway-env kinematics + solver features); the goal is held while the safety
  layer plans towards it at every step, or plans at the decision and tracks the plan in between,
  as the agent was trained (``replan``, :class:`SafeAgentDriver`);
- a plain agent (``--env plain``, or ``--env highway``: plain highway-env) with highway-env's
  ``DiscreteMetaAction`` has its meta-action executed as highway-env's ``MDPVehicle`` does
  (:class:`MetaActionDriver`); a plain highway-env agent with continuous actions has its action
  mapped to acceleration and steering. Either holds its action for ``decision_frames`` steps.

The SB3 policies run on the CPU and read numpy; a safe-layer driver computes on its safety
layer's device (:attr:`SafeAgentDriver.device`, the run's), the plain ones on the CPU.
"""

from __future__ import annotations

import time
import zlib
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterable, Optional

import numpy as np
import torch

from mmpc.drivers import Candidates, Decision, Driver, Observation
from mmpc.rl.meta_actions import MetaActions, MetaTargets

if TYPE_CHECKING:
    from mmpc.rl.agent_step import AgentStep
    from mmpc.rl.safety import DecisionSolve, SafePlan
    from mmpc.rl.runs import TrainedRun
    from mmpc.scenario import ScenarioConfig


def _flat_kinematics(observation: Observation, rows: list[int], vehicles: int) -> np.ndarray:
    if observation.kinematics is None:
        raise ValueError("the sb3 driver needs highway-env's Kinematics observation (`Observation.kinematics`)")
    kinematics = np.asarray(observation.kinematics, dtype=np.float32)[rows]
    if kinematics.ndim != 3 or kinematics.shape[1] != vehicles:
        raise ValueError(f"the agent was trained on {vehicles} Kinematics rows; the observation has shape {kinematics.shape[1:]}")
    return kinematics.reshape(len(rows), -1)


class _Hold:
    """Per-environment actions held for ``frames`` control steps."""

    def __init__(self, frames: int) -> None:
        self.frames = frames
        self.values: dict[int, Any] = {}
        self.left: dict[int, int] = {}

    def clear(self) -> None:
        self.values.clear()
        self.left.clear()

    def due(self, ids: list[int]) -> list[int]:
        """Rows whose environment needs a new decision."""
        return [row for row, env in enumerate(ids) if self.left.get(env, 0) <= 0]

    def set(self, env: int, value: Any) -> None:
        self.values[env] = value
        self.left[env] = self.frames

    def refresh(self, ids: list[int], fresh: Callable[[list[int]], Iterable[Any]]) -> list[Any]:
        """The held value of every row of ``ids`` after rows that are due got ``fresh(due_rows)``;
        then one control step passes."""
        due = self.due(ids)
        if due:
            for row, value in zip(due, fresh(due)):
                self.set(ids[row], value)
        values = [self.values[env] for env in ids]
        self.tick(ids)
        return values

    def tick(self, ids: list[int]) -> None:
        for env in ids:
            self.left[env] -= 1


class SafeAgentDriver(Driver):
    """A safe-layer agent: its goal choice executed through the safety layer, as in training
    (:attr:`mmpc.rl.config.SafeEnvConfig.replan`):

    - ``replan: frame``: the held goal is planned afresh at every frame (:meth:`SafetyLayer.plan`);
    - ``replan: decision``: the goal is planned at the agent's decision (discrete goals: chosen from
      the solve behind the observation's features) and the plan tracked over the agent step's
      other frames, solved again only where it is no longer safe (:meth:`SafetyLayer.frame`).

    Both run the agent step of training (:class:`mmpc.rl.agent_step.AgentStep`), one frame per call.
    In decision mode a row that tracked its plan (or was solved again inside the layer) has no
    candidates to report: its decision row carries ``goal_index`` -1 and ``plan_cost`` NaN, with
    the layer's ``fallback`` and the ``feasible_goals`` of the solve behind the plan executed;
    ``candidates`` and ``plan`` are given only when every row executes one fresh plan.

    Args:
        run: the trained run (model, environment settings).
        scenario: the scenario driven (its MPC supplies the standard goals and the meta cost).
    """

    name = "sb3-safe"

    def __init__(self, run: "TrainedRun", scenario: "ScenarioConfig") -> None:
        from mmpc.rl.safety import SafetyLayer

        self.model = run.model
        self.continuous = run.continuous
        self.config = run.config.env
        self.layer = SafetyLayer.for_scenario(scenario, self.config)
        self.period = scenario.period
        self.steps: dict[int, tuple["AgentStep", int]] = {}  # environment id -> its agent step, its row in it
        #: frames the layer overrode the agent (another candidate or the fallback drove), per
        #: environment id since the last reset
        self.intervention_frames: dict[int, int] = {}

    @property
    def device(self) -> torch.device:
        """Where the safety layer computes (its MPC's device): the runner hands observations there."""
        return self.layer.device

    def reset(self, num_envs: int) -> None:
        self.steps.clear()
        self.layer.forget()
        self.intervention_frames = dict.fromkeys(range(num_envs), 0)

    def _choose(self, observation: Observation, due: list[int]) -> tuple[Observation, Optional["DecisionSolve"], torch.Tensor]:
        """The agent's new choice for the rows ``due``: their road-frame state, the decision solve
        behind their solver features (also made for a discrete ``replan: decision`` agent; else
        None) and the actions (float (R, 2) continuous, long (R,) discrete)."""
        from mmpc.rl.safety import observation_rows

        sub = observation_rows(observation, torch.as_tensor(due, dtype=torch.long))
        solve = self.layer.decision_solve(sub) if self.layer.needs_decision_solve(self.continuous) else None
        parts = [_flat_kinematics(observation, due, self.config.kinematics_vehicles)]
        if self.config.solver_features:
            parts.append(self.layer.features(solve).reshape(len(due), -1))
        vector = np.clip(np.concatenate(parts, axis=1), -1.0, 1.0).astype(np.float32)
        actions, _ = self.model.predict(vector, deterministic=True)
        if self.continuous:
            return sub, solve, torch.as_tensor(np.asarray(actions, dtype=np.float32))
        return sub, solve, torch.as_tensor(np.asarray(actions).reshape(-1), dtype=torch.long)

    def decide(self, observation: Observation) -> Decision:
        """Rows whose agent step is over (or that have none) get the agent's new choice, one
        :class:`mmpc.rl.agent_step.AgentStep` for all of them; then every row executes the next
        frame of its step, one safety-layer call per step (rows start together, so normally one)."""
        from mmpc.rl.agent_step import AgentStep
        from mmpc.rl.safety import observation_rows

        start = time.perf_counter()
        ids = observation.ids().tolist()
        due = [row for row, env in enumerate(ids) if env not in self.steps or self.steps[env][0].over]
        compile_ms = 0.0
        if due:
            sub, solve, actions = self._choose(observation, due)
            step = AgentStep.begin(self.layer, sub, actions, continuous=self.continuous, period=self.period, solve=solve)
            if step.decided is not None:
                compile_ms += step.decided.plan.compile_ms
            for member, row in enumerate(due):
                self.steps[ids[row]] = (step, member)
        groups: dict[int, tuple["AgentStep", list[int], list[int]]] = {}  # id(step) -> step, rows, its members
        for row, env in enumerate(ids):
            step, member = self.steps[env]
            group = groups.setdefault(id(step), (step, [], []))
            group[1].append(row)
            group[2].append(member)
        count, device = len(ids), self.device
        decision = Decision.command_only(torch.zeros(count, dtype=self.layer.mpc.optimizer.dtype, device=device),
                                         torch.zeros(count, dtype=self.layer.mpc.optimizer.dtype, device=device), 0.0)
        if self.layer.guard is not None:
            decision = decision._replace(verified=torch.zeros(count, dtype=torch.bool, device=device),
                                         failsafe=torch.zeros(count, dtype=torch.bool, device=device))
        plans = []
        for step, rows, members in groups.values():
            index = torch.as_tensor(rows, dtype=torch.long, device=device)
            control = step.frame(observation_rows(observation, index), torch.as_tensor(members, dtype=torch.long))
            if step.frame_solved:
                compile_ms += self.layer.mpc.optimizer.last_compile_ms
            decision.acceleration[index] = control.acceleration.to(decision.acceleration.dtype)
            decision.steering[index] = control.steering.to(decision.steering.dtype)
            decision.fallback[index] = control.fallback
            decision.feasible_goals[index] = control.feasible_goals
            if control.verified is not None:
                decision.verified[index], decision.failsafe[index] = control.verified, control.failsafe
            for row, intervened in zip(rows, control.intervention.tolist()):
                self.intervention_frames[ids[row]] = self.intervention_frames.get(ids[row], 0) + intervened
            if control.plan is not None:
                decision.goal_index[index] = control.plan.plan.selection.index
                decision.plan_cost[index] = control.plan.plan.selection.cost.to(decision.plan_cost.dtype)
            plans.append(control.plan)
        solve_ms = (time.perf_counter() - start) * 1e3 - compile_ms
        if len(plans) == 1 and plans[0] is not None and self.layer.guard is None:  # one fresh plan executed: the whole of it
            return _plan_decision(plans[0], solve_ms)
        return decision._replace(solve_ms=solve_ms)


def _plan_decision(safe: "SafePlan", solve_ms: float) -> Decision:
    """The decision of a safety-layer plan that served every row."""
    plan = safe.plan
    trajectories = plan.result.trajectories
    return Decision(
        acceleration=plan.acceleration,
        steering=plan.steering,
        solve_ms=solve_ms,
        goal_index=plan.selection.index,
        feasible_goals=safe.feasible_goals,
        fallback=safe.fallback,
        plan_cost=plan.selection.cost,
        candidates=Candidates(torch.stack([trajectories.x, trajectories.y], dim=-1), plan.result.feasible,
                              plan.selection.index, plan.problem.goals),
        plan=plan,
    )


class ContinuousActionDriver(Driver):
    """A plain highway-env agent with ``ContinuousAction``: [-1, 1]^2 -> acceleration, steering."""

    name = "sb3"

    def __init__(self, run: "TrainedRun") -> None:
        from mmpc.highway import ACCELERATION_RANGE, STEERING_RANGE

        self.model = run.model
        self.vehicles = run.config.env.kinematics_vehicles
        self.ranges = (ACCELERATION_RANGE, STEERING_RANGE)
        self.hold = _Hold(run.config.env.decision_frames)

    def reset(self, num_envs: int) -> None:
        self.hold.clear()

    def _actions(self, observation: Observation, due: list[int]) -> np.ndarray:
        """The agent's new actions in [-1, 1]^2 for the rows ``due``."""
        actions, _ = self.model.predict(_flat_kinematics(observation, due, self.vehicles), deterministic=True)
        return np.clip(np.asarray(actions, dtype=np.float64).reshape(len(due), 2), -1.0, 1.0)

    def decide(self, observation: Observation) -> Decision:
        start = time.perf_counter()
        ids = [int(i) for i in observation.ids()]
        actions = np.stack(self.hold.refresh(ids, lambda due: self._actions(observation, due)))
        (a_low, a_high), (s_low, s_high) = self.ranges
        acceleration = a_low + 0.5 * (actions[:, 0] + 1.0) * (a_high - a_low)
        steering = s_low + 0.5 * (actions[:, 1] + 1.0) * (s_high - s_low)
        return Decision.command_only(torch.as_tensor(acceleration, dtype=torch.float32),
                                     torch.as_tensor(steering, dtype=torch.float32), (time.perf_counter() - start) * 1e3)


class MetaActionDriver(Driver):
    """A plain agent with highway-env's ``DiscreteMetaAction`` (0 LANE_LEFT, 1 IDLE, 2 LANE_RIGHT,
    3 FASTER, 4 SLOWER), executed as highway-env's ``MDPVehicle`` executes it
    (:class:`mmpc.rl.meta_actions.MetaActions`, the plain environments' controller, with the run's
    ``env.meta_speeds``): a new meta-action every ``decision_frames`` frames, the lane and speed
    controller's command at every frame (L the scenario's vehicle length, highway-env's 5 m
    unless ``vehicle_size`` says otherwise)."""

    name = "sb3"

    def __init__(self, run: "TrainedRun", scenario: "ScenarioConfig") -> None:
        self.model = run.model
        self.vehicles = run.config.env.kinematics_vehicles
        self.meta = MetaActions(scenario.road, scenario.vehicle[0], run.config.env.meta_speeds)
        self.hold = _Hold(run.config.env.decision_frames)
        self.targets: dict[int, tuple[int, int]] = {}  # environment -> (lane, speed index)

    def reset(self, num_envs: int) -> None:
        self.hold.clear()
        self.targets.clear()

    def decide(self, observation: Observation) -> Decision:
        start = time.perf_counter()
        ids = [int(i) for i in observation.ids()]
        ego = observation.ego.to(torch.float64).cpu()
        new = [row for row, env in enumerate(ids) if env not in self.targets]
        if new:
            started = self.meta.start(ego[new])
            self.targets.update((ids[row], (int(lane), int(index)))
                                for row, lane, index in zip(new, started.lane, started.speed_index))
        lanes, indices = zip(*(self.targets[env] for env in ids))
        targets = MetaTargets(torch.tensor(lanes), torch.tensor(indices))
        due = self.hold.due(ids)
        if due:
            actions, _ = self.model.predict(_flat_kinematics(observation, due, self.vehicles), deterministic=True)
            actions = np.asarray(actions).reshape(-1)
            rows = torch.tensor(due)
            moved = self.meta.apply(targets.select(rows), torch.as_tensor(actions), ego[rows])
            targets.lane[rows], targets.speed_index[rows] = moved.lane, moved.speed_index
            for row, action in zip(due, actions):
                self.targets[ids[row]] = (int(targets.lane[row]), int(targets.speed_index[row]))
                self.hold.set(ids[row], int(action))
        self.hold.tick(ids)
        acceleration, steering = self.meta.command(targets, ego)
        return Decision.command_only(acceleration.to(torch.float32), steering.to(torch.float32),
                                     (time.perf_counter() - start) * 1e3)


class RandomGoals:
    """A stand-in for a trained model: uniformly random discrete actions (the grid's goals, and
    the expert's choice with ``expert_action``), the layer's least careful user. Each row's action
    is drawn from a generator seeded by ``seed`` and the bytes of the row's first ``key_size``
    observation values (the Kinematics rows), so an episode gets the same actions whichever
    lockstep group, batch position or worker drives it."""

    def __init__(self, num_goals: int, key_size: int, seed: int = 0) -> None:
        self.num_goals = num_goals
        self.key_size = key_size
        self.seed = seed

    def predict(self, observations: np.ndarray, deterministic: bool = True) -> tuple[np.ndarray, None]:
        keys = np.ascontiguousarray(np.asarray(observations, dtype=np.float32)[:, :self.key_size])
        return np.array([np.random.default_rng([self.seed, zlib.crc32(row.tobytes())]).integers(self.num_goals)
                         for row in keys], dtype=np.int64), None


class ExpertChoice:
    """A stand-in for a trained model that always takes the expert action (the last discrete
    action with ``expert_action``): the MPC expert at the agent's decision rate."""

    def __init__(self, action: int) -> None:
        self.action = action

    def predict(self, observations: np.ndarray, deterministic: bool = True) -> tuple[np.ndarray, None]:
        return np.full(len(observations), self.action, dtype=np.int64), None


class RandomSafeAgentDriver(SafeAgentDriver):
    """Random discrete goals behind the safety layer (``safe-random[:RL_CONFIG]``): what the
    layer alone guarantees, whatever an agent asks."""

    name = "safe-random"


class ExpertSafeAgentDriver(SafeAgentDriver):
    """The expert action at every decision (``safe-expert[:RL_CONFIG]``): what an agent gets by
    always deferring to the MPC expert, the baseline a trained agent has to beat."""

    name = "safe-expert"


def _stand_in_run(scenario: "ScenarioConfig", config: Optional[str], **env_settings: Any) -> "TrainedRun":
    """A run of the RL config ``config`` (a shipped name, a YAML path, a training run's folder or
    its ``config.yaml``, or None: the defaults) on ``scenario``, with ``env_settings`` on top, for
    a stand-in model."""
    import dataclasses

    from mmpc.config import load_config
    from mmpc.rl.config import RLConfig
    from mmpc.rl.runs import TrainedRun, recorded_config

    run_config = (recorded_config(config) if config else None) or load_config(RLConfig, config or None)
    run_config = dataclasses.replace(run_config, scenario=scenario, env=dataclasses.replace(run_config.env, **env_settings))
    return TrainedRun(None, "stand-in", "safe", False, run_config)


def make_random_safe_driver(scenario: "ScenarioConfig", config: Optional[str]) -> Driver:
    """The driver of ``safe-random[:RL_CONFIG]`` (registry entry ``"safe-random"``): random
    discrete actions behind the safety layer of ``scenario``, with the environment settings (goal
    grid, ``replan``, ...) of the RL config ``RL_CONFIG`` (a shipped name such as ``high_speed``,
    a YAML path, or a training run's folder: the agent's own settings; default: the defaults,
    :class:`mmpc.rl.config.SafeEnvConfig`)."""
    from mmpc.rl.spaces import KINEMATICS_FEATURES

    run = _stand_in_run(scenario, config)
    env = run.config.env
    model = RandomGoals(env.num_actions, key_size=env.kinematics_vehicles * len(KINEMATICS_FEATURES))
    return RandomSafeAgentDriver(run._replace(model=model), scenario)


def make_expert_safe_driver(scenario: "ScenarioConfig", config: Optional[str]) -> Driver:
    """The driver of ``safe-expert[:RL_CONFIG]`` (registry entry ``"safe-expert"``): the expert
    action at every decision, with the environment settings of ``RL_CONFIG`` (as
    ``safe-random``) and ``replan: decision``, ``expert_action: true`` on top."""
    run = _stand_in_run(scenario, config, replan="decision", expert_action=True)
    return ExpertSafeAgentDriver(run._replace(model=ExpertChoice(run.config.env.num_discrete_goals)), scenario)


def make_sb3_driver(scenario: "ScenarioConfig", path: Optional[str]) -> Driver:
    """The driver of ``sb3:MODEL.zip`` (the registry entry ``"sb3"`` of :data:`mmpc.drivers.DRIVERS`).

    Args:
        scenario: the scenario to drive.
        path: ``model.zip`` (or a checkpoint) of a run written by ``mmpc rl train``, or the name
            of a shipped agent (:func:`mmpc.rl.runs.shipped_models`).
    """
    from mmpc.rl.runs import load_run

    if not path:
        raise ValueError("driver 'sb3' needs a model: sb3:RUN/model.zip or a shipped agent's name")
    run = load_run(path)
    if scenario.road != run.config.scenario.road:
        raise ValueError(f"the agent was trained on {run.config.scenario.road}; scenario {scenario.name!r} has {scenario.road}")
    if run.env_kind == "safe":
        return SafeAgentDriver(run, scenario)
    if run.continuous:
        return ContinuousActionDriver(run)
    return MetaActionDriver(run, scenario)


def sb3_files(path: Optional[str]) -> tuple[Path, ...]:
    """The files the driver of ``sb3:PATH`` reads, a model and its run's config (:func:`mmpc.rl.runs.run_files`;
    :func:`mmpc.drivers.driver_files`); none where ``PATH`` names no run."""
    from mmpc.rl.runs import run_files

    try:
        return tuple(sorted(run_files(path))) if path else ()
    except FileNotFoundError:
        return ()


def rl_config_files(config: Optional[str]) -> tuple[Path, ...]:
    """The RL config file that ``safe-random:RL_CONFIG`` and ``safe-expert:RL_CONFIG`` read (a run's
    ``config.yaml``, a shipped name's or a path); none for the defaults or a name that is none of these."""
    from mmpc.config import read_config_yaml
    from mmpc.rl.config import RLConfig
    from mmpc.rl.runs import recorded_config

    if not config:
        return ()
    path = Path(config)
    if recorded_config(path) is not None:
        return (path / "config.yaml" if path.is_dir() else path,)
    try:
        return (read_config_yaml(RLConfig, config)[0],)
    except (FileNotFoundError, ValueError):
        return ()


make_sb3_driver.files = sb3_files
make_random_safe_driver.files = rl_config_files
make_expert_safe_driver.files = rl_config_files
