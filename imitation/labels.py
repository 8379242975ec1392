"""Ranking labels at scale: the expert's verdict on every goal of every visited state, with the
proposer in the loop (DAgger), streamed to disk and published as a Minari dataset per round.

:class:`RankingExpert` is the driver of a labelling round. At every step it solves the MPC's
full goal set for all environments (one optimizer call), keeps the verdict as the label (each
goal's meta cost and feasibility, and the goal the expert would drive), and then drives: the
expert's choice with probability ``beta`` per environment-step, else the choice of the
proposer's driver (:class:`mmpc.imitation.proposer_driver.ProposerDriver`: the best feasible
goal among the proposed ones, the expert's where none is). The goals are independent problems of
the batch, so picking among the proposed columns of the full solve is what the proposer's own
solve gives, and labelling a state the proposer visits costs one full solve, not two.

:func:`label_episodes` drives a round's seeds in lockstep groups on the scenario's world (the
batched simulator for labels at scale), stages every finished episode atomically (a
:class:`mmpc.imitation.dataset.DemonstrationsDir`: a re-run resumes after the last finished
group) and builds the round's Minari dataset. Per step, besides the demonstrations' infos, the
episodes carry :func:`ranking_fields`.
"""

from __future__ import annotations

import time
import zlib
from pathlib import Path
from typing import Callable, NamedTuple, Optional, Sequence

import numpy as np
import torch

from mmpc.config import to_dict
from mmpc.drivers import Candidates, Decision, Driver, Observation
from mmpc.evaluate.tasks import lockstep_groups
from mmpc.imitation.dataset import DemonstrationsError, Manifest, build_minari, built_seeds, load_episode, package_versions
from mmpc.imitation.demos import locked_directory, sigterm_as_interrupt
from mmpc.imitation.listwise import RankingLabels
from mmpc.imitation.proposer import ModeProposer
from mmpc.imitation.proposer_driver import DEFAULT_KEEP, ProposerDriver
from mmpc.imitation.rollout import Rollout, rollout_lockstep
from mmpc.mpc import MPC
from mmpc.problem import EGO_V
from mmpc.drivers.verified import guarded_command
from mmpc.ranking import Selection
from mmpc.scenario import ScenarioConfig, build_mpc
from mmpc.verify import Guard, Verifier
from mmpc.warm import WarmStarts


def ranking_fields(num_goals: int) -> dict[str, tuple[type, tuple[int, ...], float]]:
    """The per-step infos of a labelled episode (declared as :data:`mmpc.imitation.rollout.INFO_FIELDS`):
    ``goal_cost`` (G,) meta cost of every goal's plan, ``goal_feasible`` (G,), ``expert_goal`` the
    goal the expert drives, ``learner_drove`` whether the proposer's choice was executed."""
    return {
        "goal_cost": (np.float32, (num_goals,), np.nan),
        "goal_feasible": (np.bool_, (num_goals,), False),
        "expert_goal": (np.int64, (), -1),
        "learner_drove": (np.bool_, (), False),
    }


def goal_count(mpc: MPC) -> int:
    """G, the size of the MPC's goal set (goal sampler and stop goals): fixed per scenario."""
    device = mpc.optimizer.device
    ego = torch.tensor([[0.0, 0.0, 0.0, 10.0, 0.0, 0.0]], dtype=torch.float32, device=device)
    return mpc.build_problem(ego, torch.zeros(1, 0, 4, device=device)).num_goals


