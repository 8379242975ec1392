"""Module mechanics: buffers, dtype moves, residual history."""

import torch

import mmpc
from mmpc.scenes import demo_scene


def test_every_constant_matrix_is_a_buffer_built_once():
    opt = mmpc.BatchOptimizer()
    names = {name for name, _ in opt.named_buffers()}
    assert {"position", "position_init", "heading", "gather", "heading_gather", "samples"} <= names
    cfg = opt.config
    assert opt.position.shape == (cfg.iterations, cfg.max_obstacles + 1, 2, cfg.order + 1, 3 * (cfg.order + 1) + 4)
    assert opt.state_dict() == {}  # derived from the config, not parameters


def test_to_dtype_moves_every_buffer_and_the_computation():
    opt = mmpc.BatchOptimizer().to(torch.float64)
    assert all(buffer.dtype == torch.float64 for buffer in opt.buffers())
    result = opt(demo_scene().problem)
    assert result.trajectories.x.dtype == torch.float64


def test_history_records_every_iteration_and_ends_at_the_final_residuals():
    opt = mmpc.BatchOptimizer(dtype=torch.float64)
    scene = demo_scene()
    result = opt(scene.problem, history=True)
    history = result.history
    assert history.shape == (opt.config.iterations, 1, 11, 3)
    torch.testing.assert_close(history[-1, ..., 0], result.residual_obstacle)
    torch.testing.assert_close(history[-1, ..., 1], result.residual_acceleration)
    torch.testing.assert_close(history[-1, ..., 2], result.residual_nonholonomic)
    # Feasible elements drive their obstacle residual down from where the iterations started.
    feasible = result.feasible[0]
    started = history[0, 0, feasible, 0]
    assert (history[-1, 0, feasible, 0] <= 1e-3).all() and (started > history[-1, 0, feasible, 0]).any()
    assert opt(scene.problem).history is None
