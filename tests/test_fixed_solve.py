"""BatchOptimizer(fixed_shapes=True): a solve that reads nothing on the host (shapes known from the
input shapes) gives the checked solve's answers; its warm start re-solves at most ``cold_capacity``
problems cold; it traces as one graph."""

import pytest
import torch

import mmpc
from mmpc.result import Status
from mmpc.scenes import synthetic_scenes
from tests.conftest import small_config

SLOTS = 3


@pytest.fixture(scope="module")
def problem() -> mmpc.ProblemBatch:
    """Four problems of 5 goals, 3 obstacle slots holding 2, 3, 0 and 3 obstacles (float64)."""
    config = small_config(iterations=30, max_obstacles=SLOTS)
    scenes = synthetic_scenes(11, seed=4, num_steps=config.num_steps, dtype=torch.float64)
    egos, goals, obstacles, masks = [], [], [], []
    for scene, count in zip((scenes[2], scenes[3], scenes[4], scenes[3]), (2, 3, 0, 3)):
        padded = torch.zeros(1, SLOTS, config.num_steps, 2, dtype=torch.float64)
        present = min(count, scene.problem.obstacles.shape[1])
        padded[:, :present] = scene.problem.obstacles[:, :present]
        egos.append(scene.problem.ego)
        goals.append(scene.problem.goals[:, :5])
        obstacles.append(padded)
        masks.append(torch.arange(SLOTS)[None] < present)
    return mmpc.ProblemBatch(torch.cat(egos), torch.cat(goals), torch.cat(obstacles), torch.cat(masks))


@pytest.fixture(scope="module")
def optimizer() -> mmpc.BatchOptimizer:
    return mmpc.BatchOptimizer(small_config(iterations=30, max_obstacles=SLOTS), dtype=torch.float64)


def _assert_same_answers(result: mmpc.SolveResult, expected: mmpc.SolveResult, rows=slice(None)) -> None:
    assert torch.equal(result.status[rows], expected.status[rows])
    for name in ("x", "y", "psi", "v"):
        torch.testing.assert_close(getattr(result.trajectories, name)[rows], getattr(expected.trajectories, name)[rows])
    torch.testing.assert_close(result.warm.position[rows], expected.warm.position[rows])


def test_a_cold_fixed_shape_solve_gives_the_checked_solves_answers(optimizer, problem):
    expected = optimizer(problem)
    assert expected.feasible.any() and not expected.feasible.all()  # both outcomes compared
    _assert_same_answers(optimizer(problem, fixed_shapes=True), expected)


def _warm_start(optimizer, problem):
    """The iterates of a cold solve, problem 1's made NaN (it restarts) and problem 3's taken from
    problem 2, which has no obstacle (its warm solve may find no feasible goal)."""
    warm = optimizer(problem).warm
    rows = torch.tensor([0, 1, 2, 2])
    warm = warm.take(rows)
    return warm._replace(position=torch.where(torch.arange(4)[:, None, None, None] == 1, float("nan"), warm.position))


def test_a_warm_fixed_shape_solve_solves_cold_what_the_checked_solve_does(optimizer, problem):
    warm = _warm_start(optimizer, problem)
    expected = optimizer(problem, warm=warm, warm_iterations=5)
    result = optimizer(problem, warm=warm, warm_iterations=5, fixed_shapes=True)
    _assert_same_answers(result, expected)
    cold_again = expected.iterations[:, 0] == 30 + 5
    restarted = expected.iterations[:, 0] == 30
    assert restarted.tolist() == [False, True, False, False]
    # The same problems solved cold: the restarting one also ran the warm iterations from a standstill.
    assert torch.equal(result.iterations[:, 0] == 35, cold_again | restarted)
    assert torch.equal(result.iterations[:, 0] == 5, ~(cold_again | restarted))


def test_problems_past_the_cold_capacity_keep_their_warm_answer(optimizer, problem):
    warm = _warm_start(optimizer, problem)
    warm_only = optimizer(problem, warm=warm, warm_iterations=5, fixed_shapes=True, cold_capacity=0)
    assert warm_only.iterations.unique().tolist() == [5]
    assert not warm_only.feasible[1].any()  # the restarting problem, 5 iterations from a standstill
    one = optimizer(problem, warm=warm, warm_iterations=5, fixed_shapes=True, cold_capacity=1)
    every = optimizer(problem, warm=warm, warm_iterations=5, fixed_shapes=True)
    _assert_same_answers(one, every, rows=slice(0, 2))  # problem 1: the first to solve cold
    _assert_same_answers(one, warm_only, rows=slice(2, 4))
    for bad in (-1, 5, 1.5, True):
        with pytest.raises(ValueError, match="cold_capacity"):
            optimizer(problem, warm=warm, warm_iterations=5, fixed_shapes=True, cold_capacity=bad)
    with pytest.raises(ValueError, match="cold_capacity"):
        optimizer(problem, cold_capacity=1)


def test_a_problem_with_nan_comes_out_numerical_and_leaves_the_others_alone(optimizer, problem):
    broken = problem._replace(ego=problem.ego.clone())
    broken.ego[3, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        optimizer(broken)  # checked
    result = optimizer(broken, fixed_shapes=True)
    assert (result.status[3] & Status.NUMERICAL).all() and not result.feasible[3].any()
    _assert_same_answers(result, optimizer(problem), rows=slice(0, 3))


def test_fixed_shapes_refuse_early_exits():
    exiting = mmpc.BatchOptimizer(small_config(iterations=30, exit_checks=(10,)))
    scene = synthetic_scenes(1, seed=4, num_steps=exiting.config.num_steps)[0].problem
    with pytest.raises(ValueError, match="exit_checks"):
        exiting(scene, fixed_shapes=True)
    with pytest.raises(TypeError, match="fixed_shapes"):
        exiting(scene, fixed_shapes="yes")


def test_a_warm_fixed_shape_solve_traces_as_one_graph(optimizer, problem):
    warm = _warm_start(optimizer, problem)

    def solve(problem, warm):
        return optimizer(problem, warm=warm, warm_iterations=5, fixed_shapes=True, cold_capacity=2)

    explained = torch._dynamo.explain(solve)(problem, warm)
    assert (explained.graph_count, explained.graph_break_count) == (1, 0), explained.break_reasons

