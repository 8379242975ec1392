"""Warm starts: a solve from earlier iterates (mmpc.WarmStart) runs the last k iterations of the
schedule; BatchOptimizer.shifted moves iterates one control step on; MPCDriver keeps them."""

import dataclasses

import pytest
import torch

import mmpc
from mmpc.solver.basis import bernstein_basis
from mmpc.drivers import Observation
from mmpc.drivers.mpc_driver import MPCDriver
from mmpc.result import WarmStart
from mmpc.scenes import synthetic_scenes


@pytest.fixture(scope="module")
def cruise_mpc() -> mmpc.MPC:
    optimizer = mmpc.BatchOptimizer()
    horizon = optimizer.config.horizon
    goals = mmpc.NearLaneGoals(mmpc.CruiseGoals(num_goals=6, horizon=horizon), speeds=(3.0, 6.0, 9.0, 12.0), horizon=horizon)
    return mmpc.MPC(optimizer, goals, mmpc.CruiseCost(15.0), mmpc.Road(num_lanes=6))


@pytest.fixture(scope="module")
def solved():
    optimizer = mmpc.BatchOptimizer()
    scene = synthetic_scenes(2, seed=3)[1].problem
    problem = mmpc.ProblemBatch(*(torch.cat([t, t]) for t in scene[:3]))  # two problems: one may restart, one not
    return optimizer, problem, optimizer(problem)


def test_a_solve_started_from_its_own_iterates_keeps_its_answer(solved):
    optimizer, problem, cold = solved
    again = optimizer(problem, warm=cold.warm, warm_iterations=10)
    assert torch.equal(again.feasible, cold.feasible)
    torch.testing.assert_close(again.trajectories.x, cold.trajectories.x, atol=2e-2, rtol=0)
    torch.testing.assert_close(again.trajectories.y, cold.trajectories.y, atol=2e-2, rtol=0)
    assert again.warm.position.shape == cold.warm.position.shape == (*cold.feasible.shape, 2, optimizer.config.order + 1)
    history = optimizer(problem, warm=cold.warm, warm_iterations=10, history=True).history
    assert history.shape == (optimizer.config.iterations, *cold.feasible.shape, 3)
    assert bool(history[:90].isnan().all()) and bool(history[90:].isfinite().all())  # the schedule's last 10 run


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


def test_the_warm_and_the_cold_rows_of_a_step_are_solved_in_power_of_two_tiles_without_padding(solved):
    """Compiled on the CPU, the warm and the cold rows of a warm-started step are each tiled in
    powers of two of problems (a few compiled layouts), and here, 4 warm rows and 1 cold, with no
    padding problem solved."""
    _, problem, cold = solved
    rows = torch.tensor([0, 1, 0, 1, 0])  # five problems, the last one restarting
    batch = mmpc.ProblemBatch(*(None if field is None else field[rows] for field in problem))
    warm = cold.warm.take(rows)
    warm = warm._replace(position=torch.where(torch.arange(5)[:, None, None, None] == 4, float("nan"), warm.position))
    num_goals = batch.goals.shape[1]
    tiled = mmpc.BatchOptimizer(tile_size=2 * num_goals)  # two problems a tile
    tiled.compiled = True  # the padding and tiling read the flag; eager functions keep the test fast
    shapes, solve = [], tiled._solve

    def recording(ego, goals, *args):
        shapes.append(tuple(goals.shape[:2]))
        return solve(ego, goals, *args)

    tiled._solve = recording
    result = tiled(batch, warm=warm, warm_iterations=30)
    assert sorted(shapes) == [(1, num_goals), (2, num_goals), (2, num_goals)]  # the lone cold row: a tile of one
    expected = mmpc.BatchOptimizer()(batch, warm=warm, warm_iterations=30)
    assert torch.equal(result.feasible, expected.feasible)
    assert result.iterations[:, 0].tolist() == expected.iterations[:, 0].tolist() == [30, 30, 30, 30, 100]
    torch.testing.assert_close(result.trajectories.x, expected.trajectories.x, atol=2e-2, rtol=1e-5)


