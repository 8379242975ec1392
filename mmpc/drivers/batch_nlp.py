"""Batch-NLP baseline: the same goal-directed problems as ours, one IPOPT solve per goal, solved
in parallel worker processes (the paper's multi-threaded ACADO baseline), ranked by the same meta
cost.

Each goal's problem is :class:`mmpc.drivers.nlp.TrajectoryNLP` in ``goal`` mode: smoothness
objective, end position = goal, end heading and rate 0, same kinematics, bounds and ellipses as
the batch optimizer. Every solve is cold-started (as the batch optimizer, and the authors'
ACADO baseline, are). The B goals are an evenly spaced subset of the scenario's goal sampler
(``indices = round(linspace(0, G - 1, B))``; all of them when B = G). The solutions are sampled
on the optimizer's instants, ranked by the scenario's meta cost among the feasible ones
(recomputed constraint check, not IPOPT's word), and the best becomes the command exactly as in
:class:`mmpc.MPC`; with none feasible the MPC's lane-keeping brake is executed.
"""

from __future__ import annotations

import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor
from typing import Optional, Sequence

import numpy as np
import torch

from mmpc.drivers.common import checked_ego, obstacles_for, ranked_decision
from mmpc.drivers.nlp import NLPConfig, TrajectoryNLP, resample
from mmpc.config import require_int
from mmpc.drivers.base import Decision, Driver, Observation
from mmpc.mpc import MPC
from mmpc.road import Road
from mmpc.solver.config import OptimizerConfig

#: The worker process's NLP (built once per process by :func:`_init_worker`).
_WORKER_NLP: Optional[TrajectoryNLP] = None


def _init_worker(optimizer: OptimizerConfig, road: Road, road_margin: float, num_obstacles: int, config: NLPConfig) -> None:
    global _WORKER_NLP
    torch.set_num_threads(1)
    _WORKER_NLP = TrajectoryNLP(optimizer, road, road_margin, num_obstacles, config)


def _solve_in_worker(task: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]) -> tuple[np.ndarray, bool, str, float]:
    """(ego, obstacles, mask, goal) -> (knot states, feasible, IPOPT status, solve ms)."""
    solution = _WORKER_NLP.solve(*task)
    return solution.states, solution.feasible, solution.status, solution.solve_ms


def goal_subset(num_goals: int, batch: int) -> torch.Tensor:
    """(batch,) indices spread evenly over ``num_goals`` goals (first and last included)."""
    if not isinstance(batch, int) or batch < 1 or batch > num_goals:
        raise ValueError(f"batch size must be an int in [1, {num_goals}] (the scenario's goals); got {batch!r}")
    if batch == 1:
        return torch.zeros(1, dtype=torch.long)
    return torch.linspace(0, num_goals - 1, batch, dtype=torch.float64).round().long()


