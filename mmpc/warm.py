"""Warm starts from one control step to the next, per environment, for every receding-horizon
user of the MPC (the MPC driver, the safety layer's decision solves, the mode proposer's driver,
DAgger's ranking labeller).

Consecutive problems of an environment differ by one control step: its last solve's final
iterates, moved one step on (:meth:`mmpc.BatchOptimizer.shifted`), start the next solve near the
answer, which then runs only the last :attr:`mmpc.MPCConfig.warm_iterations` iterations of the
schedule. An environment solves cold instead

- at its first solve, when it was not in the last solve (it joined the batch, or skipped a solve),
  and after :meth:`WarmStarts.forget` (a new episode),
- when it solves a goal its last solve did not (a solver of a subset of the goal set names the
  goals by their slots in the whole set),
- at the solve after one that found no feasible goal (its plan was a fallback),
- at the solve after a warm one that kept fewer than :attr:`mmpc.MPCConfig.warm_keep_share` of
  its last cold solve's feasible goals (a warm chain's feasible set only shrinks),
- every :attr:`mmpc.MPCConfig.warm_cold_every`-th solve since its last cold one (warm chains
  drift to costlier plans),

and a problem whose warm solve finds no feasible goal is solved again cold by the optimizer.
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import torch

from mmpc.mpc import MPC, Scored
from mmpc.problem import ProblemBatch
from mmpc.result import SolveResult, WarmStart


class WarmRound(NamedTuple):
    """What :meth:`WarmStarts.start` hands a solve of E environments and takes back in :meth:`WarmStarts.keep`.

    Fields:
        warm: the iterates to start from, (E, G, ...), NaN in the rows that solve cold; ``None``
            where every row solves cold.
        steps: (E,) long, each row's warm solves since its last cold one, this one included (0: cold).
        cold_feasible_goals: (E,) long, the feasible goals of each row's last cold solve (0 where cold).
    """

    warm: Optional[WarmStart]
    steps: torch.Tensor
    cold_feasible_goals: torch.Tensor


class _Kept(NamedTuple):
    """The last solve of each environment it served (rows E')."""

    ids: torch.Tensor  # (E',) environment ids
    slots: Optional[torch.Tensor]  # (E', G) long, the goal set's slots solved; None: the whole set in order
    starts: torch.Tensor  # (E', 2) ego positions the iterates are relative to [m]
    warm: WarmStart  # the final iterates, (E', G, ...)
    steps: torch.Tensor  # (E',) long, warm solves since the environment's last cold one
    fell_back: torch.Tensor  # (E',) bool, the solve found no feasible goal
    feasible_goals: torch.Tensor  # (E',) long
    cold_feasible_goals: torch.Tensor  # (E',) long, of the environment's last cold solve


class WarmStarts:
    """Each environment's last solve, kept to warm-start its next one (the module's rules).

    Args:
        mpc: the MPC whose optimizer solves (its :attr:`mmpc.MPCConfig` warm settings apply).
        period: time between two solves of an environment [s] (a driver's control period, the
            safety layer's decision period); default: the MPC's :attr:`mmpc.MPC.control_period`.
            Needed (> 0) when ``mpc.config.warm_iterations`` > 0.

    Use per solve: :meth:`score` (start, the MPC's score, keep), or by hand
    ``round = warm_starts.start(ids, ego)``, solve with ``warm=round.warm``, then
    ``warm_starts.keep(ids, ego, result, round)``; a solver of some goals of a goal set passes
    their ``slots`` to both. With ``warm_iterations`` 0 :attr:`enabled` is False and
    :meth:`start` always answers cold.
    """

    def __init__(self, mpc: MPC, period: Optional[float] = None) -> None:
        period = mpc.control_period if period is None else period
        if mpc.config.warm_iterations and not (period is not None and period > 0):
            raise ValueError(f"warm starts (MPCConfig.warm_iterations={mpc.config.warm_iterations}) need the time "
                             f"between two solves, `period` > 0 s (or an MPC with a control_period, "
                             f"mmpc.scenario.build_mpc); got {period!r}")
        self.mpc = mpc
        self.period = period
        self._kept: Optional[_Kept] = None

    @property
    def enabled(self) -> bool:
        """Whether solves are warm-started at all (``MPCConfig.warm_iterations`` > 0)."""
        return self.mpc.config.warm_iterations > 0

    def reset(self) -> None:
        """Forget every environment (new episodes everywhere)."""
        self._kept = None

    def forget(self, ids: torch.Tensor) -> None:
        """Forget the environments ``ids`` (long, any device): their next solve is cold (e.g. a new episode)."""
        if self._kept is None:
            return
        gone = (self._kept.ids[:, None] == ids.to(self._kept.ids.device)[None, :]).any(dim=1)
        self._kept = self._kept._replace(fell_back=self._kept.fell_back | gone)

    def start(self, ids: torch.Tensor, ego: torch.Tensor, slots: Optional[torch.Tensor] = None) -> WarmRound:
        """The starts of a solve of E environments ``ids`` (E,) long at the ego states ``ego`` (E, 6),
        of the goals ``slots`` (E, K) long of a goal set (``None``: the whole set, in order)."""
        steps = torch.zeros(ids.shape[0], dtype=torch.long, device=ids.device)
        if not self.enabled or self._kept is None or (slots is None) != (self._kept.slots is None):
            return WarmRound(None, steps, steps)
        kept, config = self._kept, self.mpc.config
        match = ids[:, None] == kept.ids[None, :]  # (E, E')
        rows = match.int().argmax(dim=1)
        steps = kept.steps[rows] + 1
        decayed = kept.feasible_goals[rows] < config.warm_keep_share * kept.cold_feasible_goals[rows]
        cold = ~match.any(dim=1) | kept.fell_back[rows] | decayed | (steps >= config.warm_cold_every)
        warm = kept.warm.take(rows)
        if slots is not None:  # each goal's iterate from where the last solve had it; a goal it had not: cold
            same = slots[:, :, None] == kept.slots[rows][:, None, :]  # (E, K, K')
            cold = cold | ~same.any(dim=2).all(dim=1)
            where = same.int().argmax(dim=2)  # (E, K)
            warm = WarmStart(*(field.gather(1, where.view(*where.shape, *[1] * (field.dim() - 2)).expand(
                *where.shape, *field.shape[2:])) for field in warm))
        steps = torch.where(cold, 0, steps)
        cold_feasible_goals = torch.where(cold, 0, kept.cold_feasible_goals[rows])
        if not self.mpc.fixed_shapes and bool(cold.all()):  # a host read: skipped where a step must not
            return WarmRound(None, steps, cold_feasible_goals)
        warm = self.mpc.optimizer.shifted(warm, self.period, ego[:, :2] - kept.starts[rows])
        restart = torch.full((), float("nan"), dtype=warm.position.dtype, device=warm.position.device)
        warm = WarmStart(*(torch.where(cold.view(-1, *[1] * (field.dim() - 1)), restart, field) for field in warm))
        return WarmRound(warm, steps, cold_feasible_goals)

    def score(self, ids: torch.Tensor, ego: torch.Tensor, problem: ProblemBatch,
              slots: Optional[torch.Tensor] = None) -> Scored:
        """The MPC's :meth:`mmpc.MPC.score` of ``problem`` (the E environments ``ids`` at the ego
        states ``ego``, the goals ``slots`` of a goal set or ``None``, as for :meth:`start`), started
        from their last solves where the rules allow and kept for their next."""
        round = self.start(ids, ego, slots)
        scored = self.mpc.score(problem, round.warm)
        self.keep(ids, ego, scored.result, round, slots)
        return scored

    def keep(self, ids: torch.Tensor, ego: torch.Tensor, result: SolveResult, round: WarmRound,
             slots: Optional[torch.Tensor] = None) -> None:
        """Keep the solve of ``ids`` at ``ego`` (of the goals ``slots``, as given to :meth:`start`)
        that :meth:`start` began with ``round``: its final iterates and feasible goals. The
        environments not in ``ids`` are forgotten: one that skips a solve starts its next one cold."""
        if not self.enabled:
            return
        feasible_goals = result.feasible.sum(dim=1)
        solved_warm = round.steps > 0
        self._kept = _Kept(ids, slots, ego[:, :2], result.warm, round.steps, feasible_goals == 0, feasible_goals,
                           torch.where(solved_warm, round.cold_feasible_goals, feasible_goals))