def _recording_mpc(cruise_mpc: mmpc.MPC, **changes) -> tuple[mmpc.MPC, list[tuple[bool, ...]]]:
    """``cruise_mpc`` with ``changes`` to its config, and the list its optimizer appends to at
    every call: per problem, whether it was warm-started."""
    calls = []

    class Recording(mmpc.BatchOptimizer):
        def forward(self, problem, **kwargs):
            warm = kwargs.get("warm")
            rows = problem.goals.shape[0]
            calls.append((False,) * rows if warm is None else tuple(warm.position.flatten(1).isfinite().all(dim=1).tolist()))
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
    driver.decide(observe([0, 1], 5.6))  # environment 0 was not in the last step: it alone cold
    driver.reset(2)
    driver.decide(observe([0, 1], 0.0))
    assert calls == [(False, False), (True, True), (True, True), (True,), (False, True), (False, False)]


def test_warm_iterations_cannot_exceed_the_schedule(cruise_mpc):
    config = dataclasses.replace(cruise_mpc.config, warm_iterations=101)
    with pytest.raises(ValueError, match="warm_iterations=101 exceeds"):
        mmpc.MPC(cruise_mpc.optimizer, cruise_mpc.goal_sampler, cruise_mpc.meta_cost, cruise_mpc.road, config)
    with pytest.raises(ValueError, match="warm_iterations"):
        mmpc.MPCConfig(warm_iterations=-1)


def test_problems_with_iterates_not_finite_solve_cold_with_the_whole_schedule(solved):
    optimizer, problem, cold = solved
    position = cold.warm.position.clone()
    position[0, 1] = float("nan")  # goal 1 of problem 0 diverged: problem 0 restarts, problem 1 stays warm
    warm = cold.warm._replace(position=position)
    result = optimizer(problem, warm=warm, warm_iterations=30, history=True)
    warm_only = optimizer(problem, warm=cold.warm, warm_iterations=30)
    torch.testing.assert_close(result.trajectories.x[0], cold.trajectories.x[0])
    torch.testing.assert_close(result.trajectories.x[1:], warm_only.trajectories.x[1:])
    assert torch.equal(result.feasible, torch.cat([cold.feasible[:1], warm_only.feasible[1:]]))
    assert result.iterations[:, 0].tolist() == [optimizer.config.iterations, 30]
    assert result.history.shape == (optimizer.config.iterations, *cold.feasible.shape, 3)
    assert bool(torch.isfinite(result.history[:, 0]).all()) and bool(result.history[:70, 1:].isnan().all())
    assert bool(torch.isfinite(result.history[70:, 1:]).all())
    every = optimizer(problem, warm=WarmStart(*(torch.full_like(f, float("nan")) for f in warm)), warm_iterations=30)
    torch.testing.assert_close(every.trajectories.x, cold.trajectories.x)


def test_the_mpc_driver_solves_cold_every_nth_step(cruise_mpc):
    mpc, calls = _recording_mpc(cruise_mpc, warm_iterations=20, warm_cold_every=3)
    driver = MPCDriver(mpc, period=0.1)
    for x in (0.0, 1.4, 2.8, 4.2, 5.6, 7.0, 8.4):
        driver.decide(Observation(torch.tensor([[x, 8.0, 0.0, 14.0, 0.0, 0.0]]), torch.tensor([[[x + 60.0, 8.0, 10.0, 0.0]]])))
    assert calls == [(False,), (True,), (True,), (False,), (True,), (True,), (False,)]


def test_the_mpc_driver_solves_cold_after_a_fallback_in_that_environment_only(cruise_mpc):
    mpc, calls = _recording_mpc(cruise_mpc, warm_iterations=20, warm_cold_every=100)
    driver = MPCDriver(mpc, period=0.1)
    ego = torch.tensor([[0.0, 8.0, 0.0, 14.0, 0.0, 0.0], [0.0, 12.0, 0.0, 14.0, 0.0, 0.0]])
    cars = torch.tensor([[[3.0, 8.0, 0.0, 0.0]], [[40.0, 12.0, 10.0, 0.0]]])  # environment 0 stuck behind a stopped car
    decisions = [driver.decide(Observation(ego, cars, None, None, torch.tensor([0, 1]))) for _ in range(3)]
    assert [d.fallback.tolist() for d in decisions] == [[True, False]] * 3
    assert calls == [(False, False), (False, True), (False, True)]
    assert [d.iterations.tolist() for d in decisions] == [[100, 100], [100, 20], [100, 20]]  # the first 100 cold


