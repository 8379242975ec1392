"""The proposer drives, the optimizer guarantees (spec ``proposer:RUN/proposer.pt``).

Per step and environment: the MPC builds its full goal set (cheap: the goal sampler and the stop
goals), the :class:`mmpc.imitation.proposer.ModeProposer` keeps the ``keep`` goals it scores
highest, plus two goals no proposal can leave out: the stop goal on the ego's lane (a certified way
to slow down) and the goal driven at the previous step (the expert keeps its goal from one step to
the next in 83 % of the high-speed states), and the optimizer solves only those. The MPC ranks and certifies them exactly as it
ranks its own set (feasibility, meta cost, tie-break, the same fallback), so a bad proposal costs
meta cost, never safety checks. Where none of the proposed goals is feasible the step escalates:
the full goal set is solved for those environments (``escalate``), so the proposer never leaves
the ego on the fallback while the expert would have had a feasible plan. With the scenario's warm
starts (:attr:`mmpc.MPCConfig.warm_iterations`), an environment whose proposed goals were all solved
at its last step starts from those iterates (:class:`mmpc.warm.WarmStarts`, goals named by slot).

The driver computes on its MPC's device (the run's, :func:`mmpc.device.run_device`), the
proposer network included; the road features are computed on the host from one copy of the
observation per step.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Optional

import torch

from mmpc.drivers import Candidates, Decision, Driver, Observation
from mmpc.imitation.features import nearest_neighbours
from mmpc.imitation.proposer import ModeProposer, load_proposer_checkpoint, proposer_from_checkpoint
from mmpc.mpc import MPC
from mmpc.problem import EGO_X, EGO_Y, ProblemBatch
from mmpc.scenario import ScenarioConfig, build_mpc
from mmpc.warm import WarmStarts

logger = logging.getLogger(__name__)

#: Goals kept per step besides the stop goal, unless the checkpoint or the spec says otherwise.
DEFAULT_KEEP = 4

#: Proposers shipped with mmpc: ``models/<name>.pt`` beside this module (``proposer:NAME`` drives one).
SHIPPED_PROPOSERS = Path(__file__).resolve().parent / "models"


def shipped_proposers() -> list[str]:
    """Names of the shipped proposers."""
    return sorted(p.stem for p in SHIPPED_PROPOSERS.glob("*.pt"))


def ego_lane_stop_goal(mpc: MPC, ego: torch.Tensor, num_goals: int) -> Optional[torch.Tensor]:
    """(E,) slot of the stop goal on the ego's lane in the MPC's goal set (the stop goals come
    last, one per lane of :meth:`mmpc.Road.lanes_around`); ``None`` when the MPC has no stop goals."""
    lanes_either_side = mpc.config.stop_lanes
    if lanes_either_side is None:
        return None
    lanes = mpc.road.lanes_around(ego[:, EGO_Y], lanes_either_side)  # (E, S)
    own = (lanes == mpc.road.lane_index(ego[:, EGO_Y])[:, None]).long().argmax(dim=1)
    return num_goals - lanes.shape[1] + own


def subset_problem(problem: ProblemBatch, slots: torch.Tensor) -> ProblemBatch:
    """The problems with only the goals of ``slots`` (E, K) kept."""
    goals = torch.gather(problem.goals, 1, slots[..., None].expand(-1, -1, 2))
    return problem._replace(goals=goals)


def problem_rows(problem: ProblemBatch, rows: torch.Tensor) -> ProblemBatch:
    """The problems of ``rows`` (long indices)."""
    mask = None if problem.obstacle_mask is None else problem.obstacle_mask[rows]
    axes = None if problem.obstacle_axes is None else problem.obstacle_axes[rows]
    return problem._replace(ego=problem.ego[rows], goals=problem.goals[rows], obstacles=problem.obstacles[rows],
                            obstacle_mask=mask, obstacle_axes=axes)


class ProposerDriver(Driver):
    """The MPC restricted to the proposer's goals (see the module docstring).

    Args:
        mpc: the scenario's MPC (goal set, optimizer, ranking, fallback).
        proposer: a proposer trained on this MPC's goal set.
        keep: goals kept per step besides the ego lane's stop goal and the last step's goal, 1 <= keep <= G.
        escalate: solve the full goal set where no proposed goal is feasible.
        name: the driver's name in tables.
        period: the control period [s] for warm starts; default: the MPC's (:attr:`mmpc.MPC.control_period`).

    Attributes:
        decided_rows, escalated_rows: environment-steps decided, and those that escalated.

    The proposer is moved to the MPC's device (in place, as it is put in eval mode).
    """

    def __init__(self, mpc: MPC, proposer: ModeProposer, *, keep: int = DEFAULT_KEEP, escalate: bool = True,
                 name: str = "proposer", period: Optional[float] = None) -> None:
        if proposer.road != mpc.road:
            raise ValueError(f"the proposer was trained on {proposer.road}; the MPC drives {mpc.road}")
        if not isinstance(keep, int) or isinstance(keep, bool) or not 1 <= keep <= proposer.num_goals:
            raise ValueError(f"`keep` must be an int in [1, {proposer.num_goals}] (the goal set); got {keep!r}")
        self.mpc = mpc
        self.proposer = proposer.to(mpc.optimizer.device).eval()
        self.keep = keep
        self.escalate = escalate
        self.name = name
        self.decided_rows = 0
        self.escalated_rows = 0
        self.warm_starts = WarmStarts(mpc, period)
        # environment id -> the goal driven at its last step, (x ahead of the ego [m], y [m])
        self._previous: dict[int, tuple[float, float]] = {}

    @property
    def device(self) -> torch.device:
        """Where the driver computes: its MPC's device."""
        return self.mpc.optimizer.device

    def reset(self, num_envs: int) -> None:
        self._previous = {}
        self.warm_starts.reset()

    def remember(self, observation: Observation, problem: ProblemBatch, slots: torch.Tensor) -> None:
        """Note the goals of ``slots`` (E,) driven in the environments of ``observation``, whose
        goal set is ``problem``'s, for their next step."""
        goals = problem.goals[torch.arange(problem.num_problems, device=slots.device), slots]
        ahead = goals[:, 0] - problem.ego[:, EGO_X]
        driven = torch.stack([ahead, goals[:, 1]], dim=1).tolist()  # one copy to the host
        self._previous.update(zip(observation.ids().tolist(), map(tuple, driven)))

    def previous_goal(self, observation: Observation, problem: ProblemBatch) -> Optional[torch.Tensor]:
        """(E,) slot of the goal nearest the one each environment drove at its last step (the same
        lane first, then the same distance ahead; -1 where it has not driven yet): a goal slot of the
        ego's neighbour lanes names another lane once the ego has changed lanes, so the goal is
        found again by place, not by slot. ``None`` when no environment has driven yet."""
        previous = [self._previous.get(i) for i in observation.ids().tolist()]
        if all(p is None for p in previous):
            return None
        known = torch.tensor([p is not None for p in previous], dtype=torch.bool, device=problem.goals.device)
        target = problem.goals.new_tensor([p if p is not None else (0.0, 0.0) for p in previous])  # (E, 2)
        ahead = problem.goals[..., 0] - problem.ego[:, EGO_X, None]
        lane_width = self.mpc.road.lane_width
        distance = ((problem.goals[..., 1] - target[:, 1:]).abs() / lane_width).round() * 1e3 \
            + (ahead - target[:, :1]).abs()
        return torch.where(known, distance.argmin(dim=1), -1)

    def propose(self, observation: Observation, problem: ProblemBatch) -> torch.Tensor:
        """(E, K) goal slots to solve: the ego lane's stop goal, the goal driven at the previous
        step and the best ``keep``, in the goal set's order (so that ties between equal candidates
        break as the expert breaks them)."""
        if problem.num_goals != self.proposer.num_goals:
            raise ValueError(f"the proposer scores {self.proposer.num_goals} goals; this MPC's goal set has "
                             f"{problem.num_goals} (was it trained on another scenario?)")
        host = observation.to("cpu")  # the road features are numpy: one copy of the state per step
        mask = None if host.vehicle_mask is None else host.vehicle_mask.numpy()
        ego = host.ego.numpy()
        neighbours = nearest_neighbours(ego, host.vehicles.numpy(), mask, ellipse=self.proposer.scene.ellipse)
        forced = [slot for slot in (ego_lane_stop_goal(self.mpc, problem.ego, problem.num_goals),) if slot is not None]
        previous = self.previous_goal(observation, problem)
        if previous is not None:
            forced.append(previous)
        count = min(self.keep + len(forced), problem.num_goals)
        stacked = torch.stack(forced, dim=1) if forced else None
        features = torch.as_tensor(self.proposer.features(ego, neighbours), dtype=torch.float32, device=self.device)
        return self.proposer.top_goals(features, count, forced=stacked).sort(dim=1).values

    def decide(self, observation: Observation) -> Decision:
        start = time.perf_counter()
        observation = observation.to(self.device)
        problem = self.mpc.build_problem(observation.ego, observation.vehicles, observation.vehicle_mask)
        slots = self.propose(observation, problem)
        subset = subset_problem(problem, slots)
        plan = self.mpc.choose(subset, self.warm_starts.score(observation.ids(), observation.ego, subset, slots))
        compile_ms = plan.compile_ms
        selection = plan.selection
        acceleration, steering = plan.acceleration.clone(), plan.steering.clone()
        goal_index = slots.gather(1, selection.index[:, None]).squeeze(1)
        feasible_goals = plan.result.feasible.sum(dim=1)
        iterations = plan.result.problem_iterations()
        fallback = ~selection.feasible
        plan_cost = selection.cost.clone()
        # what was considered, laid out over the full goal set (unsolved goals: NaN paths, infeasible)
        solved = torch.stack([plan.result.trajectories.x, plan.result.trajectories.y], dim=-1)  # (E, K, N, 2)
        paths = solved.new_full((problem.num_problems, problem.num_goals, *solved.shape[2:]), float("nan"))
        paths.scatter_(1, slots[:, :, None, None].expand_as(solved), solved)
        feasible = torch.zeros(problem.num_problems, problem.num_goals, dtype=torch.bool,
                               device=slots.device).scatter(1, slots, plan.result.feasible)
        escalated = fallback & self.escalate
        escalated_count = int(escalated.sum())
        if escalated_count:
            rows = escalated.nonzero().flatten()
            full = self.mpc.plan_problem(problem_rows(problem, rows))
            compile_ms += full.compile_ms
            acceleration[rows], steering[rows] = full.acceleration, full.steering
            goal_index[rows] = full.selection.index
            feasible_goals[rows] = full.result.feasible.sum(dim=1)
            iterations[rows] += full.result.problem_iterations()
            fallback[rows] = ~full.selection.feasible
            plan_cost[rows] = full.selection.cost
            paths[rows] = torch.stack([full.result.trajectories.x, full.result.trajectories.y], dim=-1).to(paths.dtype)
            feasible[rows] = full.result.feasible
        self.remember(observation, problem, goal_index)
        self.decided_rows += observation.num_envs
        self.escalated_rows += escalated_count
        candidates = Candidates(paths, feasible, goal_index, problem.goals)
        elapsed_ms = (time.perf_counter() - start) * 1e3 - compile_ms
        return Decision(acceleration, steering, elapsed_ms, goal_index, feasible_goals, fallback, plan_cost, candidates,
                        iterations=iterations)


