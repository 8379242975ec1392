"""Invariants of the batch solve (hypothesis)."""

import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import mmpc
from tests.conftest import small_config

CONFIG = small_config()
OPT64 = mmpc.BatchOptimizer(CONFIG, dtype=torch.float64)
OPT32 = mmpc.BatchOptimizer(CONFIG, dtype=torch.float32)


@st.composite
def problems(draw, max_problems=3, max_goals=4):
    """Random batches with per-problem obstacle counts (mask) and mixed goals."""
    e = draw(st.integers(1, max_problems))
    g = draw(st.integers(1, max_goals))
    m = draw(st.integers(0, CONFIG.max_obstacles))
    seed = draw(st.integers(0, 2**31 - 1))
    gen = torch.Generator().manual_seed(seed)

    def rand(*shape):
        return torch.rand(*shape, generator=gen, dtype=torch.float64)

    ego = mmpc.ego_state(
        rand(e) * 100, 4.0 * torch.randint(0, 4, (e,), generator=gen), (rand(e) - 0.5) * 0.1,
        8 + 10 * rand(e), (rand(e) - 0.5), (rand(e) - 0.5) * 0.05, dtype=torch.float64,
    )
    goals = torch.stack(
        [ego[:, None, 0] + 60 + 80 * rand(e, g), 4.0 * torch.randint(0, 4, (e, g), generator=gen)], -1
    )
    states = torch.stack(
        [ego[:, None, 0] + 15 + 100 * rand(e, m), 4.0 * torch.randint(0, 4, (e, m), generator=gen),
         5 + 10 * rand(e, m), torch.zeros(e, m, dtype=torch.float64)], -1
    )
    obstacles = mmpc.predict_constant_velocity(states, OPT64.times)
    mask = rand(e, m) < 0.7
    return mmpc.ProblemBatch(ego, goals, obstacles, mask)


def _fields(result):
    return [*result.trajectories[1:], result.coefficients, result.residual_obstacle,
            result.residual_nonholonomic, result.min_obstacle_distance, result.status]


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(problems())
def test_batch_equals_each_element_alone(problem):
    batched = OPT64(problem)
    for e in range(problem.ego.shape[0]):
        for g in range(problem.goals.shape[1]):
            alone = OPT64(mmpc.ProblemBatch(
                problem.ego[e : e + 1], problem.goals[e : e + 1, g : g + 1],
                problem.obstacles[e : e + 1], problem.obstacle_mask[e : e + 1],
            ))
            for full, single in zip(_fields(batched), _fields(alone)):
                torch.testing.assert_close(full[e, g], single[0, 0], atol=1e-6, rtol=1e-6)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(problems(), st.randoms(use_true_random=False))
def test_permuting_the_batch_permutes_the_result(problem, rng):
    e, g = problem.goals.shape[:2]
    pe = torch.tensor(rng.sample(range(e), e))
    pg = torch.tensor(rng.sample(range(g), g))
    permuted = mmpc.ProblemBatch(problem.ego[pe], problem.goals[pe][:, pg], problem.obstacles[pe],
                                 problem.obstacle_mask[pe])
    reference, result = OPT64(problem), OPT64(permuted)
    for ref, out in zip(_fields(reference), _fields(result)):
        torch.testing.assert_close(out, ref[pe][:, pg], atol=1e-6, rtol=1e-6)


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(problems())
def test_absent_obstacles_change_nothing(problem):
    """Masked slots (here filled with NaN) give the same answer as removing them."""
    for e in range(problem.ego.shape[0]):
        mask = problem.obstacle_mask[e]
        obstacles = problem.obstacles[e : e + 1].clone()
        obstacles[:, ~mask] = float("nan")
        masked = OPT64(mmpc.ProblemBatch(problem.ego[e : e + 1], problem.goals[e : e + 1], obstacles, mask[None]))
        removed = OPT64(mmpc.ProblemBatch(problem.ego[e : e + 1], problem.goals[e : e + 1],
                                          problem.obstacles[e : e + 1, mask]))
        for a, b in zip(_fields(masked), _fields(removed)):
            torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-6)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(problems())
def test_dtype_is_preserved_and_bounds_hold(problem):
    for opt in (OPT32, OPT64):
        result = opt(problem)  # float64 inputs are cast to the module dtype
        for field in result.trajectories:
            assert field.dtype == opt.dtype and field.isfinite().all()
        assert (result.trajectories.v >= CONFIG.v_min).all() and (result.trajectories.v <= CONFIG.v_max).all()
        assert result.status.dtype == torch.int32
        assert torch.equal(result.feasible, result.status == 0)
