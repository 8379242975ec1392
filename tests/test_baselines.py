"""Baselines: the CasADi/IPOPT NLP (constraints checked independently of CasADi), the Frenet
polynomials, every baseline driving a scripted scene, and the batch NLP's ranking."""

import math

import numpy as np
import pytest
import torch

from mmpc.config import from_dict
from mmpc.drivers.batch_nlp import BatchNLPDriver, BatchNLPSolver, goal_subset
from mmpc.drivers.common import obstacles_for
from mmpc.drivers.frenet import FrenetConfig, FrenetPlanner, evaluate_polynomial, quartic_coefficients, quintic_coefficients
from mmpc.drivers.nlp import SOLVED_STATUSES, NLPConfig, TrajectoryNLP, resample
from mmpc.highway.runner import run_episode
from mmpc.drivers import Observation, make_driver
from mmpc.scenario import EgoConfig, ScenarioConfig, build_mpc
from mmpc.traffic_config import ScriptedTraffic, ScriptedVehicle

pytestmark = pytest.mark.usefixtures("one_thread")


def scripted(vehicles, *, lanes=3, ego_lane=1, ego_speed=15.0, duration=3.0) -> ScenarioConfig:
    return ScenarioConfig(
        name="scene", lanes=lanes, duration=duration, ego=EgoConfig(speed=ego_speed, lane=ego_lane),
        traffic=ScriptedTraffic(tuple(ScriptedVehicle(*v) for v in vehicles)),
    )


#: A slow car 30 m ahead in the ego's lane and one beside, behind.
SCENE = [(1, 30.0, 8.0), (2, -10.0, 14.0)]


def _rk4(state, control, dt):
    def f(s):
        return np.array([s[3] * math.cos(s[2]), s[3] * math.sin(s[2]), s[5], s[4], control[0], control[1]])

    k1 = f(state)
    k2 = f(state + 0.5 * dt * k1)
    k3 = f(state + 0.5 * dt * k2)
    k4 = f(state + dt * k3)
    return state + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def test_standard_mpc_nlp_solution_satisfies_its_constraints():
    scenario = scripted(SCENE)
    mpc = build_mpc(scenario)
    cfg = scenario.optimizer
    stage = lambda v, y: scenario.objective.stage_cost(v, y, scenario.road)  # noqa: E731
    nlp = TrajectoryNLP(cfg, scenario.road, scenario.mpc.road_margin, scenario.mpc.num_obstacles, stage_cost=stage)
    ego = torch.tensor([[0.0, 4.0, 0.0, 15.0, 0.0, 0.0]], dtype=torch.float64)
    vehicles = torch.tensor([[[30.0, 4.0, 8.0, 0.0], [-10.0, 8.0, 14.0, 0.0]]], dtype=torch.float64)
    obstacles, mask = obstacles_for(mpc, ego, vehicles, None, torch.as_tensor(nlp.times))
    solution = nlp.solve(ego[0].numpy(), obstacles[0].numpy(), mask[0].numpy())
    assert solution.status in SOLVED_STATUSES and solution.feasible and solution.violation < 1e-6

    s, u = solution.states, solution.controls
    np.testing.assert_allclose(s[0], ego[0].numpy())
    for k in range(nlp.config.intervals):  # the dynamics, integrated here without CasADi
        np.testing.assert_allclose(s[k + 1], _rk4(s[k], u[k], nlp.dt), atol=1e-6)
    present = obstacles[0][mask[0]].numpy()  # (2, K+1, 2)
    distance = np.hypot((s[None, 1:, 0] - present[:, 1:, 0]) / cfg.ellipse_a, (s[None, 1:, 1] - present[:, 1:, 1]) / cfg.ellipse_b)
    assert distance.min() >= 1.0 - 1e-6
    assert np.all(s[1:, 4] ** 2 + (s[1:, 3] * s[1:, 5]) ** 2 <= cfg.a_max**2 + 1e-6)
    assert np.all((s[1:, 3] >= cfg.v_min - 1e-6) & (s[1:, 3] <= cfg.v_max + 1e-6))
    assert np.abs(s[1:, 2]).max() <= math.radians(cfg.max_heading_deg) + 1e-6
    left, right = scenario.road.bounds
    assert s[:, 1].min() >= left + scenario.mpc.road_margin - 1e-6 and s[:, 1].max() <= right - scenario.mpc.road_margin + 1e-6
    assert abs(s[-1, 2]) < 1e-6 and abs(s[-1, 5]) < 1e-6
    # The slow car blocks the lane: the meta cost (v - 15)^2 makes the plan overtake, not follow.
    assert abs(s[-1, 1] - 4.0) > 2.0 and s[-1, 0] > 30.0 + 8.0 * nlp.times[-1]
    # The recomputed check catches a violation: move the slow car onto the solution.
    moved = obstacles[0].numpy().copy()
    moved[0, :, :] = s[:, :2]
    params = nlp.parameters(moved, mask[0].numpy(), None)
    assert nlp.constraint_values(solution.primal, params)["obstacle"].min() < 1.0
    assert nlp.violation(solution.primal, params, *nlp.bounds(ego[0].numpy())) > 0.5


