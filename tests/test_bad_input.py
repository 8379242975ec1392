"""Bad input gets a clear error or a flagged result, never a NaN."""

import pytest
import torch

import mmpc
from mmpc import ProblemBatch, Status
from tests.conftest import small_config

OPT = mmpc.BatchOptimizer(small_config())
N = OPT.config.num_steps


def good(e=2, g=3, m=2):
    ego = mmpc.ego_state(torch.zeros(e), torch.full((e,), 4.0), torch.zeros(e), torch.full((e,), 14.0))
    goals = torch.stack([torch.full((e, g), 110.0), 4.0 * torch.arange(g).float().expand(e, g)], -1)
    states = torch.tensor([[60.0, 0.0, 12.0, 0.0], [70.0, 8.0, 9.0, 0.0]])[:m].expand(e, m, 4)
    return ProblemBatch(ego, goals, mmpc.predict_constant_velocity(states, OPT.times))


def assert_finite(result):
    for field in [*result.trajectories, result.coefficients, result.residual_obstacle,
                  result.residual_acceleration, result.residual_nonholonomic]:
        assert not field.isnan().any()


def test_good_input_is_feasible():
    result = OPT(good())
    assert result.feasible.all() and result.trajectories.x.shape == (2, 3, N)


@pytest.mark.parametrize("field, index", [("ego", (0, 1)), ("goals", (1, 2, 0)), ("obstacles", (0, 1, 5, 1))])
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_values_are_rejected_by_name(field, index, bad):
    problem = good()
    tensor = getattr(problem, field).clone()
    tensor[index] = bad
    with pytest.raises(ValueError, match=f"`{field}` contains NaN or inf"):
        OPT(problem._replace(**{field: tensor}))


@pytest.mark.parametrize(
    "field, shape, message",
    [("ego", (2, 4), r"`ego` must have shape \(E, 6\)"), ("ego", (6,), r"`ego` must have shape"),
     ("goals", (2, 3, 3), r"`goals` must have shape \(2, G, 2\)"), ("goals", (3, 3, 2), r"`goals` must have shape"),
     ("obstacles", (2, 2, N + 1, 2), rf"`obstacles` must have shape \(2, M, {N}, 2\)")],
)
def test_wrong_shapes_name_argument_and_expected_shape(field, shape, message):
    with pytest.raises(ValueError, match=message):
        OPT(good()._replace(**{field: torch.zeros(shape)}))


def test_wrong_types_and_dtypes():
    with pytest.raises(TypeError, match="`ego` must be a torch.Tensor"):
        OPT(good()._replace(ego=[[0.0] * 6]))
    with pytest.raises(TypeError, match="`goals` must be a floating tensor"):
        OPT(good()._replace(goals=good().goals.long()))
    with pytest.raises(TypeError, match="`obstacle_mask` must be a bool tensor"):
        OPT(good()._replace(obstacle_mask=torch.ones(2, 2)))
    with pytest.raises(TypeError, match="ProblemBatch"):
        OPT((good().ego, good().goals, good().obstacles))


def test_wrong_device_is_an_error():
    problem = good()
    with pytest.raises(ValueError, match="`goals` is on meta but the optimizer is on cpu"):
        OPT(problem._replace(goals=problem.goals.to("meta")))


def test_empty_batches_are_errors():
    with pytest.raises(ValueError, match="empty batch: `ego`"):
        OPT(ProblemBatch(torch.zeros(0, 6), torch.zeros(0, 3, 2), torch.zeros(0, 0, N, 2)))
    with pytest.raises(ValueError, match="empty batch: `goals`"):
        OPT(good()._replace(goals=torch.zeros(2, 0, 2)))


def test_too_many_obstacle_slots():
    with pytest.raises(ValueError, match="max_obstacles=4"):
        OPT(good()._replace(obstacles=torch.zeros(2, 5, N, 2)))


def test_no_obstacles_is_fine():
    result = OPT(good(m=0))
    assert result.feasible.all()
    assert torch.isinf(result.min_obstacle_distance).all()
    assert (result.residual_obstacle == 0).all()


def test_negative_speed_is_rejected():
    problem = good()
    ego = problem.ego.clone()
    ego[1, 3] = -2.0
    with pytest.raises(ValueError, match=r"ego speed `v` must be >= 0 m/s; got \[-2.0\] in problem\(s\) \[1\]"):
        OPT(problem._replace(ego=ego))


def test_goal_behind_is_flagged():
    problem = good()
    goals = problem.goals.clone()
    goals[0, 1, 0] = -20.0
    result = OPT(problem._replace(goals=goals))
    assert result.status[0, 1] & Status.GOAL_BEHIND and not result.feasible[0, 1]
    assert result.feasible[0, 0] and result.feasible[1].all()
    assert_finite(result)


def test_start_inside_obstacle_is_flagged():
    problem = good(m=1)
    states = torch.tensor([[[1.0, 4.2, 14.0, 0.0]]]).expand(2, 1, 4)  # on top of the ego
    result = OPT(problem._replace(obstacles=mmpc.predict_constant_velocity(states, OPT.times)))
    assert (result.status & Status.START_IN_COLLISION).all() and not result.feasible.any()
    assert_finite(result)


def test_obstacle_exactly_at_ego_centre_stays_finite():
    problem = good(m=1)
    states = torch.tensor([[[0.0, 4.0, 14.0, 0.0]]]).expand(2, 1, 4)
    result = OPT(problem._replace(obstacles=mmpc.predict_constant_velocity(states, OPT.times)))
    assert not result.feasible.any()
    assert_finite(result)


def test_overflowing_input_is_flagged_numerical_with_finite_output():
    problem = good()
    goals = problem.goals.clone()
    goals[1, 0, 0] = 3e38  # finite, but the iterations overflow float32
    result = OPT(problem._replace(goals=goals))
    assert result.status[1, 0] & Status.NUMERICAL
    assert result.feasible[0].all()
    assert_finite(result)


def test_status_describe():
    assert Status.describe(0) == "OK"
    assert Status.describe(int(Status.OBSTACLE | Status.HEADING)) == "OBSTACLE|HEADING"
