"""Holding a plan between replans: sample it, track it, and check it against new predictions.

A receding-horizon loop that replans less often than it controls (e.g. the safe RL layer at
the agent's decision rate, :mod:`mmpc.rl.safety`) executes the plan it holds: at ``elapsed``
seconds after planning it follows the plan's acceleration and heading rate, corrected for the
drift of the real vehicle from the plan (:func:`track`). Every frame it checks the rest of the
plan against the obstacles as they are predicted *now* (:func:`plan_clearance`) and replans
where they have come too close or the vehicle has drifted too far (:func:`needs_replan`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Union

import torch

from mmpc.config import require_positive
from mmpc.obstacles.prediction import Predictor
from mmpc.obstacles.shape import ellipse_distance_squared, smallest_distance
from mmpc.problem import EGO_PSI, EGO_V, EGO_X, EGO_Y
from mmpc.result import Trajectories

@dataclass(frozen=True)
class TrackingConfig:
    """Tracking a held plan, and when to give it up.

    Attributes:
        speed_gain: acceleration per unit of speed error, ``a = a_plan + k (v_plan - v)`` [1/s].
        heading_gain: heading rate per unit of heading error [1/s].
        lateral_gain: heading rate per metre of lateral error [rad/(m s)].
        max_lateral_error: replan when the vehicle is farther than this from the plan across the road [m].
        max_speed_error: replan when its speed differs from the plan's by more than this [m/s].
    """

    speed_gain: float = 1.0
    heading_gain: float = 1.0
    lateral_gain: float = 0.1
    max_lateral_error: float = 0.5
    max_speed_error: float = 1.0

    def __post_init__(self) -> None:
        require_positive("tracking", speed_gain=self.speed_gain, heading_gain=self.heading_gain,
                         lateral_gain=self.lateral_gain, max_lateral_error=self.max_lateral_error,
                         max_speed_error=self.max_speed_error)


def sample(trajectory: Trajectories, at: torch.Tensor) -> Trajectories:
    """Plans sampled at other times, by linear interpolation between their samples.

    Args:
        trajectory: E plans, every field (E, N), at ``trajectory.times`` (N,) [s].
        at: (E, K) query times [s] measured from each plan's start; clamped to the horizon.

    Returns:
        :class:`Trajectories` with every field (E, K) and ``times`` the clamped ``at`` (E, K).
    """
    times = trajectory.times.to(at.dtype)
    at = at.clamp(float(times[0]), float(times[-1]))
    upper = torch.searchsorted(times, at.contiguous(), right=True).clamp(1, times.numel() - 1)  # (E, K)
    lower = upper - 1
    weight = (at - times[lower]) / (times[upper] - times[lower])
    fields = [torch.lerp(field.gather(1, lower), field.gather(1, upper), weight.to(field.dtype)) for field in trajectory[1:]]
    return Trajectories(at, *fields)


def plan_clearance(
    trajectory: Trajectories,
    elapsed: torch.Tensor,
    states: torch.Tensor,
    mask: torch.Tensor,
    predict: Predictor,
    ellipse: Union[tuple[float, float], torch.Tensor],
) -> torch.Tensor:
    """The smallest normalised ellipse distance between the rest of each plan and the obstacles
    as predicted now.

    Args:
        trajectory: E plans, every field (E, N) at ``trajectory.times`` (N,) [s].
        elapsed: (E,) time since each plan's start [s].
        states: (E, M, 4) obstacles now (x, y, vx, vy) [m, m/s], e.g. :meth:`mmpc.MPC.nearest_obstacles`.
        mask: (E, M) bool, present obstacles.
        predict: obstacle prediction over times from now.
        ellipse: (a, b) semi-axes [m], or (E, M, 2) per obstacle (:meth:`mmpc.MPC.obstacle_axes`).

    Returns:
        (E,) ``min sqrt((dx / a)^2 + (dy / b)^2)`` over present obstacles and the plan's remaining
        samples (< 1: the plan runs into an ellipse); +inf without obstacles or plan left.
    """
    if states.shape[1] == 0:
        return torch.full_like(elapsed, float("inf"))
    times = trajectory.times
    ahead = elapsed[:, None] + times[None, :]  # (E, N) plan times of the prediction instants
    rest = sample(trajectory, ahead)
    centres = predict(states, times)  # (E, M, N, 2)
    points = torch.stack([rest.x, rest.y], dim=-1)[:, None]  # (E, 1, N, 2)
    axes = ellipse[:, :, None, :] if isinstance(ellipse, torch.Tensor) else ellipse  # (E, M, 1, 2)
    counted = mask[..., None] & (ahead <= times[-1] + 1e-9)[:, None, :]
    return smallest_distance(ellipse_distance_squared(points, centres, axes), counted, (1, 2))


def track(
    trajectory: Trajectories, elapsed: torch.Tensor, ego: torch.Tensor, window: float, config: TrackingConfig
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Commands that follow held plans ``elapsed`` seconds after they were made.

    The feed-forward is the plan's tangential acceleration and heading rate averaged over
    ``[elapsed, elapsed + window]`` (as :class:`mmpc.MPC` commands a fresh plan); the feedback
    pulls the speed, the heading and the lateral position back to the plan's at ``elapsed``.

    Args:
        trajectory: E plans, every field (E, N) at ``trajectory.times`` (N,) [s].
        elapsed: (E,) [s].
        ego: (E, 6) the vehicles now (x, y, psi, v, a, psidot).
        window: averaging window of the feed-forward [s].
        config: gains.

    Returns:
        acceleration (E,) [m/s^2], heading rate (E,) [rad/s], lateral error (E,) [m] and speed
        error (E,) [m/s] (plan minus vehicle).
    """
    times = trajectory.times
    count = max(2, int((times <= window + 1e-9).sum()))
    offsets = torch.linspace(0.0, window, count, dtype=elapsed.dtype, device=elapsed.device)
    ahead = sample(trajectory, elapsed[:, None] + offsets[None, :])  # (E, count)
    speed = torch.hypot(ahead.xdot, ahead.ydot).clamp_min(1e-3)
    tangential = (ahead.xdot * ahead.xddot + ahead.ydot * ahead.yddot) / speed
    ref_speed, ref_psi = speed[:, 0], ahead.psi[:, 0]
    # lateral error in the plan's own frame: the offset across its direction of travel
    dx, dy = ahead.x[:, 0] - ego[:, EGO_X], ahead.y[:, 0] - ego[:, EGO_Y]
    lateral = -torch.sin(ref_psi) * dx + torch.cos(ref_psi) * dy
    speed_error = ref_speed - ego[:, EGO_V]
    heading_error = torch.atan2(torch.sin(ref_psi - ego[:, EGO_PSI]), torch.cos(ref_psi - ego[:, EGO_PSI]))
    acceleration = tangential.mean(dim=1) + config.speed_gain * speed_error
    heading_rate = ahead.psidot.mean(dim=1) + config.heading_gain * heading_error + config.lateral_gain * lateral
    return acceleration, heading_rate, lateral, speed_error


def needs_replan(
    clearance: torch.Tensor, lateral_error: torch.Tensor, speed_error: torch.Tensor, obstacle_tolerance: float,
    config: TrackingConfig,
) -> torch.Tensor:
    """(E,) bool: the held plan now runs into an obstacle's ellipse (``clearance < 1 -
    obstacle_tolerance``, the optimizer's own feasibility test) or the vehicle has left it."""
    return (
        (clearance < 1.0 - obstacle_tolerance)
        | (lateral_error.abs() > config.max_lateral_error)
        | (speed_error.abs() > config.max_speed_error)
    )