def test_goal_nlp_reaches_its_goal_and_the_warm_start_shift_holds_the_end():
    scenario = scripted([])
    nlp = TrajectoryNLP(scenario.optimizer, scenario.road, 1.0, 2)
    ego = np.array([0.0, 4.0, 0.0, 14.0, 0.0, 0.0])
    none = np.zeros((2, nlp.config.intervals + 1, 2))
    solution = nlp.solve(ego, none, np.zeros(2, dtype=bool), np.array([115.0, 8.0]))
    assert solution.status in SOLVED_STATUSES and solution.feasible
    np.testing.assert_allclose(solution.states[-1, :2], [115.0, 8.0], atol=1e-6)
    shifted = nlp.shift(solution, 0.1).reshape(-1)[: 6 * (nlp.config.intervals + 1)].reshape(-1, 6)
    np.testing.assert_allclose(shifted[-1], solution.states[-1])
    assert shifted[0, 0] == pytest.approx(np.interp(0.1, nlp.times, solution.states[:, 0]))


def test_frenet_polynomials_meet_their_boundary_conditions():
    start = torch.tensor([[4.0, 1.5, -0.8], [0.0, 0.0, 0.0]], dtype=torch.float64)
    end = torch.tensor([[12.0, 0.0, 0.0], [-4.0, 0.0, 0.0]], dtype=torch.float64)
    duration = torch.tensor([4.0, 2.5], dtype=torch.float64)
    quintic = quintic_coefficients(start, end, duration)
    at_zero = torch.stack(evaluate_polynomial(quintic, torch.zeros(2, 1, dtype=torch.float64)), dim=-1)[:, 0]
    at_end = torch.stack(evaluate_polynomial(quintic, duration[:, None]), dim=-1)[:, 0]
    torch.testing.assert_close(at_zero, start)
    torch.testing.assert_close(at_end, end)

    s_start = torch.tensor([[10.0, 14.0, 1.0]], dtype=torch.float64)
    quartic = quartic_coefficients(s_start, torch.tensor([20.0], dtype=torch.float64), torch.tensor([0.0], dtype=torch.float64),
                                   torch.tensor([5.0], dtype=torch.float64))
    value, rate, second = evaluate_polynomial(quartic, torch.tensor([[0.0, 5.0]], dtype=torch.float64))
    torch.testing.assert_close(torch.stack([value[0, 0], rate[0, 0], second[0, 0]]), s_start[0])
    assert rate[0, 1].item() == pytest.approx(20.0) and second[0, 1].item() == pytest.approx(0.0, abs=1e-9)


def test_frenet_candidates_hold_their_end_state_and_the_filters_bite():
    scenario = scripted(SCENE)
    mpc = build_mpc(scenario)
    planner = FrenetPlanner(mpc, scenario.objective.top_speed)
    assert planner.config.num_candidates == 11 * 6 * 8
    ego = torch.tensor([[0.0, 4.0, 0.0, 15.0, 0.0, 0.0]])
    trajectories = planner.candidates(ego)
    assert trajectories.x.shape == (1, planner.offsets.numel() * 6 * 8, mpc.optimizer.config.num_steps)
    # The first candidate: T = 3 s, offset 0 (leftmost lane), slowest speed; after T it holds.
    late = mpc.optimizer.times > 3.0 + 1e-6
    assert torch.allclose(trajectories.y[0, 0, late], torch.zeros(()), atol=1e-4)
    assert torch.allclose(trajectories.v[0, 0, late], planner.speeds[0], atol=1e-4)
    assert torch.allclose(trajectories.x[0, :, 0], torch.zeros(()), atol=1e-5)
    vehicles = torch.tensor([[[30.0, 4.0, 8.0, 0.0], [-10.0, 8.0, 14.0, 0.0]]])
    obstacles, mask = obstacles_for(mpc, ego, vehicles, None, trajectories.times)
    feasible = planner.feasible(ego, trajectories, obstacles, mask)
    assert 0 < int(feasible.sum()) < feasible.numel()
    # Staying in the lane at speed would run into the slow car: no such candidate passes.
    keep_lane_fast = (trajectories.y[0, :, -1] - 4.0).abs() < 0.5
    keep_lane_fast &= trajectories.v[0, :, -1] > 12.0
    assert not torch.any(feasible[0] & keep_lane_fast)