@pytest.mark.parametrize("share", [0.75, 0.0])
def test_the_mpc_driver_solves_cold_after_a_warm_solve_lost_feasible_goals(cruise_mpc, share):
    mpc, calls = _recording_mpc(cruise_mpc, warm_iterations=20, warm_cold_every=100, warm_keep_share=share)
    driver = MPCDriver(mpc, period=0.1)
    decisions = []
    for step, x in enumerate((0.0, 1.4, 2.8, 4.2, 5.6)):
        far = [[x + 60.0, 8.0, 10.0, 0.0]] * 3
        boxed_in = [[x + 2.0, 12.0, 14.0, 0.0], [x + 2.0, 4.0, 14.0, 0.0], [x + 15.0, 8.0, 14.0, 0.0]]  # from step 2
        cars = torch.tensor([far if step < 2 else boxed_in])
        decisions.append(driver.decide(Observation(torch.tensor([[x, 8.0, 0.0, 14.0, 0.0, 0.0]]), cars)))
    feasible = [int(d.feasible_goals) for d in decisions]
    assert feasible[2] < 0.75 * feasible[0] and not any(bool(d.fallback) for d in decisions)
    if share:  # step 2's warm solve kept under 75 % of step 0's feasible goals: step 3 cold, its count the new reference
        assert calls == [(False,), (True,), (True,), (False,), (True,)]
    else:
        assert calls == [(False,), (True,), (True,), (True,), (True,)]
    with pytest.raises(ValueError, match="warm_keep_share"):
        mmpc.MPCConfig(warm_keep_share=1.5)


def test_a_problem_whose_warm_solve_finds_no_feasible_goal_solves_again_cold(solved):
    optimizer, problem, cold = solved
    assert bool(cold.feasible.any(dim=1).all())
    standing = WarmStart(*(torch.zeros_like(field) for field in cold.warm))  # every plan a standstill at the start
    result = optimizer(problem, warm=standing, warm_iterations=1, history=True)
    assert torch.equal(result.feasible, cold.feasible)
    torch.testing.assert_close(result.trajectories.x, cold.trajectories.x)
    assert bool(result.history.isfinite().all())  # the whole schedule ran
    assert bool((result.iterations == optimizer.config.iterations + 1).all())  # after the warm one


# ------------------------------------------------------------------ every receding-horizon user of the MPC


def test_a_solver_of_some_goals_is_warm_only_where_it_solved_every_one_of_them_before(cruise_mpc):
    """mmpc.warm.WarmStarts with goal slots (the mode proposer's driver): a row's solve starts
    from the last one's iterates, goal by goal, only where each of its goals was solved then."""
    from mmpc.warm import WarmStarts

    mpc = mmpc.MPC(cruise_mpc.optimizer, cruise_mpc.goal_sampler, cruise_mpc.meta_cost, cruise_mpc.road,
                   dataclasses.replace(cruise_mpc.config, warm_iterations=10, warm_cold_every=100), control_period=0.1)
    warm_starts = WarmStarts(mpc)
    assert warm_starts.period == 0.1  # the MPC's control period
    ego = torch.tensor([[0.0, 8.0, 0.0, 14.0, 0.0, 0.0], [0.0, 12.0, 0.0, 14.0, 0.0, 0.0]])
    cars = torch.tensor([[[60.0, 8.0, 10.0, 0.0]], [[60.0, 12.0, 10.0, 0.0]]])
    problem = mpc.build_problem(ego, cars)
    ids = torch.tensor([3, 7])
    slots = torch.tensor([[0, 2, 4], [1, 2, 3]])
    first = warm_starts.start(ids, ego, slots)
    assert first.warm is None and first.steps.tolist() == [0, 0]
    goals = lambda chosen: problem._replace(goals=torch.gather(problem.goals, 1, chosen[..., None].expand(-1, -1, 2)))
    result = mpc.score(goals(slots)).result
    warm_starts.keep(ids, ego, result, first, slots)
    later = ego + torch.tensor([1.4, 0.0, 0.0, 0.0, 0.0, 0.0])
    swapped = torch.tensor([[4, 0, 2], [1, 2, 5]])  # row 0: the same goals in another order; row 1: goal 5 is new
    second = warm_starts.start(ids, later, swapped)
    assert second.steps.tolist() == [1, 0]
    assert bool(second.warm.position[1].isnan().all()) and bool(second.warm.position[0].isfinite().all())
    shifted = mpc.optimizer.shifted(result.warm.take(torch.tensor([0])), 0.1, later[:1, :2] - ego[:1, :2])
    torch.testing.assert_close(second.warm.position[0], shifted.position[0, [2, 0, 1]])  # goal by goal, by slot
    assert warm_starts.start(ids, later).warm is None  # the whole goal set: not what was kept


