import fcntl
import os
import sys
from pathlib import Path

import pytest
import torch

import mmpc
from mmpc.scenes import synthetic_scenes
from mmpc.solver.execution import COMPILE_ENV

# The scenario MPC compiles its optimizer by default (compile="auto"); a cold compile takes a
# minute per batch layout, so the tests, subprocesses included, run the eager reference. The
# compiled path has its own tests (test_compiled.py, test_mpc.py, test_tiling.py).
os.environ[COMPILE_ENV] = "0"

# The benchmark scripts (outside the installed package) import as top-level modules.
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))


@pytest.fixture(scope="session")
def optimizer64() -> mmpc.BatchOptimizer:
    return mmpc.BatchOptimizer(dtype=torch.float64)


@pytest.fixture(scope="session")
def scenes64():
    return synthetic_scenes(36, seed=0, dtype=torch.float64)


@pytest.fixture(scope="session")
def solved_scenes(optimizer64, scenes64):
    return [(scene, optimizer64(scene.problem)) for scene in scenes64]


def small_config(**overrides) -> mmpc.OptimizerConfig:
    """A cheap optimizer for property and gradient tests."""
    values = dict(num_steps=30, order=8, iterations=20, max_obstacles=4)
    values.update(overrides)
    return mmpc.OptimizerConfig(**values)


@pytest.fixture
def one_thread():
    """Closed-loop tests: one torch thread (the solves are small; two threads thrash on a busy
    2-core machine)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


def hold_lock(path: Path):
    """An open handle holding an exclusive flock on ``path`` (as a second process would)."""
    handle = open(path, "w")
    fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    return handle


def lock_is_free(path: Path) -> bool:
    """Nobody holds an flock on ``path`` (created if missing)."""
    with open(path, "a") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return False
        fcntl.flock(handle, fcntl.LOCK_UN)
    return True


def evaluation_folder(path: Path, scenario, returns, seeds=None, driver: str = "mpc") -> Path:
    """An evaluation folder as `mmpc evaluate` leaves it (episodes.csv, scenarios.json): one finished
    episode of ``driver`` on ``scenario`` per seed (default 0, 1, ...), ``returns`` its task returns,
    every other column 0."""
    import csv

    from mmpc.evaluate import COLUMNS
    from mmpc.evaluate.store import check_inputs

    path.mkdir()
    with open(path / "episodes.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, COLUMNS)
        writer.writeheader()
        for seed, value in zip(seeds or range(len(returns)), returns):
            row = dict.fromkeys(COLUMNS, 0)
            row.update(driver=driver, scenario=scenario.name, seed=seed, status="ok", error="", worker="w",
                       collision_part="", task_return=value, duration=scenario.duration)
            writer.writerow(row)
    check_inputs(path, [scenario], (driver,))
    return path
