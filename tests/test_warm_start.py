"""Warm starts: a solve from earlier iterates (mmpc.WarmStart) runs the last k iterations of the
schedule; BatchOptimizer.shifted moves iterates one control step on; MPCDriver keeps them."""

import dataclasses

import pytest
import torch

import mmpc
from mmpc.basis import bernstein_basis
from mmpc.drivers import Observation
from mmpc.drivers.mpc_driver import MPCDriver
from mmpc.scenes import synthetic_scenes


@pytest.fixture(scope="module")
def cruise_mpc() -> mmpc.MPC:
    goals = mmpc.NearLaneGoals(mmpc.CruiseGoals(num_goals=6), speeds=(3.0, 6.0, 9.0, 12.0))
    return mmpc.MPC(mmpc.BatchOptimizer(), goals, mmpc.CruiseCost(15.0), mmpc.Road(num_lanes=6))


@pytest.fixture(scope="module")
def solved():
    optimizer = mmpc.BatchOptimizer()
    scene = synthetic_scenes(2, seed=3)[1]
    return optimizer, scene.problem, optimizer(scene.problem)


def test_a_solve_started_from_its_own_iterates_keeps_its_answer(solved):
    optimizer, problem, cold = solved
    again = optimizer(problem, warm=cold.warm, warm_iterations=10)
    assert torch.equal(again.feasible, cold.feasible)
    torch.testing.assert_close(again.trajectories.x, cold.trajectories.x, atol=2e-2, rtol=0)
    torch.testing.assert_close(again.trajectories.y, cold.trajectories.y, atol=2e-2, rtol=0)
    assert again.warm.position.shape == cold.warm.position.shape == (*cold.feasible.shape, 2, optimizer.config.order + 1)
    history = optimizer(problem, warm=cold.warm, warm_iterations=10, history=True).history
    assert history.shape[0] == 10  # the iterations run, not the schedule's


def test_a_shift_follows_the_trajectory_and_moves_it_to_the_new_start(solved):
    optimizer, _, cold = solved
    cfg = optimizer.config
    rows = cold.feasible.shape[0]
    same = optimizer.shifted(cold.warm, 0.0, torch.zeros(rows, 2))
    torch.testing.assert_close(same.position, cold.warm.position, atol=1e-4, rtol=0)
    offset = torch.tensor([[3.0, -1.0]]).expand(rows, 2)
    moved = optimizer.shifted(cold.warm, 0.4, offset)
    basis = bernstein_basis(cfg.order, cfg.num_steps, cfg.horizon).P.to(torch.float32)
    before = cold.warm.position @ basis.T  # (E, G, 2, N) relative to the old start
    after = moved.position @ basis.T
    step = round(0.4 / (cfg.horizon / (cfg.num_steps - 1)))  # 0.4 s lands within half a sample
    expected = before[..., step:step + 80] - offset[:, None, :, None]
    got = after[..., :80]
    assert (got - expected).abs().max() < 0.6  # interior samples; a sample is 0.08 s of motion at up to ~25 m/s


def test_warm_starts_are_checked(solved):
    optimizer, problem, cold = solved
    with pytest.raises(ValueError, match="warm_iterations"):
        optimizer(problem, warm=cold.warm)
    with pytest.raises(ValueError, match="warm_iterations"):
        optimizer(problem, warm=cold.warm, warm_iterations=optimizer.config.iterations + 1)
    with pytest.raises(ValueError, match="needs a `warm` start"):
        optimizer(problem, warm_iterations=10)
    with pytest.raises(ValueError, match=r"`warm.position` must have shape"):
        optimizer(problem, warm=cold.warm._replace(position=cold.warm.position[:, :2]), warm_iterations=10)
    with pytest.raises(TypeError, match="WarmStart"):
        optimizer(problem, warm=tuple(cold.warm), warm_iterations=10)


