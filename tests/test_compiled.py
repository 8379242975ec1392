"""The torch.compile path gives the eager answers (float32 tolerance)."""

import pytest
import torch

import mmpc
from mmpc.scenes import synthetic_scenes
from mmpc.solver.execution import goal_padding
from tests.conftest import small_config


def test_compiled_matches_eager():
    # heading_target_deg and the back-offs: the clipped heading step and the scaled projections are
    # part of the compiled graph too
    config = small_config(num_steps=100, order=10, iterations=20, max_obstacles=10, heading_target_deg=6.0,
                          obstacle_backoff=0.03, acceleration_backoff=0.2)
    eager = mmpc.BatchOptimizer(config)
    compiled = mmpc.BatchOptimizer(config, compile=True)
    assert compiled.chunk == 10
    scene = synthetic_scenes(8, seed=3)[7]  # 7 obstacles, lane changes; one shape = one compile
    assert scene.problem.obstacles.shape[1] == 7
    assert scene.problem.goals.shape[:2] == (1, 8)  # solved as 16 goals, 8 of them padding
    for _ in range(2):  # the second call runs the cached graphs
        expected, result = eager(scene.problem), compiled(scene.problem)
        assert result.trajectories.x.shape == expected.trajectories.x.shape == (1, 8, 100)
        torch.testing.assert_close(result.trajectories.x, expected.trajectories.x, atol=1e-3, rtol=1e-5)
        torch.testing.assert_close(result.trajectories.psi, expected.trajectories.psi, atol=1e-4, rtol=1e-4)
        torch.testing.assert_close(result.coefficients, expected.coefficients, atol=1e-3, rtol=1e-4)
        torch.testing.assert_close(result.min_obstacle_distance, expected.min_obstacle_distance, atol=1e-4, rtol=1e-4)
        assert torch.equal(result.feasible, expected.feasible)
        assert torch.equal(result.status, expected.status)


def test_compiled_history_drops_the_padding_goals():
    config = small_config(iterations=3)  # one chunk of 3: a small graph
    eager, compiled = mmpc.BatchOptimizer(config), mmpc.BatchOptimizer(config, compile=True)
    scene = synthetic_scenes(2, seed=1, num_steps=config.num_steps)[1]
    problem = scene.problem._replace(goals=scene.problem.goals[:, :5])
    expected, result = eager(problem, history=True), compiled(problem, history=True)
    assert result.history.shape == expected.history.shape == (3, 1, 5, 3)
    torch.testing.assert_close(result.history, expected.history, atol=1e-3, rtol=1e-4)
    torch.testing.assert_close(result.trajectories.y, expected.trajectories.y, atol=1e-3, rtol=1e-5)


def test_goal_padding_fills_whole_vectors_only_where_cheap():
    assert goal_padding(1, 11, 4) == 5  # 16 float32 lanes
    assert goal_padding(1, 11, 8) == 5  # 8 float64 lanes: 16
    assert goal_padding(4, 11, 4) == 1  # 4 x 12 = 48
    assert goal_padding(1, 32, 4) == 0
    assert goal_padding(5, 11, 4) == 0  # 5 x 16 would add 25 elements a row: more than a vector
    assert goal_padding(64, 11, 4) == 0  # 704 = 44 vectors already


def test_compiled_solves_allow_more_recompiles_than_torchs_default(monkeypatch):
    """Each call layout recompiles the same functions (shared by every optimizer of a process):
    a proposer driver with its escalations, or several scenarios in one worker, pass torch's
    default limit of 8, where a fullgraph compile fails hard. The compiled path raises the limit
    for its own calls only."""
    from mmpc.solver.execution import RECOMPILE_LIMIT

    default = torch._dynamo.config.recompile_limit
    seen = []
    monkeypatch.setattr(mmpc.BatchOptimizer, "_solve_batch", lambda self, *args: seen.append(torch._dynamo.config.recompile_limit))
    scene = synthetic_scenes(1, seed=0)[0]
    mmpc.BatchOptimizer(compile=True)(scene.problem)
    mmpc.BatchOptimizer(compile=False)(scene.problem)
    assert seen == [RECOMPILE_LIMIT, default] and RECOMPILE_LIMIT > default
    assert torch._dynamo.config.recompile_limit == default  # restored after the call


