"""mmpc.tracking: sampling, tracking and checking a held plan."""

import math

import pytest
import torch

import mmpc
from mmpc.config import ConfigError
from mmpc.obstacles.prediction import predict_constant_velocity
from mmpc.result import Trajectories
from mmpc.tracking import TrackingConfig, needs_replan, plan_clearance, sample, track

TIMES = torch.linspace(0.0, 8.0, 101, dtype=torch.float64)
ELLIPSE = (8.0, 3.0)


def straight(x0: float, y0: float, speed: float, count: int = 1) -> Trajectories:
    """``count`` identical plans driving along the road at constant speed."""
    x = (x0 + speed * TIMES).expand(count, -1)
    zeros = torch.zeros_like(x)
    return Trajectories(TIMES, x, zeros + y0, zeros, zeros + speed, zeros + speed, zeros, zeros, zeros, zeros)


def predict(states: torch.Tensor, times: torch.Tensor) -> torch.Tensor:
    return predict_constant_velocity(states, times)


def test_sample_interpolates_between_samples_and_clamps_to_the_horizon():
    plan = straight(10.0, 4.0, 20.0)
    at = torch.tensor([[0.0, 0.08, 0.1, 3.33, 8.0, 9.5]], dtype=torch.float64)
    picked = sample(plan, at)
    expected = 10.0 + 20.0 * at.clamp(max=8.0)
    torch.testing.assert_close(picked.x, expected)
    torch.testing.assert_close(picked.times, at.clamp(max=8.0))
    assert picked.y.shape == (1, 6) and bool((picked.y == 4.0).all())


def test_sample_returns_the_samples_at_the_plan_times():
    plan = straight(0.0, 0.0, 10.0)
    wavy = plan._replace(y=torch.sin(TIMES)[None])
    picked = sample(wavy, TIMES[None])
    torch.testing.assert_close(picked.y, wavy.y)


def test_clearance_of_a_car_ahead_at_the_same_speed_is_its_distance_over_a():
    plan = straight(0.0, 4.0, 20.0, count=2)
    cars = torch.tensor([[[40.0, 4.0, 20.0, 0.0]], [[40.0, 4.0, 20.0, 0.0]]], dtype=torch.float64)
    mask = torch.tensor([[True], [False]])
    clearance = plan_clearance(plan, torch.zeros(2, dtype=torch.float64), cars, mask, predict, ELLIPSE)
    assert clearance[0].item() == pytest.approx(40.0 / 8.0)
    assert math.isinf(clearance[1].item())  # a masked slot does not count


def test_clearance_follows_the_plan_from_where_it_has_got_to():
    # 0.5 s into a 20 m/s plan the ego is 10 m on; a car 16 m ahead of the plan's start, driving
    # at 20 m/s too, is 6 m ahead of the ego now and stays so: the rest of the plan is 6 / 8.
    plan = straight(0.0, 4.0, 20.0)
    car = torch.tensor([[[16.0, 4.0, 20.0, 0.0]]], dtype=torch.float64)
    clearance = plan_clearance(plan, torch.tensor([0.5], dtype=torch.float64), car, torch.tensor([[True]]), predict, ELLIPSE)
    assert clearance.item() == pytest.approx(6.0 / 8.0)
    assert bool(needs_replan(clearance, torch.zeros(1), torch.zeros(1), 0.01, TrackingConfig()))


def test_clearance_without_obstacles_is_infinite():
    plan = straight(0.0, 4.0, 20.0, count=3)
    clearance = plan_clearance(plan, torch.zeros(3, dtype=torch.float64), torch.zeros(3, 0, 4, dtype=torch.float64),
                               torch.zeros(3, 0, dtype=torch.bool), predict, ELLIPSE)
    assert bool(torch.isinf(clearance).all())


