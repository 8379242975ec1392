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