def proposer_checkpoint(argument: str) -> Path:
    """The checkpoint a ``proposer:`` argument names: the file, else the shipped proposer of that name."""
    path = Path(argument)
    return SHIPPED_PROPOSERS / f"{argument}.pt" if not path.is_file() and argument in shipped_proposers() else path


def make_proposer_driver(scenario: ScenarioConfig, argument: Optional[str]) -> Driver:
    """Driver factory of the spec ``proposer:PATH`` (a checkpoint of
    :func:`mmpc.imitation.proposer.save_proposer`; it keeps the goal count it was trained with) or
    ``proposer:NAME`` (a shipped proposer, :func:`shipped_proposers`)."""
    if not argument:
        raise ValueError("driver 'proposer' needs a checkpoint path or a shipped name: 'proposer:RUN/proposer.pt' "
                         f"(shipped: {', '.join(shipped_proposers()) or 'none'})")
    path = proposer_checkpoint(argument)
    if not path.is_file():
        raise FileNotFoundError(f"no proposer checkpoint {argument} (shipped proposers: "
                                f"{', '.join(shipped_proposers()) or 'none'}; train one with `mmpc imitate proposer`)")
    checkpoint = load_proposer_checkpoint(path)
    if checkpoint.get("scenario") not in (None, scenario.name):
        logger.warning("proposer %s was trained on scenario %r; driving %r", argument, checkpoint["scenario"], scenario.name)
    keep = int(checkpoint.get("info", {}).get("keep", DEFAULT_KEEP))
    return ProposerDriver(build_mpc(scenario), proposer_from_checkpoint(checkpoint), keep=keep, name=f"proposer:{argument}")


def proposer_files(argument: Optional[str]) -> tuple[Path, ...]:
    """The file the driver of ``proposer:ARGUMENT`` reads (:func:`mmpc.drivers.driver_files`); none where it names none."""
    path = proposer_checkpoint(argument) if argument else None
    return (path,) if path is not None and path.is_file() else ()


make_proposer_driver.files = proposer_files
