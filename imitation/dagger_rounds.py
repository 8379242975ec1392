"""The skeleton both of mmpc's DAgger loops fill in (Ross et al., 2011): behaviour cloning's
(:mod:`mmpc.imitation.dagger`) and the mode proposer's (:mod:`mmpc.imitation.proposer_dagger`).

A run is rounds 0 ... K. Round 0 is the expert's alone; in round i >= 1 the expert drives with
probability :func:`beta_of` and the policy of round i - 1 otherwise. Each round drives, labels and
trains (the loop's own steps, one ``play`` call), is appended to the rounds of the run and
written out (the loop's ``record``); a resumed run starts after its last written round, and the
policy a run returns is its :func:`best_of` round.
"""

from __future__ import annotations

from typing import Callable, Optional, Sequence


def beta_of(beta: float, beta_decay: float, round_index: int) -> float:
    """The expert's share of the driving in round ``round_index``: 1 in round 0, then
    ``beta * beta_decay^(round_index - 1)``."""
    return 1.0 if round_index == 0 else beta * beta_decay ** (round_index - 1)


def best_of(rounds: Sequence[dict], score: Callable[[dict], Optional[tuple]]) -> int:
    """The ``round`` of the entry with the lowest ``score`` (the first of equal scores); the last
    round when no entry has one (``score`` is ``None`` for entries without a check)."""
    scored = [(score(entry), entry) for entry in rounds]
    checked = [(key, entry) for key, entry in scored if key is not None]
    if not checked:
        return rounds[-1]["round"]
    return min(checked, key=lambda pair: pair[0])[1]["round"]


def run_rounds(rounds: list[dict], last_round: int, play: Callable[[int], dict], record: Callable[[list[dict]], None],
               on_round: Optional[Callable[[dict], None]] = None) -> list[dict]:
    """Play the rounds after those in ``rounds`` (a resumed run's, or none) up to ``last_round``:
    each ``play(index)`` returns the round's entry, which joins ``rounds`` before ``record(rounds)``
    writes the run out and ``on_round(entry)`` is told. Returns ``rounds``."""
    for index in range(len(rounds), last_round + 1):
        entry = play(index)
        rounds.append(entry)
        record(rounds)
        if on_round is not None:
            on_round(entry)
    return rounds