def _goals_widened(problem, num_goals):
    """``problem`` with ``num_goals`` goals (its goals repeated): a call layout of its own."""
    repeats = -(-num_goals // problem.goals.shape[1])
    return problem._replace(goals=problem.goals.repeat(1, repeats, 1)[:, :num_goals])


def test_each_compiled_layout_gets_shape_specialised_kernels():
    """torch's default compiles a second shape with dynamic dims, whose CPU kernels ran up to 2x
    slower (a proposer's 50 x 6 tiles after an expert's 7 x 35 ones): every new layout compiles
    static iterations of its own, and a layout seen before compiles nothing."""
    from torch._dynamo.eval_frame import _debug_get_cache_entry_list

    from mmpc.solver import iterations

    def iterate_graphs() -> int:
        return len(_debug_get_cache_entry_list(iterations.iterate.__code__))

    config = small_config(iterations=2, heading_target_deg=7.5)  # a config no other test compiles
    compiled = mmpc.BatchOptimizer(config, compile=True)
    problem = synthetic_scenes(2, seed=1, num_steps=config.num_steps)[1].problem
    added = []
    for num_goals in (16, 32, 48, 16, 32):  # multiples of the 16 float32 lanes: no goal padding
        before = iterate_graphs()
        compiled(_goals_widened(problem, num_goals))
        added.append(iterate_graphs() - before)
    assert added == [1, 1, 1, 0, 0]  # dynamic dims would serve the third layout with the second's graph


def test_a_cold_and_a_warm_solve_of_one_shape_share_every_compiled_function():
    """The cold start is resumed from its iterates, so a warm solve (the schedule's last chunk, from
    earlier iterates) compiles nothing a cold solve of its shape did not: a warm-started run pays the
    cold schedule's compiles, not a second set."""
    from torch._dynamo.eval_frame import _debug_get_cache_entry_list

    from mmpc.solver import execution

    def graphs() -> int:
        return sum(len(_debug_get_cache_entry_list(function.__code__)) for function in execution.EAGER)

    config = small_config(iterations=20, heading_target_deg=7.25)  # two chunks of 10 cold, the last one warm
    compiled, eager = mmpc.BatchOptimizer(config, compile=True), mmpc.BatchOptimizer(config)
    problem = _goals_widened(synthetic_scenes(2, seed=1, num_steps=config.num_steps)[1].problem, 48)
    start = graphs()
    cold = compiled(problem)
    assert graphs() > start and compiled.last_compile_ms > 0.0  # the shape's first solve compiled
    before = graphs()
    result = compiled(problem, warm=cold.warm, warm_iterations=10)
    assert graphs() == before
    assert compiled.last_compile_ms == 0.0  # the same layout: not run untimed first
    expected = eager(problem, warm=cold.warm, warm_iterations=10)
    assert torch.equal(result.feasible, expected.feasible)
    torch.testing.assert_close(result.trajectories.x, expected.trajectories.x, atol=1e-3, rtol=1e-5)


def test_compiled_layouts_past_the_recompile_limit_solve_eagerly(monkeypatch, caplog):
    """A fullgraph compile fails hard at torch's recompile limit: a layout past it solves eagerly
    (the same answers to float32 rounding), with one warning."""
    import logging

    from mmpc.solver import execution

    config = small_config(iterations=2, heading_target_deg=8.5)
    compiled, eager = mmpc.BatchOptimizer(config, compile=True), mmpc.BatchOptimizer(config)
    problem = synthetic_scenes(2, seed=1, num_steps=config.num_steps)[1].problem
    compiled(_goals_widened(problem, 16))  # every compiled function now holds at least one layout
    monkeypatch.setattr(execution, "RECOMPILE_LIMIT", 1)
    wide = _goals_widened(problem, 32)
    with caplog.at_level(logging.WARNING, logger="mmpc.solver"):
        result = compiled(wide)
        compiled(wide)
    assert caplog.text.count("solve eagerly") == 1
    assert compiled.last_compile_ms == 0.0
    expected = eager(wide)
    torch.testing.assert_close(result.trajectories.x, expected.trajectories.x, atol=1e-3, rtol=1e-5)
    assert torch.equal(result.feasible, expected.feasible)


def test_a_layout_solves_eagerly_until_its_estimated_eager_time_is_spent(monkeypatch):
    """compile_after: each call layout runs eagerly until the eager seconds estimated from its calls
    (not clocks: the same episodes on any machine load) reach it, then compiled (warm-up + timed)."""
    from mmpc.solver.execution import EAGER_SECONDS

    runs = []

    class Counting(mmpc.BatchOptimizer):
        def _run(self, prepared, history):
            runs.append((prepared.num_goals - prepared.padding, prepared.compiled))
            return super()._run(prepared, history)

    optimizer = Counting()
    optimizer.compiled = True  # the deferral only reads the flag; eager functions keep the test fast
    scene = synthetic_scenes(1, seed=3)[0]
    goals = scene.problem.goals.shape[1]
    fixed, per_element = EAGER_SECONDS[False]
    optimizer.compile_after = 2.5 * (fixed + per_element * goals)  # three eager calls reach it
    for _ in range(5):
        optimizer(scene.problem)
    assert runs == [(goals, False)] * 3 + [(goals, True)] * 3  # then the compile's warm-up run and two solves
    fewer = scene.problem._replace(goals=scene.problem.goals[:, :2])  # another layout starts eagerly again
    optimizer(fewer)
    assert runs[-1] == (2, False)


def test_compile_after_defaults_to_deferring_only_for_auto(monkeypatch):
    from mmpc.solver.execution import AUTO_COMPILE_AFTER_S, COMPILE_ENV

    assert mmpc.BatchOptimizer(compile=True).compile_after == 0.0
    monkeypatch.delenv(COMPILE_ENV)
    assert mmpc.BatchOptimizer(compile="auto").compile_after == AUTO_COMPILE_AFTER_S
    monkeypatch.setenv(COMPILE_ENV, "1")  # --compile on: at the first call
    assert mmpc.BatchOptimizer(compile="auto").compile_after == 0.0
    for bad in (-1.0, True, "soon", float("nan")):
        with pytest.raises(ValueError, match="compile_after"):
            mmpc.BatchOptimizer(compile_after=bad)
