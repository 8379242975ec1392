"""Lane discipline: lane keeping in the optimizer's lateral cost (OptimizerConfig.lane_weight) and the
lane-change cost of the meta costs (hysteresis on the lane)."""

import pytest
import torch

import mmpc
from mmpc.solver.basis import bernstein_basis
from mmpc.solver.operators import build_operators, lane_keeping_profile, position_equality_matrix
from mmpc.solver.config import OptimizerConfig


def test_without_lane_keeping_both_axes_share_the_papers_matrices():
    operators = build_operators(bernstein_basis(10, 100, 8.0), OptimizerConfig(iterations=3))
    assert torch.equal(operators.position[:, :, 0], operators.position[:, :, 1])
    assert torch.equal(operators.position_init[0], operators.position_init[1])


def test_the_lateral_cold_start_solves_the_lane_keeping_qp():
    """position_init's y block equals a direct KKT solve of smoothness + lane keeping s.t. the boundary conditions."""
    config = OptimizerConfig(iterations=1, lane_weight=4.0, lane_settle_time=2.0)
    basis = bernstein_basis(config.order, config.num_steps, config.horizon)
    operators = build_operators(basis, config)
    equality = position_equality_matrix(basis, config.start_acceleration)
    b = torch.tensor([0.0, 0.3, -0.1, 4.0], dtype=torch.float64)  # start y, ydot, yddot; end y (relative) [m, m/s, m/s^2, m]
    weight = config.lane_weight * lane_keeping_profile(basis.times, config.lane_settle_time)
    hessian = config.weight_xy * basis.Pddot.T @ basis.Pddot + basis.P.T @ (weight[:, None] * basis.P)
    k, n_eq = hessian.shape[0], equality.shape[0]
    kkt = torch.zeros(k + n_eq, k + n_eq, dtype=torch.float64)
    kkt[:k, :k], kkt[:k, k:], kkt[k:, :k] = hessian, equality.T, equality
    rhs = torch.cat([basis.P.T @ weight * b[-1], b])
    expected = torch.linalg.solve(kkt, rhs)[:k]
    assert torch.allclose(operators.position_init[1] @ b, expected, atol=1e-9)
    assert lane_keeping_profile(basis.times, 2.0)[0] == 0 and lane_keeping_profile(basis.times, 2.0)[-1] == 1


def _lane_change(lane_weight: float) -> tuple[float, mmpc.SolveResult]:
    config = OptimizerConfig(ellipse_a=8.0, ellipse_b=3.3, heading_target_deg=11.7, lane_weight=lane_weight)
    optimizer = mmpc.BatchOptimizer(config, dtype=torch.float64)
    ego = mmpc.ego_state(0.0, 4.0, 0.0, 15.0).double()
    goals = torch.tensor([[[120.0, 8.0]]], dtype=torch.float64)
    result = optimizer(mmpc.ProblemBatch(ego, goals, torch.zeros(1, 0, config.num_steps, 2, dtype=torch.float64)))
    y, times = result.trajectories.y[0, 0], result.trajectories.times
    off = (y - 8.0).abs() > 0.5
    return float(times[off.nonzero().max() + 1]), result


def test_lane_keeping_completes_a_lane_change_early_and_stays_in_the_lane():
    settled_plain, plain = _lane_change(0.0)
    settled_kept, kept = _lane_change(5.0)
    assert bool(plain.feasible.all()) and bool(kept.feasible.all())
    assert settled_plain > 5.0 and settled_kept < 4.0  # within 0.5 m of the new lane's centre from then on
    y = kept.trajectories.y[0, 0]
    assert float((y - 8.0).abs()[kept.trajectories.times >= 5.0].max()) < 0.25  # a slight overshoot, no drift back
    # the longitudinal plan is the paper's: same distance covered to within the goal's end condition
    assert abs(float(kept.trajectories.x[0, 0, -1] - plain.trajectories.x[0, 0, -1])) < 1e-6 + 0.01


def test_lane_weight_must_be_non_negative():

    with pytest.raises(ValueError, match="lane_weight"):
        OptimizerConfig(lane_weight=-1.0)
    with pytest.raises(ValueError, match="lane_settle_time"):
        OptimizerConfig(lane_settle_time=0.0)


def _trajectories(y_start: float, y_end: float, v: float = 15.0) -> mmpc.Trajectories:
    """One problem, one candidate: y moving linearly from y_start to y_end at constant speed v."""
    times = torch.linspace(0.0, 8.0, 5)
    y = torch.linspace(y_start, y_end, 5)[None, None]
    full = lambda value: torch.full((1, 1, 5), value)  # noqa: E731
    return mmpc.Trajectories(times, full(0.0), y, full(0.0), full(v), full(v), full(0.0), full(0.0), full(0.0), full(0.0))


def test_lane_change_cost_charges_every_lane_between_start_and_end():
    from mmpc.meta_costs import CruiseCost, LaneChangeCost

    road, base = mmpc.Road(), CruiseCost(15.0)
    cost = LaneChangeCost(base, per_lane=20.0)
    assert float(cost(_trajectories(4.0, 4.0), road)) == float(base(_trajectories(4.0, 4.0), road)) == 0.0
    assert float(cost(_trajectories(4.0, 12.0), road)) == 40.0  # two lanes over
    assert float(cost(_trajectories(4.4, 5.9), road)) == 0.0  # drifting within lane 1
    # past the lane line the new lane is the current one: going back costs, finishing does not
    assert float(cost(_trajectories(6.2, 4.0), road)) == 20.0
    assert float(cost(_trajectories(6.2, 8.0), road)) == 0.0


def test_scenario_objectives_add_the_lane_change_cost_only_when_asked():
    from mmpc.meta_costs import CruiseCost, HighSpeedCost, LaneChangeCost
    from mmpc.scenario import CruiseObjective, HighSpeedObjective

    assert isinstance(CruiseObjective().meta_cost(), CruiseCost)  # the paper's by default
    assert isinstance(HighSpeedObjective().meta_cost(), HighSpeedCost)
    kept = HighSpeedObjective(lane_change_cost=50.0).meta_cost()
    assert isinstance(kept, LaneChangeCost) and kept.per_lane == 50.0
    with pytest.raises(ValueError, match="lane_change_cost"):
        CruiseObjective(lane_change_cost=-1.0)

