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

from mmpc.compaction import capacity, compact, scatter
from mmpc.verify.verifier import Verifier

#: Decelerations tried with the asked steering where the asked command does not verify [m/s^2].
BRAKING = (1.0, 2.0, 3.0, 4.0)

#: With the verifier's ``fixed_shapes``: the share of environments whose command did not verify
#: that are tried again with alternatives in one step (the others drive their stored fail-safes).
RETRY_SHARE = 0.25

#: ... and at least this many (a small batch may have a bad step everywhere).
RETRY_FLOOR = 8

#: The caller's alternatives for the rows (R,) whose command did not verify: (R, K) accelerations
#: and steerings on the rows' device, NaN where a row has fewer than K.
Alternatives = Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]


class Guarded(NamedTuple):
    """The commands driven in E environments.

    Fields:
        acceleration, steering: (E,) the commands [m/s^2], [rad] (on the states' device).
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

    With the verifier's ``fixed_shapes`` a step reads nothing on the host: every environment's
    alternatives are built, at most :data:`RETRY_SHARE` of them checked (an environment past that
    drives its stored fail-safe: safe, as any), and the store holds the environments of the last
    step only (a fixed-shape batch decides the same environments every step).

    Args:
        verifier: the check.
    """

    def __init__(self, verifier: Verifier) -> None:
        self.verifier = verifier
        self._stored: Optional[_Stored] = None  # the fail-safes verified last, per environment id

    def reset(self) -> None:
        """Forget every environment's stored fail-safe (new episodes everywhere)."""
        self._stored = None

    def forget(self, ids: torch.Tensor | Iterable[int]) -> None:
        """Forget the stored fail-safes of environments ``ids`` (they start new episodes)."""
        if self._stored is not None:
            ids = torch.as_tensor(ids, dtype=torch.long).to(self._stored.ids.device)
            self._stored = self._stored.without(ids)

    def stored_ids(self) -> list[int]:
        """The environment ids with a stored fail-safe (a host read)."""
        return [] if self._stored is None else self._stored.ids[self._stored.known].tolist()

    def choose(self, ego: torch.Tensor, vehicles: torch.Tensor, mask: Optional[torch.Tensor], ids: torch.Tensor,
               acceleration: torch.Tensor, steering: torch.Tensor, alternatives: Optional[Alternatives] = None) -> Guarded:
        """The commands to drive (module docstring).

        Args:
            ego: (E, 6) ego states; vehicles: (E, M, 4) other cars' x, y, vx, vy; mask: (E, M) bool,
                the present cars (``None``: all), on one device (the CPU unless the verifier has fixed shapes).
            ids: (E,) long environment ids, stable over an episode (they key the stored fail-safes).
            acceleration, steering: (E,) the commands asked for [m/s^2], [rad].
            alternatives: the caller's other commands for the rows whose own does not verify.
        """
        verifier, fixed = self.verifier, self.verifier.fixed_shapes
        dtype, num_envs = ego.dtype, ego.shape[0]
        if mask is None:
            mask = torch.ones(vehicles.shape[:2], dtype=torch.bool, device=vehicles.device)
        asked_acceleration, asked_steering = acceleration.to(dtype), steering.to(dtype)
        first = verifier.check(ego, vehicles, mask, asked_acceleration[:, None], asked_steering[:, None])
        acceleration, steering, verified = asked_acceleration, asked_steering, first.verified[:, 0]
        lane, deceleration = first.lane[:, 0], first.deceleration[:, 0]
        retried = compact(~verified, capacity(fixed, num_envs, RETRY_SHARE, RETRY_FLOOR, num_envs) if num_envs else None,
                          fill=num_envs)
        rows = retried.index[0]  # (R,) the padding: one past the last row
        if rows.numel():  # with fixed shapes the buffer's size, known before the data
            read = rows.clamp_max(num_envs - 1)
            candidates = self._candidates(ego, asked_acceleration, asked_steering, read, alternatives)
            verdict = verifier.check(ego[read], vehicles[read], mask[read], *candidates)
            found = verdict.verified.any(dim=1) & retried.valid
            pick = verdict.verified.int().argmax(dim=1, keepdim=True)
            update = {"acceleration": candidates[0].gather(1, pick)[:, 0], "steering": candidates[1].gather(1, pick)[:, 0],
                      "lane": verdict.lane.gather(1, pick)[:, 0], "deceleration": verdict.deceleration.gather(1, pick)[:, 0]}
            now = {"acceleration": acceleration, "steering": steering, "lane": lane, "deceleration": deceleration}
            now = {name: scatter(value, 0, rows, torch.where(found, update[name], value[read])) for name, value in now.items()}
            acceleration, steering, lane, deceleration = now.values()
            verified = scatter(verified, 0, rows, verified[read] | found)
        failsafe = ~verified
        if fixed or bool(failsafe.any()):
            kept_lane, kept_deceleration, known = self._recall(ids.to(ego.device), num_envs)
            nearest = verifier.road.lane_index(ego[:, 1])
            strongest = max(verifier.failsafes.decelerations)
            lane = torch.where(failsafe, torch.where(known, kept_lane, nearest), lane)
            deceleration = torch.where(failsafe, torch.where(known, kept_deceleration.to(deceleration.dtype), strongest),
                                       deceleration)
            command = verifier.failsafe_command(ego, lane, deceleration)
            acceleration = torch.where(failsafe, command[0].to(dtype), acceleration)
            steering = torch.where(failsafe, command[1].to(dtype), steering)
        self._keep(_Stored(ids.to(ego.device), lane, deceleration, torch.ones_like(verified)))
        return Guarded(acceleration, steering, verified, failsafe)

    def _recall(self, ids: torch.Tensor, num_envs: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The stored fail-safes of ``ids`` (E,): (E,) lanes, decelerations and whether one is stored."""
        if self._stored is None:
            nothing = torch.zeros(num_envs, dtype=torch.long, device=ids.device)
            return nothing, nothing.double(), nothing.bool()
        stored = self._stored
        match = (ids[:, None] == stored.ids[None, :]) & stored.known[None, :]  # (E, S)
        row = match.int().argmax(dim=1)
        return stored.lane[row], stored.deceleration[row], match.any(dim=1)

    def _keep(self, chosen: "_Stored") -> None:
        """Store this step's fail-safes; with fixed shapes only these (no size read on the host),
        else also those of the environments not decided this step."""
        if self._stored is not None and not self.verifier.fixed_shapes:
            others = self._stored.without(chosen.ids)
            others = _Stored(*(field[others.known] for field in others))
            chosen = _Stored(*(torch.cat([kept, new.to(kept.dtype)]) for kept, new in zip(others, chosen)))
        self._stored = chosen

    def _candidates(self, ego: torch.Tensor, acceleration: torch.Tensor, steering: torch.Tensor, rows: torch.Tensor,
                    alternatives: Optional[Alternatives]) -> tuple[torch.Tensor, torch.Tensor]:
        """(R, K) accelerations and steerings to try in the ``rows`` whose command did not verify:
        its steering with each of :data:`BRAKING`, the caller's alternatives, then the fail-safes'
        first commands."""
        own_acceleration, own_steering = acceleration[rows, None], steering[rows, None]
        braking = torch.tensor(BRAKING, dtype=ego.dtype, device=ego.device)
        failsafe_acceleration, failsafe_steering = self.verifier.failsafe_candidates(ego[rows])
        accelerations = [torch.minimum(own_acceleration, -braking), failsafe_acceleration]
        steerings = [own_steering.expand(-1, braking.numel()), failsafe_steering]
        if alternatives is not None:
            other_acceleration, other_steering = alternatives(rows)
            usable = other_acceleration.isfinite()  # a missing one repeats the asked command, which did not verify
            accelerations.insert(1, torch.where(usable, other_acceleration.to(ego.dtype), own_acceleration))
            steerings.insert(1, torch.where(usable, other_steering.to(ego.dtype), own_steering))
        return torch.cat(accelerations, dim=1), torch.cat(steerings, dim=1)


class _Stored(NamedTuple):
    """Fail-safes stored per environment: (S,) ids, target lanes, decelerations [m/s^2], and
    whether each entry holds one (False: forgotten)."""

    ids: torch.Tensor
    lane: torch.Tensor
    deceleration: torch.Tensor
    known: torch.Tensor

    def without(self, ids: torch.Tensor) -> "_Stored":
        """These entries with those of ``ids`` forgotten."""
        gone = (self.ids[:, None] == ids[None, :]).any(dim=1)
        return self._replace(known=self.known & ~gone)
