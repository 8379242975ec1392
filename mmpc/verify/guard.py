"""The guard: per environment, the first command of a list that keeps a verified way out.

Each step, per environment, the first command of this list that verifies is driven:

1. the command asked for;
2. its steering with braking of :data:`BRAKING` [m/s^2], mildest first (brake no more than
   needed, keep the line: switching goals step by step zigzags);
3. the caller's alternatives, in its order (a planner's other feasible candidates);
4. the fail-safes' first commands from the present state (continuing one is a fail-safe from
   its end, so it verifies wherever the fail-safe stored last step still does).

Where none verifies, the fail-safe verified at the last step (from the state the ego is now in)
drives on; at an episode's first step without one, the strongest braking in the nearest lane.
By induction the ego never collides while every car keeps :class:`mmpc.verify.TrafficAssumptions`.
"""

from __future__ import annotations

from typing import Callable, Iterable, NamedTuple, Optional

import torch

from mmpc.verify.verifier import Verifier

#: Decelerations tried with the asked steering where the asked command does not verify [m/s^2].
BRAKING = (1.0, 2.0, 3.0, 4.0)

#: The caller's alternatives for the rows (R,) whose command did not verify: (R, K) accelerations
#: and steerings on the CPU, NaN where a row has fewer than K.
Alternatives = Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]


class Guarded(NamedTuple):
    """The commands driven in E environments.

    Fields:
        acceleration, steering: (E,) the commands [m/s^2], [rad] (CPU).
        verified: (E,) bool, the command driven verified.
        failsafe: (E,) bool, nothing verified and the stored fail-safe drove.
    """

    acceleration: torch.Tensor
    steering: torch.Tensor
    verified: torch.Tensor
    failsafe: torch.Tensor


class Guard:
    """Commands taken only where they keep a verified way out; the fail-safe verified last, per
    environment id, where none does.

    Args:
        verifier: the check.
    """

    def __init__(self, verifier: Verifier) -> None:
        self.verifier = verifier
        self._stored: dict[int, tuple[int, float]] = {}  # environment id -> (lane, deceleration) verified last step

    def reset(self) -> None:
        """Forget every environment's stored fail-safe (new episodes everywhere)."""
        self._stored = {}

    def forget(self, ids: Iterable[int]) -> None:
        """Forget the stored fail-safes of environments ``ids`` (they start new episodes)."""
        for env in ids:
            self._stored.pop(int(env), None)

    def choose(self, ego: torch.Tensor, vehicles: torch.Tensor, mask: Optional[torch.Tensor], ids: list[int],
               acceleration: torch.Tensor, steering: torch.Tensor, alternatives: Optional[Alternatives] = None) -> Guarded:
        """The commands to drive (module docstring).

        Args:
            ego: (E, 6) ego states; vehicles: (E, M, 4) other cars' x, y, vx, vy; mask: (E, M) bool,
                the present cars (``None``: all) (CPU).
            ids: E environment ids, stable over an episode (they key the stored fail-safes).
            acceleration, steering: (E,) the commands asked for [m/s^2], [rad].
            alternatives: the caller's other commands for the rows whose own does not verify.
        """
        verifier = self.verifier
        dtype = ego.dtype
        if mask is None:
            mask = torch.ones(vehicles.shape[:2], dtype=torch.bool)
        asked_acceleration, asked_steering = acceleration.to(dtype), steering.to(dtype)
        first = verifier.check(ego, vehicles, mask, asked_acceleration[:, None], asked_steering[:, None])
        acceleration, steering = asked_acceleration.clone(), asked_steering.clone()
        verified = first.verified[:, 0].clone()
        lane, deceleration = first.lane[:, 0].clone(), first.deceleration[:, 0].clone()
        rows = (~verified).nonzero().squeeze(1)
        if rows.numel():
            candidates = self._candidates(ego, asked_acceleration, asked_steering, rows, alternatives)
            verdict = verifier.check(ego[rows], vehicles[rows], mask[rows], *candidates)
            found = verdict.verified.any(dim=1)
            pick = verdict.verified.int().argmax(dim=1, keepdim=True)
            chosen = rows[found]
            acceleration[chosen] = candidates[0].gather(1, pick)[found, 0]
            steering[chosen] = candidates[1].gather(1, pick)[found, 0]
            lane[chosen] = verdict.lane.gather(1, pick)[found, 0]
            deceleration[chosen] = verdict.deceleration.gather(1, pick)[found, 0]
            verified[chosen] = True
        failsafe = ~verified
        if bool(failsafe.any()):
            stuck = failsafe.nonzero().squeeze(1)
            kept = [self._stored.get(ids[row]) for row in stuck.tolist()]
            nearest = verifier.road.lane_index(ego[stuck, 1])
            strongest = max(verifier.failsafes.decelerations)
            lane[stuck] = torch.tensor([held[0] if held else int(near) for held, near in zip(kept, nearest)])
            deceleration[stuck] = torch.tensor([held[1] if held else strongest for held in kept], dtype=deceleration.dtype)
            command = verifier.failsafe_command(ego[stuck], lane[stuck], deceleration[stuck])
            acceleration[stuck], steering[stuck] = command[0].to(dtype), command[1].to(dtype)
        for env, kept_lane, kept_deceleration in zip(ids, lane.tolist(), deceleration.tolist()):
            self._stored[env] = (kept_lane, kept_deceleration)
        return Guarded(acceleration, steering, verified, failsafe)

    def _candidates(self, ego: torch.Tensor, acceleration: torch.Tensor, steering: torch.Tensor, rows: torch.Tensor,
                    alternatives: Optional[Alternatives]) -> tuple[torch.Tensor, torch.Tensor]:
        """(R, K) accelerations and steerings to try in the ``rows`` whose command did not verify:
        its steering with each of :data:`BRAKING`, the caller's alternatives, then the fail-safes'
        first commands."""
        own_acceleration, own_steering = acceleration[rows, None], steering[rows, None]
        braking = torch.tensor(BRAKING, dtype=ego.dtype)
        failsafe_acceleration, failsafe_steering = self.verifier.failsafe_candidates(ego[rows])
        accelerations = [torch.minimum(own_acceleration, -braking), failsafe_acceleration]
        steerings = [own_steering.expand(-1, braking.numel()), failsafe_steering]
        if alternatives is not None:
            other_acceleration, other_steering = alternatives(rows)
            usable = other_acceleration.isfinite()  # a missing one repeats the asked command, which did not verify
            accelerations.insert(1, torch.where(usable, other_acceleration.to(ego.dtype), own_acceleration))
            steerings.insert(1, torch.where(usable, other_steering.to(ego.dtype), own_steering))
        return torch.cat(accelerations, dim=1), torch.cat(steerings, dim=1)