class RankingExpert(Driver):
    """The labelling driver (see the module docstring).

    Args:
        mpc: the scenario's MPC, the expert.
        proposer: the learner, or ``None`` (the expert drives every step).
        beta: probability that the expert drives an environment-step, in [0, 1].
        keep: goals the learner keeps per step besides the ego lane's stop goal.
        seed: seeds the draw of who drives.
        period: the control period [s] (default: the MPC's): the expert's solves are warm-started
            from each environment's last one (:class:`mmpc.warm.WarmStarts`) when the MPC's config
            says so (:attr:`mmpc.MPCConfig.warm_iterations`); its episodes are labelled in order.
        verifier: the check behind which it labels and drives (module docstring); ``None``: the MPC alone.

    It computes on its MPC's device (:attr:`device`); its labels come to the host once per step.
    """

    def __init__(self, mpc: MPC, proposer: Optional[ModeProposer] = None, *, beta: float = 1.0, keep: int = DEFAULT_KEEP,
                 seed: int = 0, period: Optional[float] = None, verifier: Optional[Verifier] = None) -> None:
        if not 0.0 <= beta <= 1.0:
            raise ValueError(f"`beta` must be in [0, 1]; got {beta!r}")
        if proposer is None and beta < 1.0:
            raise ValueError(f"beta = {beta} lets a learner drive, but no proposer was given")
        self.mpc = mpc
        self.learner = None if proposer is None else ProposerDriver(mpc, proposer, keep=keep, period=period)
        self.warm_starts = WarmStarts(mpc, period)
        self.guard = None if verifier is None else Guard(verifier)
        self.beta = beta
        self.rng = np.random.default_rng(seed)
        self.name = "ranking-expert"
        self._labels: dict[str, np.ndarray] = {}

    @property
    def device(self) -> torch.device:
        """Where the expert (and the learner) compute: the MPC's device."""
        return self.mpc.optimizer.device

    def reset(self, num_envs: int) -> None:
        self.warm_starts.reset()
        if self.guard is not None:
            self.guard.reset()
        if self.learner is not None:
            self.learner.reset(num_envs)

    def labels(self) -> dict[str, np.ndarray]:
        """The :func:`ranking_fields` of the last decision, (E, ...) arrays."""
        return self._labels

    def decide(self, observation: Observation) -> Decision:
        start = time.perf_counter()
        count, device = observation.num_envs, self.device
        observation = observation.to(device)
        problem = self.mpc.build_problem(observation.ego, observation.vehicles, observation.vehicle_mask)
        scored = self.warm_starts.score(observation.ids(), observation.ego, problem)
        if self.guard is not None:  # a goal is usable only where its first command keeps a verified way out
            scored = scored._replace(result=scored.result._replace(feasible=self._usable(observation, problem, scored)))
        expert = self.mpc.select(problem, scored)
        draws = self.rng.random(count) >= self.beta
        learner_rows = torch.as_tensor(draws, device=device)
        selection, learner = expert, torch.zeros(count, dtype=torch.bool, device=device)
        if self.learner is not None and bool(draws.any()):
            slots = self.learner.propose(observation, problem)
            proposed = torch.zeros_like(scored.result.feasible).scatter(1, slots, True)
            narrowed = scored._replace(result=scored.result._replace(feasible=scored.result.feasible & proposed))
            restricted = self.mpc.select(problem, narrowed)
            learner = learner_rows & restricted.feasible  # where none is feasible, the learner's driver escalates
            selection = Selection(torch.where(learner, restricted.index, expert.index),
                                  torch.where(learner, restricted.cost, expert.cost), expert.feasible | learner)
        if self.learner is not None:
            self.learner.remember(observation, problem, selection.index)
        plan = self.mpc.choose(problem, scored, lambda result, cost, violation: selection)
        self._labels = {  # one copy of each to the host
            "goal_cost": scored.cost.float().cpu().numpy(),
            "goal_feasible": scored.result.feasible.cpu().numpy(),
            "expert_goal": expert.index.cpu().numpy(),
            "learner_drove": learner.cpu().numpy(),
        }
        trajectories = plan.result.trajectories
        candidates = Candidates(torch.stack([trajectories.x, trajectories.y], dim=-1), plan.result.feasible,
                                selection.index, problem.goals)
        decision = Decision(plan.acceleration, plan.steering, 0.0, selection.index, plan.result.feasible.sum(dim=1),
                            ~selection.feasible, selection.cost, candidates, plan)
        if self.guard is not None:  # no usable goal: braking, the other candidates, a fail-safe
            guarded = guarded_command(self.guard, observation, plan.acceleration, plan.steering, plan, self.mpc)
            decision = decision._replace(acceleration=guarded.acceleration, steering=guarded.steering,
                                         verified=guarded.verified, failsafe=guarded.failsafe,
                                         goal_index=torch.where(guarded.changed, -1, selection.index))
        return decision._replace(solve_ms=(time.perf_counter() - start) * 1e3 - plan.compile_ms)

    def _usable(self, observation: Observation, problem, scored) -> torch.Tensor:
        """(E, G) bool: the feasible goals whose first command verifies from the observed states."""
        acceleration, steering = self.mpc.candidate_commands(problem.ego, scored.result.trajectories)
        host = observation.to("cpu")
        verdict = self.guard.verifier.check(host.ego, host.vehicles, host.vehicle_mask, acceleration.cpu().to(host.ego.dtype),
                                            steering.cpu().to(host.ego.dtype))
        return scored.result.feasible & verdict.verified.to(scored.result.feasible.device)


class LabelReport(NamedTuple):
    """What :func:`label_episodes` did: the round's seeds, those driven now, the labelled
    states of the episodes driven now and the seconds it took, and the Minari dataset's id."""

    seeds: list[int]
    generated: list[int]
    states: int
    seconds: float
    dataset_id: str


