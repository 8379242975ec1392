"""Deterministic highway scenes: the demo of ``mmpc solve`` and the synthetic test/benchmark set."""

from __future__ import annotations

from typing import NamedTuple

import torch

from mmpc.obstacles.prediction import predict_constant_velocity
from mmpc.obstacles.shape import ellipse_distance_squared, offset_distance, smallest_distance
from mmpc.problem import ProblemBatch, ego_state
from mmpc.road import Road
from mmpc.solver.config import OptimizerConfig

#: The obstacle ellipse the scenes are made for: the default (the paper authors') optimizer's [m].
SCENE_ELLIPSE = OptimizerConfig().ellipse


class Scene(NamedTuple):
    """One highway problem with its goals.

    Fields:
        name: short description.
        road: the road.
        problem: a :class:`ProblemBatch` with E = 1.
        obstacle_states: (1, M, 4) obstacle (x, y, vx, vy) at t = 0 [m, m/s].
        reachable: (1, G) bool, True where the goal is certified easy: the straight
            constant-velocity path from the ego to the goal keeps normalised distance >= 1.2 from
            every obstacle, the goal is at most two lanes away and the mean speed it asks for
            is within [5, 25] m/s.
    """

    name: str
    road: Road
    problem: ProblemBatch
    obstacle_states: torch.Tensor
    reachable: torch.Tensor


def _certify_reachable(
    ego: torch.Tensor, goals: torch.Tensor, obstacles: torch.Tensor, times: torch.Tensor,
    horizon: float, road: Road, ellipse: tuple[float, float],
) -> torch.Tensor:
    """(1, G) bool: see :class:`Scene`."""
    tau = (times / horizon)[:, None]  # (N, 1)
    start = ego[0, :2]
    path = start + tau[None] * (goals[0, :, None, :] - start)  # (G, N, 2)
    clear = smallest_distance(ellipse_distance_squared(path[:, None], obstacles[0][None], ellipse), None, (1, 2)) >= 1.2
    lateral = (goals[0, :, 1] - ego[0, 1]).abs() <= 2 * road.lane_width + 1e-6
    mean_speed = (goals[0, :, 0] - ego[0, 0]) / horizon
    speed_ok = (mean_speed >= 5.0) & (mean_speed <= 25.0)
    return (clear & lateral & speed_ok)[None]


def demo_scene(num_steps: int = 100, horizon: float = 8.0) -> Scene:
    """The built-in scene of ``mmpc solve``: ego in lane 2 of 6 at 14 m/s among six slower cars,
    11 cruise goals at 120 m."""
    road = Road(num_lanes=6)
    times = torch.linspace(0.0, horizon, num_steps)
    ego = ego_state(0.0, 8.0, 0.0, 14.0)
    states = torch.tensor(
        [
            [25.0, 8.0, 10.0, 0.0],
            [45.0, 4.0, 11.0, 0.0],
            [12.0, 12.0, 9.0, 0.0],
            [70.0, 8.0, 10.0, 0.0],
            [-15.0, 4.0, 12.0, 0.0],
            [35.0, 16.0, 8.0, 0.0],
        ]
    )[None]
    obstacles = predict_constant_velocity(states, times)
    lateral = torch.linspace(0.0, road.right_lane_y, 11)
    goals = torch.stack([torch.full_like(lateral, 120.0), lateral], dim=-1)[None]
    reachable = _certify_reachable(ego, goals, obstacles, times, horizon, road, SCENE_ELLIPSE)
    problem = ProblemBatch(ego, goals, obstacles)
    return Scene("demo: six slower cars, 11 cruise goals", road, problem, states, reachable)


def synthetic_scenes(
    count: int = 32, seed: int = 0, *, num_steps: int = 100, horizon: float = 8.0,
    dtype: torch.dtype = torch.float32,
) -> list[Scene]:
    """``count`` deterministic random highway scenes.

    Scene i has 3 + i % 4 lanes and i % 11 obstacles (so 0 ... 10 are all covered), the ego at
    a random x (up to 2 km, to exercise the relative frame) in a random lane at 10-20 m/s with a
    small heading, obstacles at 7-20 m/s in random lanes 25 ... 130 m ahead or up to 30 m
    behind, never overlapping the ego or each other at t = 0. Goals: every lane centre at
    15 m/s x t_f ahead plus the ego's lane at 10 and 20 m/s x t_f (straight ahead and lane
    changes).
    """
    if count < 1:
        raise ValueError(f"`count` must be >= 1; got {count}")
    generator = torch.Generator().manual_seed(seed)

    def uniform(low: float, high: float) -> float:
        return low + (high - low) * float(torch.rand((), generator=generator, dtype=torch.float64))

    def integer(high: int) -> int:
        return int(torch.randint(high, (), generator=generator))

    times = torch.linspace(0.0, horizon, num_steps, dtype=torch.float64)
    scenes = []
    for i in range(count):
        road = Road(num_lanes=3 + i % 4)
        lanes = road.lane_centers(dtype=torch.float64)
        ego_x = uniform(0.0, 2000.0)
        ego_lane = integer(road.num_lanes)
        ego_v = uniform(10.0, 20.0)
        ego = ego_state(ego_x, float(lanes[ego_lane]), uniform(-0.03, 0.03), ego_v, dtype=torch.float64)
        placed: list[tuple[float, float, float]] = []
        attempts = 0
        while len(placed) < i % 11 and attempts < 1000:
            attempts += 1
            lane = integer(road.num_lanes)
            x = ego_x + (uniform(25.0, 130.0) if integer(4) else uniform(-30.0, -12.0))
            y = float(lanes[lane])
            if offset_distance(x - ego_x, y - float(ego[0, 1]), SCENE_ELLIPSE) < 1.5:
                continue
            if any(py == y and abs(px - x) < 14.0 for px, py, _ in placed):
                continue
            placed.append((x, y, uniform(7.0, 20.0)))
        states = torch.tensor([[x, y, v, 0.0] for x, y, v in placed], dtype=torch.float64).reshape(1, -1, 4)
        obstacles = predict_constant_velocity(states, times)
        goal_x = [ego_x + 15.0 * horizon] * road.num_lanes + [ego_x + 10.0 * horizon, ego_x + 20.0 * horizon]
        goal_y = lanes.tolist() + [float(lanes[ego_lane])] * 2
        goals = torch.tensor([list(zip(goal_x, goal_y))], dtype=torch.float64)
        reachable = _certify_reachable(ego, goals, obstacles, times, horizon, road, SCENE_ELLIPSE)
        problem = ProblemBatch(ego.to(dtype), goals.to(dtype), obstacles.to(dtype))
        name = f"scene {i}: {road.num_lanes} lanes, {len(placed)} obstacles"
        scenes.append(Scene(name, road, problem, states.to(dtype), reachable))
    return scenes
