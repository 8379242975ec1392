import pytest
import torch

import mmpc


@pytest.fixture(scope="module")
def result() -> mmpc.SolveResult:
    """A real solve of one problem with four goals (free road); feasibility is set per test."""
    optimizer = mmpc.BatchOptimizer()
    goals = torch.tensor([[[120.0, 0.0], [120.0, 4.0], [120.0, 8.0], [120.0, 12.0]]])
    problem = mmpc.ProblemBatch(mmpc.ego_state(0.0, 8.0, 0.0, 15.0), goals, torch.zeros(1, 0, optimizer.config.num_steps, 2))
    return optimizer(problem)


def select(result, feasible, cost, **kwargs) -> mmpc.Selection:
    return mmpc.select_best(result._replace(feasible=torch.tensor([feasible])), torch.tensor([cost]),
                            mmpc.OptimizerConfig(), **kwargs)


def test_the_lowest_feasible_cost_wins_without_a_preference(result):
    chosen = select(result, [True, True, False, True], [5.0, 3.0, 1.0, 3.01])
    assert int(chosen.index[0]) == 1 and float(chosen.cost[0]) == 3.0 and bool(chosen.feasible[0])


def test_a_tie_goes_to_the_preferred_candidate(result):
    lateral_move = torch.tensor([[8.0, 4.0, 0.0, 4.0]])
    cost = [100.0, 100.5, 100.9, 98.0]  # band: 98 + 0.98 + 2 = 100.98 holds all four
    band = dict(preference=lateral_move, tie_tolerance=0.01, tie_margin=2.0)
    chosen = select(result, [True, True, True, True], cost, **band)
    assert int(chosen.index[0]) == 2 and float(chosen.cost[0]) == pytest.approx(100.9)
    assert int(select(result, [True, True, False, True], cost, **band).index[0]) == 1  # never the infeasible; first of equals
    narrow = dict(preference=lateral_move, tie_tolerance=0.01, tie_margin=0.0)  # band 0.98: only 98 itself
    assert int(select(result, [True, True, True, True], cost, **narrow).index[0]) == 3


def test_without_a_feasible_candidate_the_preference_is_ignored(result):
    chosen = select(result, [False] * 4, [1.0, 2.0, 3.0, 4.0], violation=torch.tensor([[3.0, 1.0, 2.0, 4.0]]),
                    preference=torch.tensor([[0.0, 9.0, 9.0, 9.0]]), tie_tolerance=1.0)
    assert int(chosen.index[0]) == 1 and not bool(chosen.feasible[0])


@pytest.mark.parametrize("kwargs, message", [
    (dict(preference=torch.zeros(1, 3)), "preference"),
    (dict(preference=torch.zeros(1, 4), tie_tolerance=-0.1), "tie_tolerance"),
    (dict(preference=torch.zeros(1, 4), tie_margin=float("nan")), "tie_margin"),
])
def test_bad_tie_arguments_are_refused(result, kwargs, message):
    with pytest.raises(ValueError, match=message):
        select(result, [True] * 4, [1.0, 2.0, 3.0, 4.0], **kwargs)


def test_the_mpc_keeps_its_lane_when_the_lanes_cost_the_same():
    # Free road at the cruise speed: the lane-centre goals cost nearly the same, and the MPC's
    # tie-break keeps the ego's lane instead of the numerically cheapest lane change.
    optimizer = mmpc.BatchOptimizer()
    goals = lambda ego, road: torch.tensor([[[120.0, 0.0], [120.0, 4.0], [120.0, 8.0], [120.0, 12.0]]])  # noqa: E731
    ego = mmpc.ego_state(0.0, 8.0, 0.0, 15.0)
    plans = {
        margin: mmpc.MPC(optimizer, goals, mmpc.CruiseCost(15.0), mmpc.Road(num_lanes=4),
                         mmpc.MPCConfig(tie_tolerance=0.0, tie_margin=margin, stop_lanes=None)).plan(ego, torch.zeros(1, 0, 4))
        for margin in (0.0, 1.0)
    }
    cost = plans[1.0].cost[0]
    assert float(cost.max() - cost.min()) < 1.0  # all four within the margin
    assert int(plans[1.0].selection.index[0]) == 2
    assert int(plans[0.0].selection.index[0]) == int(cost.argmin())