def test_a_warm_start_follows_the_padding_and_tiles_of_the_compiled_path(solved):
    _, problem, cold = solved
    eager = mmpc.BatchOptimizer()(problem, warm=cold.warm, warm_iterations=30)
    tiled = mmpc.BatchOptimizer(tile_size=4)
    tiled.compiled = True  # the padding and tiling read the flag; eager functions keep the test fast
    result = tiled(problem, warm=cold.warm, warm_iterations=30)
    assert torch.equal(result.feasible, eager.feasible)
    torch.testing.assert_close(result.trajectories.x, eager.trajectories.x, atol=2e-2, rtol=1e-5)  # float32 at x ~ 2 km
    assert result.warm.position.shape == eager.warm.position.shape  # padding goals and tiles joined back


def _recording_mpc(cruise_mpc: mmpc.MPC, **changes) -> tuple[mmpc.MPC, list[bool]]:
    """``cruise_mpc`` with ``changes`` to its config, and the list its optimizer appends to at
    every call: whether the call was warm-started."""
    calls = []

    class Recording(mmpc.BatchOptimizer):
        def forward(self, problem, **kwargs):
            calls.append(kwargs.get("warm") is not None)
            return super().forward(problem, **kwargs)

    config = dataclasses.replace(cruise_mpc.config, **changes)
    return mmpc.MPC(Recording(cruise_mpc.optimizer.config), cruise_mpc.goal_sampler, cruise_mpc.meta_cost, cruise_mpc.road,
                    config), calls


def test_the_mpc_driver_warm_starts_every_environment_it_has_seen(cruise_mpc):
    mpc, calls = _recording_mpc(cruise_mpc, warm_iterations=20, warm_cold_every=100)
    with pytest.raises(ValueError, match="period"):
        MPCDriver(mpc)
    driver = MPCDriver(mpc, period=0.1)
    ego = torch.tensor([[0.0, 8.0, 0.0, 14.0, 0.0, 0.0], [0.0, 12.0, 0.0, 14.0, 0.0, 0.0]])
    cars = torch.tensor([[[40.0, 8.0, 10.0, 0.0]], [[40.0, 12.0, 10.0, 0.0]]])
    observe = lambda ids, x: Observation(ego[ids] + torch.tensor([x, 0, 0, 0, 0, 0]), cars[ids], None, None, torch.tensor(ids))
    driver.reset(2)
    for x in (0.0, 1.4, 2.8):
        driver.decide(observe([0, 1], x))
    driver.decide(observe([1], 4.2))  # a row ended: the other still warm
    driver.decide(observe([0, 1], 5.6))  # environment 0 was not in the last step: all cold
    driver.reset(2)
    driver.decide(observe([0, 1], 0.0))
    assert calls == [False, True, True, True, False, False]


def test_warm_iterations_cannot_exceed_the_schedule(cruise_mpc):
    config = dataclasses.replace(cruise_mpc.config, warm_iterations=101)
    with pytest.raises(ValueError, match="warm_iterations=101 exceeds"):
        mmpc.MPC(cruise_mpc.optimizer, cruise_mpc.goal_sampler, cruise_mpc.meta_cost, cruise_mpc.road, config)
    with pytest.raises(ValueError, match="warm_iterations"):
        mmpc.MPCConfig(warm_iterations=-1)


def test_elements_whose_iterates_diverged_start_cold(solved):
    optimizer, problem, cold = solved
    position = cold.warm.position.clone()
    position[0, 1] = float("nan")  # goal 1 of problem 0 diverged; the others keep their iterates
    result = optimizer(problem, warm=cold.warm._replace(position=position), warm_iterations=30)
    assert bool(torch.isfinite(result.trajectories.x).all()) and bool(torch.isfinite(result.warm.position).all())
    assert torch.equal(result.feasible[:, 2:], optimizer(problem, warm=cold.warm, warm_iterations=30).feasible[:, 2:])


def test_the_mpc_driver_solves_cold_every_nth_step(cruise_mpc):
    mpc, calls = _recording_mpc(cruise_mpc, warm_iterations=20, warm_cold_every=3)
    driver = MPCDriver(mpc, period=0.1)
    for x in (0.0, 1.4, 2.8, 4.2, 5.6, 7.0, 8.4):
        driver.decide(Observation(torch.tensor([[x, 8.0, 0.0, 14.0, 0.0, 0.0]]), torch.tensor([[[x + 60.0, 8.0, 10.0, 0.0]]])))
    assert calls == [False, True, True, False, True, True, False]