class BatchNLPSolver:
    """B goal NLPs solved by a pool of worker processes (or in this process with ``workers=0``).

    Args:
        mpc: the scenario's MPC (bounds, ellipse, road, obstacle count).
        workers: worker processes; 0 solves in the calling process.
        config: transcription and IPOPT settings.
    """

    def __init__(self, mpc: MPC, workers: int, config: Optional[NLPConfig] = None) -> None:
        require_int("", low=0, workers=workers)
        self.config = config if config is not None else NLPConfig()
        arguments = (mpc.optimizer.config, mpc.road, mpc.config.road_margin, mpc.config.num_obstacles, self.config)
        self.workers = workers
        self.local = TrajectoryNLP(*arguments)
        self._pool: Optional[ProcessPoolExecutor] = None
        if workers > 0:
            self._pool = ProcessPoolExecutor(
                max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                initializer=_init_worker, initargs=arguments,
            )
            # Start every worker now (building its NLP) so that the first step is not timed with it.
            list(self._pool.map(_noop, range(workers)))

    @property
    def times(self) -> np.ndarray:
        return self.local.times

    def solve(self, tasks: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]) -> list[tuple[np.ndarray, bool, str, float]]:
        """Solve every (ego (6,), obstacles (M, K+1, 2), mask (M,), goal (2,)) task, in order."""
        if self._pool is None:
            results = []
            for task in tasks:
                solution = self.local.solve(*task)
                results.append((solution.states, solution.feasible, solution.status, solution.solve_ms))
            return results
        return list(self._pool.map(_solve_in_worker, tasks))

    def close(self) -> None:
        """Stop the worker processes."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


def _noop(_: int) -> None:
    return None


class BatchNLPDriver(Driver):
    """Goal-directed NLPs in parallel, ranked by the meta cost.

    Args:
        mpc: the scenario's MPC (goal sampler, meta cost, obstacle set, command extraction).
        batch: B goals per step (a subset of the sampler's, see :func:`goal_subset`).
        solver: the NLP pool.
        name: the driver's name in tables.
    """

    def __init__(self, mpc: MPC, batch: int, solver: BatchNLPSolver, name: Optional[str] = None) -> None:
        self.mpc = mpc
        self.batch = batch
        self.solver = solver
        self.name = name or f"batch-nlp:{batch}"

    def close(self) -> None:
        self.solver.close()

    @torch.no_grad()
    def decide(self, observation: Observation) -> Decision:
        start = time.perf_counter()
        mpc = self.mpc
        ego = checked_ego(observation, torch.float64)
        goals = mpc.goal_sampler(ego, mpc.road)
        goals = goals[:, goal_subset(goals.shape[1], self.batch)]  # (E, B, 2)
        knot_times = torch.as_tensor(self.solver.times, dtype=torch.float64)
        obstacles, mask = obstacles_for(mpc, ego, observation.vehicles.to(torch.float64), observation.vehicle_mask, knot_times)
        e, b = goals.shape[:2]
        tasks = [
            (ego[i].numpy(), obstacles[i].numpy(), mask[i].numpy(), goals[i, g].numpy())
            for i in range(e) for g in range(b)
        ]
        results = self.solver.solve(tasks)
        states = np.stack([r[0] for r in results]).reshape(e, b, *results[0][0].shape)
        feasible = torch.tensor([r[1] for r in results]).reshape(e, b)
        times = mpc.optimizer.times.to(torch.float64)
        trajectories = resample(states, self.solver.times, times)  # (E, B, N)
        at_samples = obstacles_for(mpc, ego, observation.vehicles.to(torch.float64), observation.vehicle_mask, times)
        return ranked_decision(mpc, ego, trajectories, feasible, start, goals, obstacles=at_samples)


def make_batch_nlp_driver(scenario, argument: Optional[str]) -> Driver:
    """Registry factory: ``batch-nlp`` (11 goals), ``batch-nlp:B`` or ``batch-nlp:B,W`` (B goals
    on W worker processes; default W = min(B, CPU count))."""
    from mmpc.scenario import build_mpc

    batch, workers = 11, None
    if argument is not None:
        parts = argument.split(",")
        try:
            if len(parts) > 2:
                raise ValueError
            batch = int(parts[0])
            workers = int(parts[1]) if len(parts) == 2 else None
        except ValueError:
            raise ValueError(f"driver 'batch-nlp' takes B or B,W (goals, worker processes), e.g. 'batch-nlp:11,2'; "
                             f"got 'batch-nlp:{argument}'") from None
    if batch < 1:
        raise ValueError(f"batch-nlp: the batch size must be >= 1; got {batch}")
    if workers is None:
        workers = min(batch, os.cpu_count() or 1)
    mpc = build_mpc(scenario, device="cpu")  # CasADi solves on the CPU
    probe = mpc.goal_sampler(torch.zeros(1, 6, dtype=torch.float64), mpc.road)
    goal_subset(probe.shape[1], batch)  # validates B against the scenario's goal count
    return BatchNLPDriver(mpc, batch, BatchNLPSolver(mpc, workers))
