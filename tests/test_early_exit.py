"""Early exit (OptimizerConfig.exit_checks): an element feasible at a check keeps that iterate,
the others run on from their iterates; SolveResult.replace_elements joins the stretches."""

import dataclasses

import pytest
import torch

import mmpc
from bench_solver import benchmark_problem
from mmpc.config import ConfigError

CHECKS = (10, 30)


@pytest.fixture(scope="module")
def problem() -> mmpc.ProblemBatch:
    """Two problems of 24 goals across six lanes, 6 obstacle slots (one absent in the second)."""
    first = benchmark_problem(24, 6, mmpc.BatchOptimizer().times)
    shifted = first.obstacles + torch.tensor([10.0, 0.0])
    mask = torch.tensor([[True] * 6, [True] * 5 + [False]])
    return mmpc.ProblemBatch(torch.cat([first.ego, first.ego]), torch.cat([first.goals, first.goals.flip(1)]),
                             torch.cat([first.obstacles, shifted]), mask)


@pytest.fixture(scope="module")
def solves(problem):
    config = mmpc.OptimizerConfig()
    early = mmpc.BatchOptimizer(dataclasses.replace(config, exit_checks=CHECKS))
    return {
        "full": mmpc.BatchOptimizer(config)(problem),
        "early": early(problem),
        "history": early(problem, history=True),
        **{k: mmpc.BatchOptimizer(dataclasses.replace(config, iterations=k))(problem) for k in CHECKS},
    }


def test_an_element_feasible_at_a_check_stops_there_with_that_iterate(solves):
    early = solves["early"]
    iterations = early.iterations
    assert set(iterations.unique().tolist()) <= {*CHECKS, 100}
    assert bool((iterations < 100).any()) and bool((iterations == 100).any())  # the scenes exercise both
    for k in CHECKS:
        stopped = iterations == k
        assert bool(stopped.any()) and bool(early.feasible[stopped].all())
        # The schedule's first k iterations are those of a k-iteration solve: the same iterate up to
        # the first check; after a resume (its scaled residual recomputed from the iterates) close to it.
        tolerance = dict(atol=1e-5, rtol=0) if k == CHECKS[0] else dict(atol=0.05, rtol=0)
        torch.testing.assert_close(early.trajectories.x[stopped], solves[k].trajectories.x[stopped], **tolerance)
        torch.testing.assert_close(early.trajectories.y[stopped], solves[k].trajectories.y[stopped], **tolerance)
    first = iterations == CHECKS[0]
    assert torch.equal(first, solves[CHECKS[0]].feasible)  # every element feasible at the first check stops
    # What drivers report per environment (Decision.iterations): the mean over its goals.
    assert torch.equal(early.problem_iterations(), iterations.double().mean(dim=1).round().long())
    assert bool((early.problem_iterations() < 100).all())


def test_the_elements_that_run_on_end_as_the_whole_schedule_does(solves):
    early, full = solves["early"], solves["full"]
    ran_on = early.iterations == 100
    assert not bool(solves[CHECKS[-1]].feasible[ran_on].any())  # none was feasible at a check
    # Resumed from their iterates (the scaled residual recomputed) rather than uninterrupted: the same verdicts.
    agree = (early.feasible[ran_on] == full.feasible[ran_on]).float().mean()
    assert agree >= 0.9
    assert early.feasible.sum() >= full.feasible.sum() - 1


def test_the_history_of_an_early_exit_stops_at_each_elements_last_iteration(solves):
    early, history = solves["early"], solves["history"]
    assert torch.equal(history.feasible, early.feasible)
    assert history.history.shape == (100, *early.feasible.shape, 3)
    ran = torch.arange(100)[:, None, None] < early.iterations[None]  # (I, E, G)
    assert bool(history.history[ran].isfinite().all())
    assert bool(history.history[~ran].isnan().all())