def test_the_safety_layer_warm_starts_its_decision_solves_and_a_new_episode_solves_cold():
    from mmpc.config import load_config
    from mmpc.rl.config import RLConfig
    from mmpc.rl.engine import SafeEnvs

    config = load_config(RLConfig, "cruise_task")
    scenario = config.scenario.replace(sim="batched", duration=0.6)  # 3 agent steps of 0.2 s
    assert scenario.mpc.warm_iterations == 10  # the shipped scenarios warm-start
    batch = SafeEnvs(2, scenario, config.env, config.reward, seed=0)
    batch.reset([5, 6])
    iterations = lambda: batch._decision.scored.result.iterations.float().mean(dim=1).tolist()
    assert min(iterations()) > 10  # the first decision: cold
    assert batch.layer.warm_starts.period == pytest.approx(0.2)  # one decision period: 2 frames of 0.1 s
    batch.advance([config.env.num_discrete_goals] * 2)  # both defer to the expert
    assert iterations() == [10.0, 10.0]
    batch.advance([config.env.num_discrete_goals] * 2)
    step = batch.advance([config.env.num_discrete_goals] * 2)  # the episodes end and start again
    assert sorted(step.reset_infos) == [0, 1] and min(iterations()) > 10


def test_take_goals_picks_each_problems_goals_in_the_order_asked(solved):
    optimizer, problem, cold = solved
    history = optimizer(problem, history=True)
    index = torch.tensor([[2, 0, 0], [1, 3, 2]])
    taken = history.take_goals(index)
    rows = torch.arange(2)[:, None]
    assert torch.equal(taken.feasible, history.feasible[rows, index])
    assert torch.equal(taken.trajectories.x, history.trajectories.x[rows, index])
    assert torch.equal(taken.warm.position, history.warm.position[rows, index])
    assert torch.equal(taken.history, history.history[:, rows, index])
    assert torch.equal(taken.trajectories.times, history.trajectories.times)


def test_the_safety_layers_frame_solves_start_from_the_solve_one_frame_before():
    """A frame solve (SafetyLayer.plan with an agent step's frame starts) starts warm from the same
    environment's solve one frame before: the decision's candidates at the first frame after it, then
    the frame before's; starts of their own (another agent step's) or after a frame without any
    solve start cold."""
    from mmpc.config import load_config
    from mmpc.rl.config import RLConfig
    from mmpc.rl.safety import SafetyLayer
    from mmpc.highway.batched_world import BatchedWorld

    config = load_config(RLConfig, "high_speed")
    scenario = config.scenario.replace(sim="batched")
    layer = SafetyLayer.for_scenario(scenario, dataclasses.replace(config.env, verify=False))
    warm_iterations = scenario.mpc.warm_iterations
    world = BatchedWorld.start(scenario, [11, 12])
    rows = [0, 1]
    observation, _ = world.observe(rows)
    solve = layer.decision_solve(observation)
    decided = layer.decide(solve, torch.tensor([4, 1]))
    assert decided.agent_index.tolist() == [4, 1]
    starts = layer.frame_starts(2, solve, decided.agent_index)
    world.apply(rows, decided.plan.acceleration, decided.plan.steering)
    observation, _ = world.observe(rows)
    longest = lambda safe: safe.plan.result.iterations.max(dim=1).values  # noqa: E731 (early exits stop some sooner)
    first = layer.plan(observation, decided.commands, starts)
    assert (longest(first) <= warm_iterations).all()  # from the decision's candidates
    world.apply(rows, first.plan.acceleration, first.plan.steering)
    observation, _ = world.observe(rows)
    other = layer.plan(observation, decided.commands, layer.frame_starts(2))  # another step's: nothing kept
    assert (longest(other) > warm_iterations).all()
    second = layer.plan(observation, decided.commands, starts)
    assert (longest(second) <= warm_iterations).all()  # from the first frame's solve, untouched by the other step
    starts.store.reset()  # what a frame without a solve does
    again = layer.plan(observation, decided.commands, starts)
    assert (longest(again) > warm_iterations).all()
    assert layer.frame_starts(2) is not None
    cold_layer = SafetyLayer.for_scenario(scenario.replace(mpc=dataclasses.replace(scenario.mpc, warm_iterations=0)),
                                          dataclasses.replace(config.env, verify=False))
    assert cold_layer.frame_starts(2) is None
