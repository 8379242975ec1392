"""Gradients flow from every output to the ego state, goals and obstacles, on every path."""

import logging
import re

import pytest
import torch
from torch.autograd.gradcheck import GradcheckError

import mmpc
from mmpc.solver.execution import kernel_compiler_found
from tests.conftest import small_config

#: Every float tensor a solve returns (``history`` requested), in the order gradcheck numbers them.
FIELDS = ("x", "y", "psi", "v", "xdot", "ydot", "xddot", "yddot", "psidot")
RESULTS = (
    "coefficients",
    "residual_obstacle",
    "residual_acceleration",
    "residual_nonholonomic",
    "min_obstacle_distance",
    "max_heading_deviation",
    "max_acceleration",
    "max_nonholonomic_error",
    "history",
)
OUTPUTS = FIELDS + RESULTS


def _outputs(result: mmpc.SolveResult) -> tuple[torch.Tensor, ...]:
    return tuple(getattr(result.trajectories, name) for name in FIELDS) + tuple(getattr(result, n) for n in RESULTS)


def _problem(case: str, times: torch.Tensor, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(ego, goals, obstacles) of one problem, two goals, away from the kinks of clamp / max / min."""
    ego = mmpc.ego_state(0.0, 4.0, 0.01, 12.0, 0.2, 0.005, dtype=dtype)
    if case == "feasible":  # a car two lanes over: obstacle and acceleration residuals exactly 0
        goals = torch.tensor([[[80.0, 4.0], [85.0, 6.0]]], dtype=dtype)
        states = torch.tensor([[[30.0, 12.0, 10.0, 0.0]]], dtype=dtype)
    else:  # the straight path runs into the first car: the obstacle step is active
        goals = torch.tensor([[[95.0, 4.0], [100.0, 8.0]]], dtype=dtype)
        states = torch.tensor([[[25.0, 5.0, 9.0, 0.0], [60.0, 8.5, 7.0, 0.0]]], dtype=dtype)
    return ego, goals, mmpc.predict_constant_velocity(states, times)


@pytest.mark.parametrize("case", ["feasible", "obstacle_active"])
def test_gradcheck_every_output(case, one_thread):
    opt = mmpc.BatchOptimizer(small_config(num_steps=12, order=6, iterations=6, max_obstacles=2), dtype=torch.float64)
    inputs = _problem(case, opt.times, torch.float64)
    result = opt(mmpc.ProblemBatch(*inputs))
    if case == "feasible":
        assert bool(result.feasible.all())
        assert (result.residual_obstacle == 0).all() and (result.residual_acceleration == 0).all()
    else:
        assert (result.residual_obstacle > 0).any() and (result.min_obstacle_distance < 1).any()

    def solve(ego, goals, obstacles):
        return _outputs(opt(mmpc.ProblemBatch(ego, goals, obstacles), history=True))

    inputs = tuple(t.clone().requires_grad_(True) for t in inputs)
    try:
        torch.autograd.gradcheck(solve, inputs, eps=1e-6, atol=1e-5, rtol=1e-3)
    except GradcheckError as error:
        index = re.search(r"output (\d+)", str(error))
        name = OUTPUTS[int(index.group(1))] if index else "?"
        pytest.fail(f"gradcheck of {name} (inputs ego, goals, obstacles): {error}")


def test_gradients_are_finite_where_every_norm_is_zero():
    # Standing at the goal, inside a static car: trajectories at rest, zero norms and distances.
    config = small_config(num_steps=12, order=6, iterations=6, max_obstacles=2)
    opt = mmpc.BatchOptimizer(config, dtype=torch.float64)
    ego = mmpc.ego_state(10.0, 4.0, 0.0, 0.0, dtype=torch.float64).requires_grad_(True)
    goals = torch.tensor([[[10.0, 4.0]]], dtype=torch.float64, requires_grad=True)
    obstacles = torch.tensor([10.0, 4.0], dtype=torch.float64).expand(1, 1, config.num_steps, 2).clone()
    obstacles.requires_grad_(True)
    result = opt(mmpc.ProblemBatch(ego, goals, obstacles), history=True)
    assert result.status[0, 0] & mmpc.Status.START_IN_COLLISION
    for name, output in zip(OUTPUTS, _outputs(result)):
        gradients = torch.autograd.grad(output.sum(), (ego, goals, obstacles), retain_graph=True)
        assert all(bool(g.isfinite().all()) for g in gradients), name


def _loss_gradients(opt: mmpc.BatchOptimizer, inputs) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Every output (history too) and the gradients of their sum w.r.t. (ego, goals, obstacles)."""
    inputs = tuple(t.clone().requires_grad_(True) for t in inputs)
    outputs = _outputs(opt(mmpc.ProblemBatch(*inputs), history=True))
    gradients = torch.autograd.grad(sum(o.sum() for o in outputs), inputs)
    return [o.detach() for o in outputs], list(gradients)


def test_compiled_backward_is_finite_and_matches_eager(caplog):
    # Inputs that require grad are solved eagerly: nothing is compiled here.
    config = small_config(num_steps=12, order=6, iterations=6, max_obstacles=2)
    eager, compiled = mmpc.BatchOptimizer(config), mmpc.BatchOptimizer(config, compile=True)
    inputs = _problem("obstacle_active", eager.times, torch.float32)
    expected_outputs, expected = _loss_gradients(eager, inputs)
    with caplog.at_level(logging.INFO, logger="mmpc.solver"):
        for _ in range(2):
            outputs, gradients = _loss_gradients(compiled, inputs)
            assert all(bool(g.isfinite().all()) for g in gradients)
            torch.testing.assert_close(gradients, expected, rtol=1e-3, atol=1e-4)
            torch.testing.assert_close(outputs, expected_outputs)
    assert sum("require grad" in record.getMessage() for record in caplog.records) == 1
    assert compiled.last_compile_ms == 0.0


@pytest.mark.skipif(not kernel_compiler_found(on_cpu=True), reason="inductor's CPU kernels need a C++ compiler")
def test_compiled_solve_then_backward_gives_the_compiled_values():
    # A compiled solve without grad, then the same problem with grad (eager): float32 rounding apart.
    config = small_config(num_steps=12, order=6, iterations=6, max_obstacles=2)
    compiled = mmpc.BatchOptimizer(config, compile=True)
    inputs = _problem("obstacle_active", compiled.times, torch.float32)
    with torch.no_grad():
        reference = _outputs(compiled(mmpc.ProblemBatch(*inputs), history=True))
    assert compiled.last_compile_ms > 0
    outputs, gradients = _loss_gradients(compiled, inputs)
    assert all(bool(g.isfinite().all()) for g in gradients)
    for name, value, expected in zip(OUTPUTS, outputs, reference):
        torch.testing.assert_close(value, expected, atol=1e-3, rtol=1e-4, msg=name)


def test_gradcheck_goals_and_obstacles(one_thread):
    config = small_config(num_steps=12, order=6, iterations=6, max_obstacles=2)
    opt = mmpc.BatchOptimizer(config, dtype=torch.float64)
    ego = mmpc.ego_state(0.0, 4.0, 0.02, 12.0, 0.3, 0.01, dtype=torch.float64)
    goals = torch.tensor([[[95.0, 4.0], [100.0, 8.0]]], dtype=torch.float64, requires_grad=True)
    # An obstacle the straight path runs into, so the obstacle step is active.
    states = torch.tensor([[[25.0, 5.0, 9.0, 0.0], [60.0, 8.5, 7.0, 0.0]]], dtype=torch.float64)
    obstacles = mmpc.predict_constant_velocity(states, opt.times).requires_grad_(True)

    def outputs(goals, obstacles):
        result = opt(mmpc.ProblemBatch(ego, goals, obstacles))
        return result.trajectories.x, result.trajectories.y, result.trajectories.v, result.trajectories.psi

    active = opt(mmpc.ProblemBatch(ego, goals.detach(), obstacles.detach()))
    assert (active.residual_obstacle > 0).any() or (active.min_obstacle_distance < 1.5).any()
    assert torch.autograd.gradcheck(outputs, (goals, obstacles), eps=1e-6, atol=1e-4, rtol=1e-3)


def test_meta_cost_gradient_reaches_goals():
    opt = mmpc.BatchOptimizer(small_config(), dtype=torch.float64)
    ego = mmpc.ego_state(0.0, 4.0, 0.0, 12.0, dtype=torch.float64)
    goals = torch.tensor([[[100.0, 4.0]]], dtype=torch.float64, requires_grad=True)
    obstacles = torch.zeros(1, 0, opt.config.num_steps, 2, dtype=torch.float64)
    result = opt(mmpc.ProblemBatch(ego, goals, obstacles))
    cost = mmpc.CruiseCost(15.0)(result.trajectories, mmpc.Road()).sum()
    cost.backward()
    # Pulling the goal further ahead raises the speed towards 15 m/s: the x-gradient is negative.
    assert goals.grad[0, 0, 0] < 0