def test_a_compiled_layout_early_exit_matches_the_eager_one(problem, solves):
    tiled = mmpc.BatchOptimizer(mmpc.OptimizerConfig(exit_checks=CHECKS), tile_size=8)
    tiled.compiled = True  # the padding and tiling read the flag; eager functions keep the test fast
    result = tiled(problem)
    assert torch.equal(result.iterations, solves["early"].iterations)
    assert torch.equal(result.feasible, solves["early"].feasible)
    torch.testing.assert_close(result.trajectories.x, solves["early"].trajectories.x, atol=1e-3, rtol=0)


def test_early_exit_applies_to_the_problems_a_warm_solve_restarts_cold(problem, solves):
    optimizer = mmpc.BatchOptimizer(mmpc.OptimizerConfig(exit_checks=CHECKS))
    warm = solves["early"].warm
    unfinished = warm._replace(position=warm.position.clone())
    unfinished.position[0] = float("nan")  # problem 0 is new to the batch: solved cold
    result = optimizer(problem, warm=unfinished, warm_iterations=10)
    assert torch.equal(result.iterations[0], solves["early"].iterations[0])
    assert torch.equal(result.feasible[0], solves["early"].feasible[0])


@pytest.mark.parametrize("checks", [(0,), (30, 10), (10, 10), (100,), (150,)])
def test_exit_checks_are_validated(checks):
    with pytest.raises(ConfigError, match="exit_checks"):
        mmpc.OptimizerConfig(exit_checks=checks)


def test_replace_elements_takes_the_parts_elements_and_refuses_other_shapes(problem, solves):
    full = solves["full"]
    goals = full.feasible.shape[1]
    elements = torch.tensor([1, goals + 4])  # flat (E, G) indices: (0, 1) and (1, 4)
    rows, columns = elements // goals, elements % goals
    one_goal_each = mmpc.ProblemBatch(problem.ego[rows], problem.goals[rows, columns].unsqueeze(1),
                                      problem.obstacles[rows], problem.obstacle_mask[rows])
    part = mmpc.BatchOptimizer(mmpc.OptimizerConfig(iterations=10))(one_goal_each, history=True)
    joined = full.replace_elements(part, elements)
    for source, (row, column) in enumerate(zip(rows.tolist(), columns.tolist())):
        assert torch.equal(joined.trajectories.x[row, column], part.trajectories.x[source, 0])
        assert torch.equal(joined.warm.position[row, column], part.warm.position[source, 0])
        assert joined.iterations[row, column] == 10
    kept = torch.ones(full.feasible.numel(), dtype=torch.bool)
    kept[elements] = False
    assert torch.equal(joined.status.flatten()[kept], full.status.flatten()[kept])
    with pytest.raises(ValueError, match="one goal per element"):
        full.replace_elements(solves[CHECKS[0]], elements)


def test_replace_elements_keeps_the_history_where_the_part_did_not_run(solves):
    early = solves["history"]
    part = early.head(1, 1)
    later = part.history.clone()
    later[:50] = float("nan")  # the part ran iterations 50-99 only
    joined = early.replace_elements(part._replace(history=later), torch.tensor([0]))
    torch.testing.assert_close(joined.history[:50, 0, 0], early.history[:50, 0, 0], equal_nan=True)
    torch.testing.assert_close(joined.history[50:, 0, 0], later[50:, 0, 0], equal_nan=True)


def test_with_back_offs_an_element_stops_only_inside_the_sets_the_iterations_aim_at(problem):
    """A plan feasible at a check may still hug the true ellipses; with back-offs it runs on until
    it also clears the larger ellipses and the smaller disc (up to the tolerances)."""
    config = mmpc.OptimizerConfig(obstacle_backoff=0.05, acceleration_backoff=0.16)
    check = 30
    early = mmpc.BatchOptimizer(dataclasses.replace(config, exit_checks=(check,)))(problem)
    at_check = mmpc.BatchOptimizer(dataclasses.replace(config, iterations=check))(problem)  # the same iterate
    settled = (at_check.feasible & (at_check.min_obstacle_distance >= 1.05 - config.obstacle_tolerance)
               & (at_check.max_acceleration <= config.a_max - 0.16 + config.acceleration_tolerance))
    assert bool(settled.any()) and bool((at_check.feasible & ~settled).any())  # the problem exercises both
    assert torch.equal(early.iterations == check, settled)
