"""Rectangle collisions by separating axes, batched, as highway-env checks them.

highway-env (``RoadObject.handle_collisions``, ``utils.are_polygons_intersecting``) checks,
after every frame, each pair (i, j), i < j in ``road.vehicles`` order:

1. a bounding-circle pre-check: no collision if the centres are farther apart than
   ``(diagonal_i + diagonal_j) / 2 + speed_i dt`` (only the first vehicle's travel is added);
2. the separating-axis test on the two rectangles' 8 edge normals (4 per polygon, from the
   corner differences): *intersecting* unless some axis separates the projections;
   *will intersect* likewise with the first rectangle's projection stretched by the relative
   displacement ``(velocity_i - velocity_j) dt`` (velocity = speed along the body heading, no slip);
3. if they will intersect: the translation, the smallest overlap along its axis pointing from j
   to i, is split as a push ``+t/2`` to i and ``-t/2`` to j, applied at the next frame (which
   marks them crashed); a vehicle in several such pairs keeps the last pair's push in that
   order. If they intersect now, both are crashed at once.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from mmpc.compaction import capacity, compact
from mmpc.sim.state import VehicleState

#: The collision test's buffer: pairs past the bounding-circle pre-check per environment on average,
#: and at least (a small batch may hold one pile-up). Traffic fills ~0.1-2.7 per environment.
PAIRS_PER_ENV = 2.0
PAIRS_FLOOR = 64


class PolygonTest(NamedTuple):
    """Separating-axis result for pairs of rectangles; shapes (...) as the pairs, ``translation`` (..., 2)."""

    intersecting: torch.Tensor  # (...) bool, the rectangles overlap now (touching is overlapping)
    will_intersect: torch.Tensor  # (...) bool, they overlap within the displacement
    translation: torch.Tensor  # (..., 2) [m], minimal push of the first out of the second; zero unless will_intersect


def rectangle_corners(
    x: torch.Tensor, y: torch.Tensor, heading: torch.Tensor, length: torch.Tensor, width: torch.Tensor
) -> torch.Tensor:
    """(..., 4, 2) corners [m] of rectangles centred at (x, y) (...), in highway-env's order:
    rear-right, rear-left, front-left, front-right in the body frame (x forward, y left)."""
    half_length, half_width = length / 2, width / 2
    local_x = torch.stack([-half_length, -half_length, half_length, half_length], dim=-1)
    local_y = torch.stack([-half_width, half_width, half_width, -half_width], dim=-1)
    cos, sin = torch.cos(heading)[..., None], torch.sin(heading)[..., None]
    return torch.stack([cos * local_x - sin * local_y + x[..., None], sin * local_x + cos * local_y + y[..., None]], dim=-1)


def _edge_normals(corners: torch.Tensor) -> torch.Tensor:
    """(..., 4, 2) unit normals of the closed polygon's 4 edges, in order."""
    edges = torch.roll(corners, -1, dims=-2) - corners
    normals = torch.stack([-edges[..., 1], edges[..., 0]], dim=-1)
    return normals / torch.sqrt(normals[..., 0] ** 2 + normals[..., 1] ** 2)[..., None]


def _interval_distance(min_a, max_a, min_b, max_b) -> torch.Tensor:
    """highway-env's ``interval_distance``: positive iff the intervals are apart."""
    return torch.where(min_a < min_b, min_b - max_a, min_a - max_b)