def label_episodes(
    scenario: ScenarioConfig,
    seeds: Sequence[int],
    out: Path,
    *,
    proposer: Optional[ModeProposer] = None,
    beta: float = 1.0,
    keep: int = DEFAULT_KEEP,
    lockstep: int = 64,
    seed: int = 0,
    dataset_id: str,
    verify: bool = True,
    on_progress: Optional[Callable[[int, int], None]] = None,
) -> LabelReport:
    """Drive and label ``seeds`` (see the module docstring); re-run after an interruption to resume.

    Args:
        scenario: the scenario (``scenario.sim`` picks the world).
        seeds: the episodes' seeds (distinct, >= 0).
        out: the round's staging directory (refused if it holds another configuration's episodes).
        proposer, beta, keep: who drives (:class:`RankingExpert`).
        lockstep: episodes driven together (one optimizer call per step for all).
        seed: seeds the draw of who drives (each group's stream from it and its first seed, so a
            resumed group draws as it would have).
        dataset_id: the Minari id of the round's dataset.
        verify: label and drive behind the scenario's check (:class:`RankingExpert`; part of the
            directory's identity: its manifest's ``expert`` is ``verified:mpc``).
        on_progress: called as ``on_progress(finished, total)`` as episodes get staged.

    Raises:
        mmpc.imitation.dataset.DemonstrationsError: ``out`` is foreign, corrupt or locked.
        KeyboardInterrupt: interrupted (SIGINT or SIGTERM); finished episodes stay staged.
    """
    seeds = [int(s) for s in seeds]
    if not seeds or len(set(seeds)) != len(seeds) or min(seeds) < 0:
        raise ValueError(f"`seeds` must be distinct non-negative ints, at least one; got {seeds[:10]}")
    mpc = build_mpc(scenario)
    verifier = Verifier.for_scenario(scenario) if verify else None
    fields = ranking_fields(goal_count(mpc))
    manifest = Manifest(to_dict(scenario), lockstep, package_versions(), "verified:mpc" if verify else "mpc")
    with locked_directory(Path(out), manifest,
                          "another `mmpc imitate proposer` labelling run") as directory, \
            sigterm_as_interrupt():
        staged = directory.finished_seeds()
        generated: list[int] = []
        states = 0
        start = time.perf_counter()

        def stage(rollout: Rollout) -> None:
            nonlocal states
            directory.write(rollout.episode)
            generated.append(rollout.episode.seed)
            states += rollout.episode.steps
            if on_progress is not None:
                on_progress(len(staged) + len(generated), len(seeds))

        for group in lockstep_groups(seeds, lockstep).values():
            if all(s in staged for s in group):
                continue
            stream = zlib.crc32(f"{seed}:{group[0]}".encode())
            driver = RankingExpert(mpc, proposer, beta=beta, keep=keep, seed=stream, verifier=verifier)
            with torch.inference_mode():
                rollout_lockstep(scenario, group, driver, on_finished=stage, extra_fields=fields, extra_infos=driver.labels)
        seconds = time.perf_counter() - start
        if built_seeds(directory.root, dataset_id) != seeds:
            build_minari(directory, scenario, seeds, identifier=dataset_id, driver="mmpc MPC expert with a mode proposer",
                         description=(f"Ranking labels of highway-env scenario '{scenario.name}': the multi-modal MPC "
                                      f"(mmpc) drove with probability {beta:g} per step, its mode proposer otherwise"
                                      f"{', behind the check (a goal is feasible only where its first command verifies)' if verify else ''}; "
                                      "infos also hold the expert's verdict on every goal of its goal set (goal_cost, "
                                      "goal_feasible), its choice (expert_goal) and whether the proposer's choice was executed (learner_drove)."))
    return LabelReport(seeds, generated, states, seconds, dataset_id)


def read_labels(directories: Sequence[Path], *, first_episode: int = 0) -> RankingLabels:
    """The labelled states of every staged episode in ``directories`` (their ``episodes/``
    folders), episode ids from ``first_episode``. States with the ego reversing (outside the
    MPC's domain) are left out."""
    parts = []
    episode = first_episode
    for directory in directories:
        for path in sorted((Path(directory) / "episodes").glob("seed_*.npz")):
            data = load_episode(path)
            infos = data.infos
            if "goal_cost" not in infos:
                raise DemonstrationsError(f"{path} holds no ranking labels (an `mmpc imitate demos` episode?)")
            rows = slice(0, data.steps)
            keep = infos["ego"][rows, EGO_V] >= 0
            parts.append(RankingLabels(
                infos["ego"][rows][keep], infos["neighbours"][rows][keep], infos["goal_cost"][rows][keep],
                infos["goal_feasible"][rows][keep], infos["expert_goal"][rows][keep],
                np.full(int(keep.sum()), episode, dtype=np.int64),
            ))
            episode += 1
    return RankingLabels.concatenate(parts)
