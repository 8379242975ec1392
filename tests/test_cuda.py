"""CUDA path: same answers as the CPU path. Skipped without a GPU."""

import pytest
import torch

import mmpc
from mmpc.scenes import synthetic_scenes

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA"),
]


def test_cuda_matches_cpu_float32():
    cpu = mmpc.BatchOptimizer()
    gpu = mmpc.BatchOptimizer(device="cuda")
    for scene in synthetic_scenes(8):
        expected = cpu(scene.problem)
        problem = mmpc.ProblemBatch(*(t.cuda() for t in scene.problem[:3]))
        result = gpu(problem)
        assert torch.equal(result.feasible.cpu(), expected.feasible)
        torch.testing.assert_close(result.trajectories.x.cpu(), expected.trajectories.x, atol=2e-2, rtol=1e-4)
        torch.testing.assert_close(result.trajectories.v.cpu(), expected.trajectories.v, atol=2e-2, rtol=1e-3)


def test_module_to_moves_every_buffer():
    opt = mmpc.BatchOptimizer().to("cuda")
    assert all(buffer.is_cuda for buffer in opt.buffers())
    with pytest.raises(ValueError, match="is on cpu but the optimizer is on cuda"):
        opt(synthetic_scenes(1)[0].problem)


def test_compiled_cuda_graph_matches_cpu_and_keeps_earlier_results():
    """The CUDA-graph path (iteration chunks replayed as graphs): CPU answers within float32
    tolerance, and a later solve does not overwrite the tensors of an earlier result."""
    cpu = mmpc.BatchOptimizer()
    gpu = mmpc.BatchOptimizer(device="cuda", compile=True)
    scenes = synthetic_scenes(4)
    expected = [cpu(scene.problem) for scene in scenes]
    results = [gpu(mmpc.ProblemBatch(*(t.cuda() for t in scene.problem[:3]))) for scene in scenes]
    for result, reference in zip(results, expected):  # read after every solve has run
        assert torch.equal(result.feasible.cpu(), reference.feasible)
        torch.testing.assert_close(result.trajectories.x.cpu(), reference.trajectories.x, atol=2e-2, rtol=1e-4)
        torch.testing.assert_close(result.trajectories.v.cpu(), reference.trajectories.v, atol=2e-2, rtol=1e-3)


def test_compiled_cuda_graph_warm_starts_match_cpu():
    """Warm-started solves replay graphs of their own (one per first iteration), the problems
    without iterates solved cold beside them: the CPU's answers within float32 tolerance."""
    cpu = mmpc.BatchOptimizer()
    gpu = mmpc.BatchOptimizer(device="cuda", compile=True)
    problem = synthetic_scenes(2, seed=3)[1].problem
    cold = cpu(problem)
    position = cold.warm.position.clone()
    position[0] = float("nan")  # problem 0 restarts cold
    warm = cold.warm._replace(position=position)
    expected = cpu(problem, warm=warm, warm_iterations=30)
    for _ in range(2):  # captured, then replayed
        result = gpu(mmpc.ProblemBatch(*(t.cuda() for t in problem[:3])), warm=mmpc.WarmStart(*(f.cuda() for f in warm)),
                     warm_iterations=30)
    assert torch.equal(result.feasible.cpu(), expected.feasible)
    torch.testing.assert_close(result.trajectories.x.cpu(), expected.trajectories.x, atol=2e-2, rtol=1e-4)


def test_compiled_cuda_graph_history_records_every_iteration():
    """Records of earlier chunks survive the replays of later ones and end at the final residuals."""
    gpu = mmpc.BatchOptimizer(device="cuda", compile=True)
    scene = synthetic_scenes(1)[0]
    result = gpu(mmpc.ProblemBatch(*(t.cuda() for t in scene.problem[:3])), history=True)
    history = result.history
    assert history.shape == (gpu.config.iterations, *result.feasible.shape, 3)
    torch.testing.assert_close(history[-1, ..., 0], result.residual_obstacle)
    torch.testing.assert_close(history[-1, ..., 2], result.residual_nonholonomic)
    expected = mmpc.BatchOptimizer()(scene.problem, history=True).history
    torch.testing.assert_close(history[0].cpu(), expected[0], atol=1e-3, rtol=1e-3)  # first chunk kept


def test_compiled_cuda_graph_early_exit_matches_cpu():
    """Early exit on the graph path: the stretches after a check replay graphs of one goal per
    problem (E rounded up to a captured size); the CPU's iterations and verdicts."""
    config = mmpc.OptimizerConfig(exit_checks=(10, 30))
    cpu = mmpc.BatchOptimizer(config)
    gpu = mmpc.BatchOptimizer(config, device="cuda", compile=True)
    for scene in synthetic_scenes(4, seed=5):
        expected = cpu(scene.problem)
        for _ in range(2):  # captured, then replayed
            result = gpu(mmpc.ProblemBatch(*(t.cuda() for t in scene.problem[:3])))
        assert torch.equal(result.iterations.cpu(), expected.iterations)
        assert torch.equal(result.feasible.cpu(), expected.feasible)
        torch.testing.assert_close(result.trajectories.x.cpu(), expected.trajectories.x, atol=2e-2, rtol=1e-4)
