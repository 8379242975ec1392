"""The obstacle shape (:mod:`mmpc.obstacles.shape`): covering a turned car, the normalised distance
and clearance, the nearest obstacles, and the optimizer's per-obstacle path."""

import math

import pytest
import torch

import mmpc
from mmpc.mpc import MPC, MPCConfig
from mmpc.obstacles.shape import (
    covering_semi_axes, ellipse_coverage, ellipse_distance_squared, longest_semi_axes, nearest_obstacles, obstacle_semi_axes,
    offset_distance, offset_distance_squared, smallest_distance, squared_obstacle_distance,
)
from mmpc.scenes import synthetic_scenes
from tests.conftest import small_config


@pytest.mark.parametrize("band", [8.0, 13.0])
def test_covering_axes_keep_the_configured_margin_at_every_heading(band):
    semi_axes = (8.0, 3.3)
    degrees = torch.tensor([0.0, 3.0, 10.0, 17.0, 27.0, -27.0], dtype=torch.float64)
    axes = covering_semi_axes(torch.deg2rad(degrees), semi_axes, band)
    assert axes[0].tolist() == list(semi_axes)  # along the road: the configured ellipse exactly
    assert (axes[:, 0] == 8.0).all() and (axes[1:4, 1] > 3.3).all()
    assert axes[4, 1] == axes[5, 1]  # symmetric in the heading
    for degree, (a, b) in zip(degrees.tolist(), axes.tolist()):
        covered = max(ellipse_coverage((a, b), e, degree) for e in (-band, 0.0, band))
        assert covered < 0.95, degree  # covers the turned car, with the configured ellipse's room to spare
    uncovered = max(ellipse_coverage(semi_axes, e, 17.0) for e in (-band, band))
    assert uncovered > 1.0  # what the fixed ellipse misses


def test_ellipse_distance_takes_one_or_many_ellipses():
    points = torch.tensor([[4.0, 3.0], [0.0, 6.0]])
    assert ellipse_distance_squared(points, torch.zeros(2), (8.0, 3.0)).tolist() == [1.25, 4.0]
    axes = torch.tensor([[8.0, 3.0], [8.0, 6.0]])
    assert ellipse_distance_squared(points, torch.zeros(2), axes).tolist() == [1.25, 1.0]



def test_one_offset_in_floats_measures_as_the_tensors_do():
    for dx, dy in [(4.0, 3.0), (-7.3, 1.1), (0.0, -6.0)]:
        squared = offset_distance_squared(dx, dy, (8.0, 3.0))
        point = torch.tensor([dx, dy], dtype=torch.float64)
        tensor = ellipse_distance_squared(point, torch.zeros(2, dtype=torch.float64), (8.0, 3.0))
        assert squared == float(tensor)
        assert offset_distance(dx, dy, (8.0, 3.0)) == pytest.approx(math.sqrt(squared), rel=1e-15)


def test_smallest_distance_counts_only_the_present_entries():
    squared = torch.tensor([[[4.0, 0.25], [9.0, 16.0]], [[1.0, 0.0], [2.25, 1.0]]])  # (2, M=2, N=2)
    present = torch.tensor([[False, True], [True, True]])[:, :, None]
    assert smallest_distance(squared, present, (1, 2)).tolist() == [3.0, 0.0]
    assert smallest_distance(squared, None, -1).tolist() == [[0.5, 3.0], [0.0, 1.0]]
    assert smallest_distance(squared, torch.zeros(2, 2, 1, dtype=torch.bool), (1, 2)).tolist() == [math.inf] * 2
    assert smallest_distance(squared[:, :0], None, (1, 2)).tolist() == [math.inf] * 2  # no obstacle slot


def test_a_stop_goal_rests_behind_the_longest_present_ellipse():
    axes = torch.tensor([[[9.0, 3.0], [12.0, 4.0]], [[7.0, 3.0], [11.0, 3.0]]])
    mask = torch.tensor([[True, True], [True, False]])
    longest, b = longest_semi_axes(axes, mask, (8.0, 3.0))
    assert longest.tolist() == [[12.0], [8.0]] and b == 3.0  # never shorter than the configured a
    assert longest_semi_axes(None, mask, (8.0, 3.0)) == (8.0, 3.0)


def test_obstacle_semi_axes_by_shape_name():
    states = torch.tensor([[[0.0, 0.0, 10.0, 3.0], [0.0, 0.0, 0.5, 0.4]]])
    assert obstacle_semi_axes(states, "fixed", (8.0, 3.3), 13.0) is None
    axes = obstacle_semi_axes(states, "heading", (8.0, 3.3), 13.0)
    assert axes[0, 0, 1] > 3.3 and axes[0, 1].tolist() == pytest.approx([8.0, 3.3])  # slow: heading 0
    with pytest.raises(ValueError, match="`shape` must be one of"):
        obstacle_semi_axes(states, "rectangle", (8.0, 3.3), 13.0)


