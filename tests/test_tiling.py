"""A batch solved in tiles gives the answers of one call (BatchOptimizer's ``tile_size``)."""

import pytest
import torch

import mmpc
from mmpc.scenes import synthetic_scenes
from mmpc.solver.execution import tiling
from tests.conftest import small_config


def _three_problems(config: mmpc.OptimizerConfig) -> mmpc.ProblemBatch:
    """Three scenes with 5 goals each and different obstacle counts (2, 3, 0 of 3 slots)."""
    scenes = synthetic_scenes(11, seed=4, num_steps=config.num_steps, dtype=torch.float64)
    picked = [scenes[2].problem, scenes[3].problem, scenes[4].problem]
    slots = 3
    egos, goals, obstacles, masks = [], [], [], []
    for problem in picked:
        count = min(problem.obstacles.shape[1], slots)
        padded = torch.zeros(1, slots, config.num_steps, 2, dtype=torch.float64)
        padded[:, :count] = problem.obstacles[:, :count]
        egos.append(problem.ego)
        goals.append(problem.goals[:, :5])
        obstacles.append(padded)
        masks.append(torch.arange(slots)[None] < count)
    masks[2][:] = False
    return mmpc.ProblemBatch(torch.cat(egos), torch.cat(goals), torch.cat(obstacles), torch.cat(masks))


@pytest.mark.parametrize(
    "tile_size, expected_tiling",
    [
        (4, (1, 3)),  # 5 goals do not fit: each problem's goals in two tiles of 3 (one padded)
        (12, (2, 5)),  # two problems per tile: the second tile is padded with a copy of the third
    ],
)
def test_tiled_solve_equals_one_call(tile_size, expected_tiling):
    config = small_config(iterations=12, max_obstacles=3)
    problem = _three_problems(config)
    assert tiling(3, 5, tile_size) == expected_tiling
    whole = mmpc.BatchOptimizer(config, dtype=torch.float64)
    tiled = mmpc.BatchOptimizer(config, dtype=torch.float64, tile_size=tile_size)
    expected, result = whole(problem, history=True), tiled(problem, history=True)
    assert result.history.shape == expected.history.shape == (12, 3, 5, 3)
    assert result.trajectories.x.shape == (3, 5, config.num_steps)
    torch.testing.assert_close(result.trajectories.times, expected.trajectories.times)
    for name in mmpc.Trajectories._fields[1:]:
        torch.testing.assert_close(getattr(result.trajectories, name), getattr(expected.trajectories, name))
    for name in mmpc.SolveResult._fields[1:]:
        torch.testing.assert_close(getattr(result, name), getattr(expected, name), msg=name)
    assert not expected.feasible.all() and expected.feasible.any()  # both outcomes compared


def test_tiling_uses_few_tile_shapes():
    assert tiling(1, 11, 256) is None  # one tile
    assert tiling(3, 11, None) is None
    assert tiling(1, 1024, 256) == (1, 256)
    assert tiling(1, 1000, 256) == (1, 250)  # four even tiles, no padding
    assert tiling(1, 257, 256) == (1, 129)  # two tiles, one padding goal
    assert tiling(64, 11, 256) == (23, 11)  # 3 tiles of as many problems as fit
    assert tiling(40, 11, 256) == (23, 11)
    assert tiling(8, 35, 256) == (4, 35)  # 2 tiles of 4 (7 fit), a power of two
    assert tiling(9, 35, 256) == (7, 35)
    assert tiling(2, 300, 256) == (1, 150)


def test_tile_size_defaults_to_the_compiled_cpu_path_only():
    assert mmpc.BatchOptimizer(small_config()).tile_size is None
    assert mmpc.BatchOptimizer(small_config(), compile=True).tile_size == 256
    assert mmpc.BatchOptimizer(small_config(), compile=True, tile_size=64).tile_size == 64
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="tile_size"):
            mmpc.BatchOptimizer(small_config(), tile_size=bad)