def polygons_intersecting(
    corners_a: torch.Tensor, corners_b: torch.Tensor, displacement_a: torch.Tensor, displacement_b: torch.Tensor
) -> PolygonTest:
    """highway-env's ``are_polygons_intersecting`` for rectangles, batched.

    Shapes:
        corners_a, corners_b: (..., 4, 2) [m] as :func:`rectangle_corners`, broadcasting.
        displacement_a, displacement_b: (..., 2) [m] travel within the frame.
    """
    axes = torch.cat(torch.broadcast_tensors(_edge_normals(corners_a), _edge_normals(corners_b)), dim=-2)  # (..., 8, 2)

    def project(corners: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        projected = corners[..., None, :, 0] * axes[..., :, None, 0] + corners[..., None, :, 1] * axes[..., :, None, 1]
        return projected.min(dim=-1).values, projected.max(dim=-1).values  # (..., 8)

    min_a, max_a = project(corners_a)
    min_b, max_b = project(corners_b)
    intersecting = (_interval_distance(min_a, max_a, min_b, max_b) <= 0).all(dim=-1)
    relative = displacement_a - displacement_b
    travel = axes[..., 0] * relative[..., None, 0] + axes[..., 1] * relative[..., None, 1]
    min_a = torch.where(travel < 0, min_a + travel, min_a)
    max_a = torch.where(travel < 0, max_a, max_a + travel)
    distance = _interval_distance(min_a, max_a, min_b, max_b)
    will_intersect = (distance <= 0).all(dim=-1)
    smallest = distance.abs().argmin(dim=-1, keepdim=True)  # first of the smallest, as highway-env's strict <
    axis = torch.gather(axes, -2, smallest[..., None].expand(*smallest.shape, 2)).squeeze(-2)
    centres = corners_a.sum(dim=-2) / 4 - corners_b.sum(dim=-2) / 4
    toward_a = (centres * axis).sum(dim=-1, keepdim=True) > 0
    translation = torch.gather(distance.abs(), -1, smallest) * torch.where(toward_a, axis, -axis)
    return PolygonTest(intersecting, will_intersect, torch.where(will_intersect[..., None], translation, 0.0))


def pair_collisions(state: VehicleState, dt: float, fixed_shapes: bool = False) -> tuple[PolygonTest, torch.Tensor]:
    """Every pair's test after a frame, (E, V, V) ([e, i, j], i < j; False elsewhere): pairs
    where either vehicle checks collisions, the bounding-circle pre-check, then
    :func:`polygons_intersecting` of i (as ``a``) and j, computed for the pairs that pass the
    pre-check only (``fixed_shapes``: gathered in a buffer of :data:`PAIRS_PER_ENV` pairs per
    environment, :mod:`mmpc.compaction`; else as many as there are, counted on the host).

    Returns:
        The test, and (E,) bool: the environment had pairs past the buffer, left untested.
    """
    dx = state.x[:, None, :] - state.x[:, :, None]
    dy = state.y[:, None, :] - state.y[:, :, None]
    diagonal = torch.sqrt(state.length ** 2 + state.width ** 2)
    reach = (diagonal[:, :, None] + diagonal[:, None, :]) / 2 + (state.speed * dt)[:, :, None]
    num_envs, num_vehicles = state.x.shape
    upper = torch.ones(num_vehicles, num_vehicles, dtype=torch.bool, device=state.x.device).triu(1)
    checking = state.check_collisions[:, :, None] | state.check_collisions[:, None, :]
    checked = upper & checking & state.alive[:, :, None] & state.alive[:, None, :] & ~(torch.sqrt(dx * dx + dy * dy) > reach)
    every_pair = num_envs * num_vehicles * (num_vehicles - 1) // 2
    pairs = compact(checked, capacity(fixed_shapes, num_envs, PAIRS_PER_ENV, PAIRS_FLOOR, every_pair))
    env, first, second = pairs.index  # (K,) each; the padding points at (0, 0, 0), never a pair
    both = (env[:, None], torch.stack([first, second], dim=1))
    corners = rectangle_corners(state.x[both], state.y[both], state.heading[both], state.length[both],
                                state.width[both])  # (K, 2, 4, 2)
    speed, heading = state.speed[both], state.heading[both]
    travel = (speed * dt)[..., None] * torch.stack([torch.cos(heading), torch.sin(heading)], dim=-1)  # (K, 2, 2)
    test = polygons_intersecting(corners[:, 0], corners[:, 1], travel[:, 0], travel[:, 1])
    intersecting = torch.zeros_like(checked)
    will_intersect = torch.zeros_like(checked)
    translation = state.x.new_zeros((*checked.shape, 2))
    intersecting[env, first, second] = test.intersecting & pairs.valid
    will_intersect[env, first, second] = test.will_intersect & pairs.valid
    translation[env, first, second] = torch.where(pairs.valid[:, None], test.translation, 0.0)
    return PolygonTest(intersecting, will_intersect, translation), pairs.dropped.flatten(1).any(dim=1)


def handle_collisions(state: VehicleState, dt: float, fixed_shapes: bool = False) -> tuple[VehicleState, torch.Tensor]:
    """Mark intersecting vehicles crashed and store the pushes of predicted collisions (see the
    module); and (E,) bool, the environments with pairs left untested (:func:`pair_collisions`)."""
    pairs, untested = pair_collisions(state, dt, fixed_shapes)
    crashed = state.crashed | pairs.intersecting.any(dim=2) | pairs.intersecting.any(dim=1)
    num_vehicles = state.x.shape[1]
    slots = torch.arange(num_vehicles, device=state.x.device)
    # highway-env's loop visits (i, j) in lexicographic order; vehicle k is last touched by its
    # own pair with the largest j > k if any, else by the pair (i, k) with the largest i < k.
    as_first = torch.where(pairs.will_intersect, slots, -1).max(dim=2).values  # (E, V): largest j for i = k
    as_second = torch.where(pairs.will_intersect, slots[:, None], -1).max(dim=1).values  # (E, V): largest i for j = k
    push_first = torch.gather(pairs.translation, 2, as_first.clamp(min=0)[..., None, None].expand(-1, -1, 1, 2)).squeeze(2) / 2
    push_second = -torch.gather(pairs.translation, 1, as_second.clamp(min=0)[:, None, :, None].expand(-1, 1, -1, 2)).squeeze(1) / 2
    pushed = (as_first >= 0) | (as_second >= 0)
    impact = torch.where((as_first >= 0)[..., None], push_first, push_second)
    return state._replace(
        crashed=crashed,
        impact=torch.where(pushed[..., None], impact, state.impact),
        impact_pending=state.impact_pending | pushed,
    ), untested