def test_nearest_obstacles_ignores_far_behind_and_pads():
    ego = mmpc.ego_state(100.0, 8.0, 0.0, 15.0)
    vehicles = torch.tensor([[[60.0, 8.0, 10.0, 0.0], [130.0, 8.0, 10.0, 0.0], [105.0, 4.0, 10.0, 0.0]]])
    states, mask = nearest_obstacles(ego, vehicles, None, 4, (8.0, 3.0), ignore_behind=20.0)
    assert states.shape == (1, 4, 4) and mask.tolist() == [[True, True, False, False]]
    assert states[0, 0, 0] == 105.0 and states[0, 1, 0] == 130.0  # nearest first


def test_nearest_obstacles_rank_a_closing_car_ahead_by_its_closest_approach():
    # the high-speed scene (seed 12 with 24 m/s goals): a 7 m/s car 46 m ahead in the ego's lane
    # (5.75 now at a = 8 m) against a car a lane over just behind (1.83) and one beside two lanes
    # over (2.67), both falling back
    ego = mmpc.ego_state(100.0, 20.0, 0.0, 23.5)
    ahead, behind, beside = [146.0, 20.0, 7.0, 0.0], [90.0, 16.0, 7.5, 0.0], [101.0, 12.0, 9.0, 0.0]
    vehicles = torch.tensor([[beside, behind, ahead]])
    now, _ = nearest_obstacles(ego, vehicles, None, 2, (8.0, 3.0), ignore_behind=20.0)
    assert now[0].tolist() == [behind, beside]  # today's distance: the car ahead is left out
    soon, _ = nearest_obstacles(ego, vehicles, None, 2, (8.0, 3.0), ignore_behind=20.0, lookahead=3.0)
    assert soon[0].tolist() == [ahead, behind]  # met within 2.8 s: first; the others keep their distance now
    shorter, _ = nearest_obstacles(ego, vehicles, None, 2, (8.0, 3.0), ignore_behind=20.0, lookahead=1.0)
    assert shorter[0].tolist() == [behind, beside]  # 30 m off after 1 s: still last
    # a car overtaking fast in the ego's lane from 15 m behind comes before the one beside
    overtaking = [85.0, 20.0, 35.0, 0.0]
    states, _ = nearest_obstacles(ego, torch.tensor([[beside, overtaking]]), None, 1, (8.0, 3.0),
                                  ignore_behind=20.0, lookahead=3.0)
    assert states[0, 0].tolist() == overtaking

def _scene():
    scene = synthetic_scenes(3, seed=5)[2]
    assert scene.problem.obstacles.shape[1] >= 2
    return scene.problem


