"""The torch.compile path gives the eager answers (float32 tolerance)."""

import torch

import mmpc
from mmpc.scenes import synthetic_scenes
from tests.conftest import small_config


def test_compiled_matches_eager():
    # heading_target_deg: the clipped heading step is part of the compiled graph too
    config = small_config(num_steps=100, order=10, iterations=20, max_obstacles=10, heading_target_deg=6.0)
    eager = mmpc.BatchOptimizer(config)
    compiled = mmpc.BatchOptimizer(config, compile=True)
    assert compiled.chunk == 10
    scene = synthetic_scenes(8, seed=3)[7]  # 7 obstacles, lane changes; one shape = one compile
    assert scene.problem.obstacles.shape[1] == 7
    for _ in range(2):  # the second call runs the cached graphs
        expected, result = eager(scene.problem), compiled(scene.problem)
        torch.testing.assert_close(result.trajectories.x, expected.trajectories.x, atol=1e-3, rtol=1e-5)
        torch.testing.assert_close(result.trajectories.psi, expected.trajectories.psi, atol=1e-4, rtol=1e-4)
        assert torch.equal(result.feasible, expected.feasible)
