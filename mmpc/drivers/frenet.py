"""Frenet-frame sampling planner (Werling et al., ICRA 2010), the paper's third baseline.

On a straight road the Frenet frame is the road frame: ``s = x`` along the road, ``d = y``
across it. For every combination of a lateral end offset ``d_T``, a duration ``T`` and an end
speed ``v_T`` (by default 11 x 6 x 8 = 528 candidates) the planner builds

* a quintic lateral polynomial ``d(t)`` from the current ``(d, d', d'')`` to ``(d_T, 0, 0)`` at
  ``T``, held at ``d_T`` afterwards;
* a quartic longitudinal polynomial ``s(t)`` from the current ``(s, s', s'')`` to
  ``(s'(T), s''(T)) = (v_T, 0)``, continued at constant speed ``v_T`` afterwards;

samples them on the batch optimizer's N instants of its horizon, and keeps the candidates whose
speed ``hypot(s', d')`` stays in ``[v_min, v_max]``, acceleration ``hypot(s'', d'')`` below
``a_max``, curvature ``(s' d'' - d' s'') / v^3`` below ``max_curvature``, heading
``atan2(d', s')`` within ``+-max_heading_deg``, that stay on the road and outside every
obstacle ellipse (same ellipse and the same predictions (:meth:`mmpc.MPC.predict`) of the same nearest
vehicles as ours). Among those the scenario's meta cost picks one (Werling's own cost, jerk plus
time plus deviation, is replaced by the meta cost so that every method optimises the same
objective). Everything is one batch of tensor operations over (E, candidates, N).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Optional

import torch

from mmpc.drivers.common import checked_ego, obstacles_for, ranked_decision
from mmpc.config import require_int, require_positive
from mmpc.drivers.base import Decision, Driver, Observation
from mmpc.mpc import MPC
from mmpc.obstacles.shape import squared_obstacle_distance
from mmpc.problem import EGO_A, EGO_PSI, EGO_PSIDOT, EGO_V, EGO_X, EGO_Y
from mmpc.result import Trajectories


@dataclass(frozen=True)
class FrenetConfig:
    """Sampling grid and filters of the Frenet planner.

    Attributes:
        num_offsets: lateral end offsets, spread evenly from the leftmost to the rightmost lane
            centre (11 on a 6-lane road: every lane centre and lane boundary) [-].
        durations: manoeuvre durations T [s]; each at most the horizon.
        num_speeds: end speeds, spread evenly over ``(0, top speed]`` of the scenario's
            objective (the fastest speed it asks for) [-].
        max_heading_deg: heading band around the road direction (the paper's assumption 2) [deg].
        max_curvature: largest path curvature (highway-env's bicycle: tan(pi/4) / 5 m) [1/m].
    """

    num_offsets: int = 11
    durations: tuple[float, ...] = (3.0, 4.0, 5.0, 6.0, 7.0, 8.0)
    num_speeds: int = 8
    max_heading_deg: float = 13.0
    max_curvature: float = 0.2

    def __post_init__(self) -> None:
        require_int("frenet", low=1, num_offsets=self.num_offsets, num_speeds=self.num_speeds)
        if not isinstance(self.durations, tuple) or not self.durations or any(
            not (isinstance(t, (int, float)) and math.isfinite(t) and t > 0) for t in self.durations
        ):
            raise ValueError(f"frenet: `durations` must be a non-empty list of finite times > 0 s; got {self.durations!r}")
        if not 0 < self.max_heading_deg < 90:
            raise ValueError(f"frenet: `max_heading_deg` must be in (0, 90) deg; got {self.max_heading_deg!r}")
        require_positive("frenet", max_curvature=self.max_curvature)

    @property
    def num_candidates(self) -> int:
        return self.num_offsets * len(self.durations) * self.num_speeds


def quintic_coefficients(start: torch.Tensor, end: torch.Tensor, duration: torch.Tensor) -> torch.Tensor:
    """Coefficients ``c_0..c_5`` of ``d(t) = sum c_i t^i`` with ``(d, d', d'')(0) = start`` and
    ``(d, d', d'')(T) = end``.

    Args:
        start: (..., 3) initial value, rate and second derivative.
        end: (..., 3) the same at ``T``.
        duration: (...,) T [s], > 0.

    Returns:
        (..., 6) coefficients (ascending powers).
    """
    d0, d1, d2 = start.unbind(-1)
    t = duration
    c2 = 0.5 * d2
    rhs = torch.stack([
        end[..., 0] - d0 - d1 * t - c2 * t**2,
        end[..., 1] - d1 - 2 * c2 * t,
        end[..., 2] - 2 * c2,
    ], dim=-1)
    matrix = torch.stack([
        torch.stack([t**3, t**4, t**5], dim=-1),
        torch.stack([3 * t**2, 4 * t**3, 5 * t**4], dim=-1),
        torch.stack([6 * t, 12 * t**2, 20 * t**3], dim=-1),
    ], dim=-2)
    high = torch.linalg.solve(matrix, rhs)
    return torch.cat([torch.stack([d0, d1, c2], dim=-1), high], dim=-1)


def quartic_coefficients(start: torch.Tensor, end_rate: torch.Tensor, end_acceleration: torch.Tensor, duration: torch.Tensor) -> torch.Tensor:
    """Coefficients ``c_0..c_4`` of ``s(t)`` with ``(s, s', s'')(0) = start`` and
    ``(s', s'')(T) = (end_rate, end_acceleration)`` (the end position is free).

    Args:
        start: (..., 3); end_rate, end_acceleration, duration: (...,).

    Returns:
        (..., 5) coefficients (ascending powers).
    """
    s0, s1, s2 = start.unbind(-1)
    t = duration
    c2 = 0.5 * s2
    rhs = torch.stack([end_rate - s1 - 2 * c2 * t, end_acceleration - 2 * c2], dim=-1)
    matrix = torch.stack([
        torch.stack([3 * t**2, 4 * t**3], dim=-1),
        torch.stack([6 * t, 12 * t**2], dim=-1),
    ], dim=-2)
    high = torch.linalg.solve(matrix, rhs)
    return torch.cat([torch.stack([s0, s1, c2], dim=-1), high], dim=-1)


def evaluate_polynomial(coefficients: torch.Tensor, times: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Value, first and second derivative of ``sum c_i t^i``.

    Args:
        coefficients: (..., P) ascending powers.
        times: (..., N) broadcastable against the leading dims [s].

    Returns:
        three (..., N) tensors.
    """
    degree = coefficients.shape[-1]
    powers = torch.arange(degree, dtype=coefficients.dtype, device=coefficients.device)
    t = times[..., None]  # (..., N, 1)
    c = coefficients[..., None, :]  # (..., 1, P)
    value = (c * t**powers).sum(-1)
    first = (c[..., 1:] * powers[1:] * t ** (powers[1:] - 1)).sum(-1)
    second = (c[..., 2:] * powers[2:] * (powers[2:] - 1) * t ** (powers[2:] - 2)).sum(-1)
    return value, first, second


class FrenetPlanner:
    """Vectorized Frenet sampling over E problems.

    Args:
        mpc: the scenario's MPC, for its sample times, bounds, ellipse, road, obstacle set and
            meta cost (nothing of its optimizer runs).
        top_speed: the fastest end speed sampled [m/s].
        config: sampling grid and filters.
    """

    def __init__(self, mpc: MPC, top_speed: float, config: Optional[FrenetConfig] = None) -> None:
        self.mpc = mpc
        self.config = config if config is not None else FrenetConfig()
        horizon = mpc.optimizer.config.horizon
        if max(self.config.durations) > horizon + 1e-9:
            raise ValueError(f"frenet: `durations` must be <= the horizon {horizon} s; got {self.config.durations}")
        if not (math.isfinite(top_speed) and top_speed > 0):
            raise ValueError(f"`top_speed` must be a finite number > 0 m/s; got {top_speed!r}")
        road = mpc.road
        self.offsets = torch.linspace(0.0, road.right_lane_y, self.config.num_offsets) if self.config.num_offsets > 1 \
            else torch.tensor([0.0])
        self.durations = torch.tensor(self.config.durations)
        self.speeds = torch.linspace(top_speed / self.config.num_speeds, top_speed, self.config.num_speeds)

    def candidates(self, ego: torch.Tensor) -> Trajectories:
        """All candidates of E problems, fields (E, C, N), C = durations x offsets x speeds
        (speed fastest-varying)."""
        times = self.mpc.optimizer.times.to(ego.dtype)
        psi, v, a, rate = ego[:, EGO_PSI], ego[:, EGO_V], ego[:, EGO_A], ego[:, EGO_PSIDOT]
        cos, sin = torch.cos(psi), torch.sin(psi)
        s_start = torch.stack([ego[:, EGO_X], v * cos, a * cos - v * rate * sin], dim=-1)  # (E, 3)
        d_start = torch.stack([ego[:, EGO_Y], v * sin, a * sin + v * rate * cos], dim=-1)
        e, n = ego.shape[0], times.numel()
        durations = self.durations.to(ego.dtype)
        offsets = self.offsets.to(ego.dtype)
        speeds = self.speeds.to(ego.dtype)
        num_d, num_o, num_s = durations.numel(), offsets.numel(), speeds.numel()

        # Lateral: (E, D, O) quintics.
        d_end = torch.stack(torch.broadcast_tensors(offsets, torch.zeros_like(offsets), torch.zeros_like(offsets)), dim=-1)
        lateral = quintic_coefficients(
            d_start[:, None, None, :].expand(e, num_d, num_o, 3), d_end[None, None].expand(e, num_d, num_o, 3),
            durations[None, :, None].expand(e, num_d, num_o),
        )
        # Longitudinal: (E, D, S) quartics.
        longitudinal = quartic_coefficients(
            s_start[:, None, None, :].expand(e, num_d, num_s, 3), speeds[None, None].expand(e, num_d, num_s),
            torch.zeros(e, num_d, num_s, dtype=ego.dtype), durations[None, :, None].expand(e, num_d, num_s),
        )
        clipped = torch.minimum(times[None, :], durations[:, None])  # (D, N)
        after = (times[None, :] - durations[:, None]).clamp_min(0.0)  # (D, N)
        d, d1, d2 = evaluate_polynomial(lateral, clipped[None, :, None, :])  # (E, D, O, N)
        holding = (after > 0)[None, :, None, :]
        d1 = torch.where(holding, torch.zeros_like(d1), d1)
        d2 = torch.where(holding, torch.zeros_like(d2), d2)
        s, s1, s2 = evaluate_polynomial(longitudinal, clipped[None, :, None, :])  # (E, D, S, N)
        s = s + speeds[None, None, :, None] * after[None, :, None, :]
        s1 = torch.where(holding, speeds[None, None, :, None].expand_as(s1), s1)
        s2 = torch.where(holding, torch.zeros_like(s2), s2)

        def grid(lat: torch.Tensor, lon: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            shape = (e, num_d, num_o, num_s, n)
            return lat[:, :, :, None].expand(shape).reshape(e, -1, n), lon[:, :, None].expand(shape).reshape(e, -1, n)

        y, x = grid(d, s)
        ydot, xdot = grid(d1, s1)
        yddot, xddot = grid(d2, s2)
        speed = torch.hypot(xdot, ydot)
        heading = torch.atan2(ydot, xdot)
        heading_rate = (xdot * yddot - ydot * xddot) / speed.clamp_min(1e-3) ** 2
        return Trajectories(times, x, y, heading, speed, xdot, ydot, xddot, yddot, heading_rate)

    def feasible(self, ego: torch.Tensor, trajectories: Trajectories, obstacles: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """(E, C) bool: the candidates that pass every filter.

        Args:
            ego: (E, 6); trajectories: fields (E, C, N); obstacles: (E, M, N, 2) predicted
            centres at the sample times; mask: (E, M).
        """
        opt = self.mpc.optimizer.config
        tr = trajectories
        speed_ok = ((tr.v >= opt.v_min) & (tr.v <= opt.v_max))[..., 1:].all(-1)
        acceleration_ok = (torch.hypot(tr.xddot, tr.yddot) <= opt.a_max + opt.acceleration_tolerance)[..., 1:].all(-1)
        curvature = tr.psidot / tr.v.clamp_min(1e-3)
        curvature_ok = (curvature.abs() <= self.config.max_curvature)[..., 1:].all(-1)
        band = torch.clamp(ego[:, EGO_PSI, None, None].abs(), min=math.radians(self.config.max_heading_deg))
        heading_ok = (tr.psi.abs() <= band + 1e-9)[..., 1:].all(-1)
        low, high = self.mpc.lateral_band(ego)
        road_ok = ((tr.y >= low[:, None, None] - 1e-9) & (tr.y <= high[:, None, None] + 1e-9)).all(-1)
        inside = (squared_obstacle_distance(tr, obstacles, opt.ellipse) < 1.0) & mask[:, None, :, None]  # (E, C, M, N)
        clear = ~inside[..., 1:].any(-1).any(-1)
        return speed_ok & acceleration_ok & curvature_ok & heading_ok & road_ok & clear


class FrenetDriver(Driver):
    """The Frenet sampling planner behind the driver interface (memoryless).

    Args:
        planner: the planner.
        name: the driver's name in tables.
    """

    def __init__(self, planner: FrenetPlanner, name: str = "frenet") -> None:
        self.planner = planner
        self.name = name

    @torch.no_grad()
    def decide(self, observation: Observation) -> Decision:
        start = time.perf_counter()
        mpc = self.planner.mpc
        ego = checked_ego(observation, mpc.optimizer.dtype)
        vehicles = observation.vehicles.to(ego.dtype)
        trajectories = self.planner.candidates(ego)
        obstacles, mask = obstacles_for(mpc, ego, vehicles, observation.vehicle_mask, trajectories.times)
        feasible = self.planner.feasible(ego, trajectories, obstacles, mask)
        return ranked_decision(mpc, ego, trajectories, feasible, start, obstacles=(obstacles, mask))


def make_frenet_driver(scenario, argument: Optional[str]) -> Driver:
    """Registry factory (``frenet``; no argument): the scenario's Frenet planner."""
    from mmpc.scenario import build_mpc

    if argument is not None:
        raise ValueError(f"driver 'frenet' takes no argument; got 'frenet:{argument}'")
    return FrenetDriver(FrenetPlanner(build_mpc(scenario, device="cpu"), scenario.objective.top_speed))