def test_an_ego_on_the_plan_gets_the_plans_own_commands():
    optimizer = mmpc.BatchOptimizer(dtype=torch.float64, compile=False)
    ego = mmpc.ego_state(0.0, 4.0, 0.0, 20.0, dtype=torch.float64)
    goals = torch.tensor([[[170.0, 8.0]]], dtype=torch.float64)  # a lane change to the right
    problem = mmpc.ProblemBatch(ego, goals, torch.zeros(1, 0, optimizer.times.numel(), 2, dtype=torch.float64))
    plan = optimizer(problem).trajectories.select(torch.zeros(1, dtype=torch.long))
    elapsed = torch.tensor([1.2], dtype=torch.float64)
    at = sample(plan, elapsed[:, None])
    speed = torch.hypot(at.xdot, at.ydot)[:, 0]
    on_plan = torch.stack([at.x[:, 0], at.y[:, 0], at.psi[:, 0], speed, at.xddot[:, 0] * 0, at.psidot[:, 0]], dim=1)
    acceleration, heading_rate, lateral, speed_error = track(plan, elapsed, on_plan, 0.3, TrackingConfig())
    assert abs(lateral.item()) < 1e-9 and abs(speed_error.item()) < 1e-9
    window = sample(plan, elapsed[:, None] + torch.linspace(0.0, 0.3, 4, dtype=torch.float64)[None])
    assert heading_rate.item() == pytest.approx(window.psidot.mean().item(), abs=1e-6)
    tangential = (window.xdot * window.xddot + window.ydot * window.yddot) / torch.hypot(window.xdot, window.ydot)
    assert acceleration.item() == pytest.approx(tangential.mean().item(), abs=1e-6)


def test_feedback_turns_back_towards_the_plan_and_matches_its_speed():
    plan = straight(0.0, 4.0, 20.0)
    elapsed = torch.tensor([0.5], dtype=torch.float64)
    # the ego is 0.3 m to the left (smaller y) of the plan and 1 m/s slow
    ego = torch.tensor([[10.0, 3.7, 0.0, 19.0, 0.0, 0.0]], dtype=torch.float64)
    acceleration, heading_rate, lateral, speed_error = track(plan, elapsed, ego, 0.3, TrackingConfig())
    assert lateral.item() == pytest.approx(0.3) and speed_error.item() == pytest.approx(1.0)
    assert heading_rate.item() > 0.0  # towards larger y
    assert acceleration.item() == pytest.approx(1.0)  # speed_gain 1/s x 1 m/s


def test_a_tracked_plan_is_followed_by_a_kinematic_bicycle():
    # highway-env's bicycle driven by the tracker over 0.5 s of a lane-change plan stays on it
    optimizer = mmpc.BatchOptimizer(dtype=torch.float64, compile=False)
    ego = mmpc.ego_state(0.0, 4.0, 0.0, 20.0, dtype=torch.float64)
    problem = mmpc.ProblemBatch(ego, torch.tensor([[[165.0, 8.0]]], dtype=torch.float64),
                                torch.zeros(1, 0, optimizer.times.numel(), 2, dtype=torch.float64))
    plan = optimizer(problem).trajectories.select(torch.zeros(1, dtype=torch.long))
    mpc = mmpc.MPC(optimizer, mmpc.CruiseGoals(horizon=optimizer.config.horizon), mmpc.CruiseCost(), mmpc.Road())
    state = ego.clone()
    length, dt = 5.0, 0.1
    for frame in range(5):
        elapsed = torch.tensor([frame * dt], dtype=torch.float64)
        acceleration, heading_rate, lateral, speed_error = track(plan, elapsed, state, 0.3, TrackingConfig())
        assert abs(lateral.item()) < 0.1 and abs(speed_error.item()) < 0.2
        steering = mpc.steering(state, heading_rate)
        x, y, psi, v = state[0, :4].tolist()
        beta = math.atan(0.5 * math.tan(steering.item()))
        state = torch.tensor([[x + v * math.cos(psi + beta) * dt, y + v * math.sin(psi + beta) * dt,
                               psi + v * math.sin(beta) / (length / 2) * dt, v + acceleration.item() * dt,
                               acceleration.item(), heading_rate.item()]], dtype=torch.float64)


def test_replan_when_the_ego_leaves_the_plan():
    config = TrackingConfig(max_lateral_error=0.5, max_speed_error=1.0)
    far = torch.full((3,), 2.0)
    lateral = torch.tensor([0.6, 0.1, 0.0])
    speed = torch.tensor([0.0, -1.5, 0.2])
    assert needs_replan(far, lateral, speed, 0.01, config).tolist() == [True, True, False]


@pytest.mark.parametrize("field", ["speed_gain", "heading_gain", "lateral_gain", "max_lateral_error", "max_speed_error"])
def test_tracking_config_refuses_non_positive_values(field):
    with pytest.raises(ConfigError, match=field):
        TrackingConfig(**{field: 0.0})