def test_configured_axes_per_obstacle_solve_as_the_shared_ones():
    optimizer = mmpc.BatchOptimizer(small_config(), dtype=torch.float64)
    problem = _scene()
    problem = problem._replace(obstacles=problem.obstacles[:, :, : optimizer.config.num_steps].double(),
                               ego=problem.ego.double(), goals=problem.goals.double())
    shared = optimizer(problem)
    axes = problem.obstacles.new_tensor(optimizer.config.ellipse).expand(*problem.obstacles.shape[:2], 2)
    each = optimizer(problem._replace(obstacle_axes=axes))
    torch.testing.assert_close(each.trajectories.x, shared.trajectories.x, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(each.min_obstacle_distance, shared.min_obstacle_distance, atol=1e-9, rtol=1e-9)
    assert torch.equal(each.status, shared.status)


def test_a_wider_obstacle_is_kept_out_of_and_checked_with_its_own_axes():
    optimizer = mmpc.BatchOptimizer(dtype=torch.float64)
    ego = mmpc.ego_state(0.0, 8.0, 0.0, 14.0, dtype=torch.float64)
    goals = torch.tensor([[[120.0, 4.0], [120.0, 12.0]]], dtype=torch.float64)
    cars = torch.tensor([[[25.0, 8.0, 10.0, 0.0], [60.0, 0.0, 10.0, 0.0]]], dtype=torch.float64)
    obstacles = mmpc.predict_constant_velocity(cars, optimizer.times)
    axes = torch.tensor([[[5.6, 4.5], [5.6, 3.0]]], dtype=torch.float64)
    result = optimizer(mmpc.ProblemBatch(ego, goals, obstacles, None, axes))
    distance = squared_obstacle_distance(result.trajectories, obstacles, axes).sqrt().amin(dim=(-1, -2))  # (E, G)
    torch.testing.assert_close(result.min_obstacle_distance, distance)
    assert bool(result.feasible.all())  # both swerves clear the 4.5 m ellipse
    shared = optimizer(mmpc.ProblemBatch(ego, goals, obstacles))
    lateral_gap = lambda r: (r.trajectories.y - 8.0).abs()[..., 20:30].amax(dim=-1)  # passing the first car
    assert bool((lateral_gap(result) > lateral_gap(shared)).all())


def test_obstacle_axes_are_checked():
    optimizer = mmpc.BatchOptimizer(small_config())
    problem = _scene()
    problem = problem._replace(obstacles=problem.obstacles[:, :, : optimizer.config.num_steps])
    num_slots = problem.obstacles.shape[1]
    with pytest.raises(ValueError, match=r"`obstacle_axes` must have shape \(1, \d+, 2\)"):
        optimizer(problem._replace(obstacle_axes=torch.ones(1, num_slots, 3)))
    bad = torch.ones(1, num_slots, 2)
    bad[0, 0, 1] = -1.0
    with pytest.raises(ValueError, match="finite and > 0"):
        optimizer(problem._replace(obstacle_axes=bad))
    with pytest.raises(TypeError, match="floating"):
        optimizer(problem._replace(obstacle_axes=torch.ones(1, num_slots, 2, dtype=torch.int64)))
    # an absent slot may hold anything
    mask = torch.ones(1, num_slots, dtype=torch.bool)
    mask[0, 0] = False
    nan = torch.ones(1, num_slots, 2)
    nan[0, 0] = float("nan")
    assert optimizer(problem._replace(obstacle_mask=mask, obstacle_axes=nan)).status.shape[0] == 1


def test_compiled_per_obstacle_axes_match_eager():
    config = small_config(num_steps=100, order=10, iterations=3, max_obstacles=10, obstacle_backoff=0.05)  # one small graph
    eager, compiled = mmpc.BatchOptimizer(config), mmpc.BatchOptimizer(config, compile=True)
    problem = synthetic_scenes(8, seed=3)[7].problem
    axes = torch.tensor([3.0, 3.5, 4.0, 3.2, 3.8, 3.1, 3.6])[None, :, None] * torch.tensor([8.0 / 3.0, 1.0])
    problem = problem._replace(obstacle_axes=axes)
    expected, result = eager(problem), compiled(problem)
    torch.testing.assert_close(result.trajectories.y, expected.trajectories.y, atol=1e-3, rtol=1e-5)
    torch.testing.assert_close(result.min_obstacle_distance, expected.min_obstacle_distance, atol=1e-4, rtol=1e-4)
    assert torch.equal(result.status, expected.status)


def _mpc(max_obstacles: int = 4, **config) -> MPC:
    optimizer = mmpc.BatchOptimizer(small_config(max_obstacles=max_obstacles))
    return MPC(optimizer, mmpc.CruiseGoals(horizon=optimizer.config.horizon), mmpc.CruiseCost(), mmpc.Road(),
               MPCConfig(**{"num_obstacles": 4, **config}))


def test_mpc_obstacle_axes_by_shape():
    turned = math.radians(15.0)
    states = torch.tensor([[[10.0, 4.0, 10.0 * math.cos(turned), 10.0 * math.sin(turned)],  # slower, turning
                            [30.0, 8.0, 25.0, 0.0],  # faster, straight
                            [20.0, 12.0, 0.5, 0.4]]])  # nearly stopped: its velocity says little of its heading
    assert _mpc().obstacle_axes(states) is None  # the optimizer's own ellipse
    a, b = _mpc().ellipse
    heading = _mpc(obstacle_shape="heading").obstacle_axes(states)[0]
    assert heading[0, 1] > b
    torch.testing.assert_close(heading[1:], torch.tensor([[a, b], [a, b]]))
    with pytest.raises(ValueError, match="obstacle_shape"):
        MPCConfig(obstacle_shape="turned")


def test_mpc_plans_around_the_wider_ellipse_it_builds():
    mpc = _mpc(obstacle_shape="heading")
    ego = mmpc.ego_state(0.0, 8.0, 0.0, 14.0)
    vehicles = torch.tensor([[[30.0, 8.0, 8.0, 0.0], [20.0, 4.0, 8.0, 1.5]]])
    plan = mpc.plan(ego, vehicles)
    assert plan.problem.obstacle_axes is not None
    distance = squared_obstacle_distance(plan.result.trajectories, plan.problem.obstacles, plan.problem.obstacle_axes)
    chosen = distance[0, int(plan.selection.index[0])]
    if bool(plan.selection.feasible[0]):
        assert float(chosen.sqrt().min()) >= 1.0 - mpc.optimizer.config.obstacle_tolerance


def test_plan_refuses_tensors_on_another_device():
    from mmpc.scenario import PAPER_SCHEDULE, build_mpc, load_scenario

    mpc = build_mpc(load_scenario("cruise", {"optimizer.iterations": 2, **PAPER_SCHEDULE}), compile=False)
    with pytest.raises(ValueError, match="`ego` is on meta but the MPC's optimizer is on cpu"):
        mpc.plan(torch.zeros(1, 6, device="meta"), torch.zeros(1, 0, 4))
    with pytest.raises(ValueError, match="`vehicles` is on meta"):
        mpc.plan(torch.zeros(1, 6), torch.zeros(1, 1, 4, device="meta"))
    with pytest.raises(ValueError, match="`stop_lanes` must be an int or null"):
        MPCConfig(stop_lanes=1.5)
