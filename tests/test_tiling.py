"""A batch solved in tiles gives the answers of one call (BatchOptimizer's ``tile_size``)."""

import pytest
import torch

import mmpc
from mmpc.scenes import synthetic_scenes
from mmpc.solver.execution import problem_tiles, tiling
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
        (12, (2, 5)),  # two problems per tile (12 / 5 goals), then the third in a tile of one
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
    assert tiling(2, 300, 256) == (1, 150)
    # Whole problems: the power of two nearest tile_size / G problems per tile.
    assert tiling(64, 11, 256) == (32, 11)  # 256 / 11 = 23.3: 32 (352 elements), not 16 (176)
    assert tiling(64, 35, 256) == (8, 35)  # 256 / 35 = 7.3: 8, and 64 problems fill 8 tiles
    assert tiling(9, 35, 256) == (8, 35)
    assert tiling(8, 35, 256) == (8, 35)  # 280 elements: one tile
    assert tiling(3, 100, 256) == (2, 100)  # at most E rounded up to a power of two
    assert tiling(5, 100, 256) == (2, 100)


def test_the_problems_left_over_take_one_smaller_power_of_two_tile():
    assert problem_tiles(64, 8) == [(first, 8) for first in range(0, 64, 8)]
    assert problem_tiles(9, 8) == [(0, 8), (8, 1)]  # not a second tile of 8: 7 padding problems
    assert problem_tiles(19, 8) == [(0, 8), (8, 8), (16, 4)]  # 3 left: a tile of 4
    assert problem_tiles(13, 8) == [(0, 8), (8, 8)]  # 5 left: a tile of 8
    assert problem_tiles(3, 2) == [(0, 2), (2, 1)]
    for problems in range(1, 40):
        tiles = problem_tiles(problems, 8)
        assert tiles[0][0] == 0 and all(a + n == b for (a, n), (b, _) in zip(tiles, tiles[1:]))
        assert 0 <= tiles[-1][0] + tiles[-1][1] - problems < max(1, problems % 8)  # fewer copies than problems left
        assert {n for _, n in tiles} <= {1, 2, 4, 8}


def test_tile_size_defaults_to_the_compiled_cpu_path_only():
    assert mmpc.BatchOptimizer(small_config()).tile_size is None
    assert mmpc.BatchOptimizer(small_config(), compile=True).tile_size == 256
    assert mmpc.BatchOptimizer(small_config(), compile=True, tile_size=64).tile_size == 64
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="tile_size"):
            mmpc.BatchOptimizer(small_config(), tile_size=bad)