@pytest.mark.parametrize("spec,duration", [("frenet", 3.0), ("standard-mpc", 3.0), ("batch-nlp:6,1", 1.0)])
def test_baseline_drivers_drive_a_scripted_scene_without_collision(spec, duration):
    scenario = scripted(SCENE, duration=duration)
    driver = make_driver(spec, scenario)
    try:
        result = run_episode(scenario, seed=0, driver=driver)
    finally:
        getattr(driver, "close", lambda: None)()
    assert result.metrics["collisions"] == 0 and result.metrics["steps"] == round(duration * 10)
    assert all(math.isfinite(r.command_acceleration) and math.isfinite(r.command_steering) for r in result.records)
    assert result.metrics["fallback_steps"] == 0
    assert all(r.feasible_goals >= 1 and math.isfinite(r.plan_cost) for r in result.records)


def test_batch_nlp_ranks_by_the_same_meta_cost_as_ours():
    scenario = scripted([], lanes=6, ego_lane=2, ego_speed=14.0)
    mpc = build_mpc(scenario)
    solver = BatchNLPSolver(mpc, workers=0)
    driver = BatchNLPDriver(mpc, batch=6, solver=solver)
    ego = torch.tensor([[0.0, 8.0, 0.0, 14.0, 0.0, 0.0]])
    observation = Observation(ego, torch.zeros(1, 0, 4))
    decision = driver.decide(observation)
    plan = mpc.plan(ego, torch.zeros(1, 0, 4))
    subset = goal_subset(mpc.goal_sampler(ego, mpc.road).shape[1], 6)  # the sampler's goals (ours add stop goals after them)
    torch.testing.assert_close(decision.candidates.goals[0], plan.problem.goals[0, subset])
    # Same goals, same verdicts where the problem is clear-cut (the slowest near-lane goals, which
    # need about a_max to reach, may fall either side of the tolerance), and the same choice.
    both = decision.candidates.feasible[0] & plan.result.feasible[0, subset]
    assert int(both.sum()) >= 3
    ours = plan.cost[0, subset]
    best_of_both = int(torch.where(both, ours, torch.full_like(ours, float("inf"))).argmin())
    assert int(decision.goal_index[0]) == best_of_both
    # Comparable trajectories: the same end points and meta costs within 10 %.
    np.testing.assert_allclose(decision.candidates.xy[0, both, -1].numpy(), plan.problem.goals[0, subset][both].numpy(), atol=1e-3)
    goal = plan.problem.goals[0, subset[best_of_both]].double().numpy()
    states = solver.local.solve(ego[0].double().numpy(), np.zeros((6, 41, 2)), np.zeros(6, dtype=bool), goal).states
    theirs = mpc.meta_cost(resample(states[None], solver.times, mpc.optimizer.times.double()), mpc.road)
    assert float(decision.plan_cost[0]) == pytest.approx(float(theirs[0]), rel=1e-5)
    assert float(theirs[0]) == pytest.approx(float(ours[best_of_both]), rel=0.1, abs=5.0)


def test_bad_input_errors():
    scenario = scripted([])
    with pytest.raises(ValueError, match="B or B,W"):
        make_driver("batch-nlp:many", scenario)
    with pytest.raises(ValueError, match=r"batch size must be an int in \[1, "):
        make_driver("batch-nlp:500,1", scenario)
    with pytest.raises(ValueError, match="takes no argument"):
        make_driver("frenet:x", scenario)
    with pytest.raises(ValueError, match="takes no argument"):
        make_driver("standard-mpc:x", scenario)
    with pytest.raises(ValueError, match="durations"):
        FrenetConfig(durations=(3.0, -1.0))
    with pytest.raises(ValueError, match="max_heading_deg"):
        FrenetConfig(max_heading_deg=95.0)
    with pytest.raises(ValueError, match="unknown key"):
        from_dict(NLPConfig, {"interval": 10})
    with pytest.raises(ValueError, match="intervals"):
        NLPConfig(intervals=1)
    mpc = build_mpc(scenario)
    with pytest.raises(ValueError, match="durations"):
        FrenetPlanner(mpc, 15.0, FrenetConfig(durations=(9.0,)))
    nlp = TrajectoryNLP(scenario.optimizer, scenario.road, 1.0, 2)
    ego = np.array([0.0, 4.0, 0.0, 14.0, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"`obstacles` must have shape \(2, 41, 2\)"):
        nlp.solve(ego, np.zeros((3, 41, 2)), np.zeros(3, dtype=bool), np.array([100.0, 4.0]))
    with pytest.raises(ValueError, match="finite `goal`"):
        nlp.solve(ego, np.zeros((2, 41, 2)), np.zeros(2, dtype=bool), None)
    with pytest.raises(ValueError, match="`ego` must be a finite array"):
        nlp.solve(ego * np.nan, np.zeros((2, 41, 2)), np.zeros(2, dtype=bool), np.array([100.0, 4.0]))
    frenet = make_driver("frenet", scenario)
    bad = torch.tensor([[0.0, float("nan"), 0.0, 14.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="finite"):
        frenet.decide(Observation(bad, torch.zeros(1, 0, 4)))
