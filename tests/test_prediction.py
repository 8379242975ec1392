import pytest
import torch

import mmpc

ROAD = mmpc.Road(num_lanes=6, lane_width=4.0)  # centres 0, 4, ..., 20
TIMES = torch.linspace(0.0, 8.0, 41)


def lateral(y: float, vy: float) -> torch.Tensor:
    """(N,) predicted y of one vehicle at (x, y) = (0, y) moving at (10, vy) m/s."""
    states = torch.tensor([[[0.0, y, 10.0, vy]]])
    return mmpc.predict_within_lanes(states, TIMES, ROAD)[0, 0, :, 1]


@pytest.mark.parametrize(
    "y, vy, final",
    [
        (10.0, 2.7, 12.0),   # mid lane change to the right: ends on the next centre
        (10.0, -2.7, 8.0),   # ... and to the left
        (11.9, 0.3, 12.0),   # settling onto its own centre, not changing further
        (12.0, 0.3, 12.0),   # lane-keeping jitter on the centre: stays
        (12.5, 0.3, 14.9),   # past the onset: heading for 16 at 0.3 m/s, not there in 8 s
        (20.5, 1.0, 20.5),   # outside the right-lane centre moving out: keeps its position
        (21.0, -1.0, 20.0),  # coming back onto the road's last centre
        (-0.5, -1.0, -0.5),
        (8.0, 0.0, 8.0),
    ],
)
def test_lateral_motion_ends_on_a_lane_centre(y, vy, final):
    path = lateral(y, vy)
    assert path[0] == pytest.approx(y)
    assert path[-1] == pytest.approx(final, abs=1e-5)
    steps = path.diff()
    assert bool((steps * (1 if vy >= 0 else -1) >= -1e-6).all())  # monotone, never back


def test_longitudinal_motion_and_resting_vehicles_match_constant_velocity():
    states = torch.tensor([[[5.0, 4.0, 12.0, 0.0], [30.0, 10.0, 8.0, 2.5]], [[-7.0, 16.0, 0.0, -0.5], [1.0, 0.0, 20.0, 0.0]]])
    within = mmpc.predict_within_lanes(states, TIMES, ROAD)
    straight = mmpc.predict_constant_velocity(states, TIMES)
    assert within.shape == straight.shape == (2, 2, 41, 2)
    torch.testing.assert_close(within[..., 0], straight[..., 0])
    torch.testing.assert_close(within[0, 0], straight[0, 0])
    torch.testing.assert_close(within[1, 1], straight[1, 1])
    assert float(within[0, 1, -1, 1]) == pytest.approx(12.0)
    assert float(straight[0, 1, -1, 1]) == pytest.approx(30.0)


def test_the_mpc_predicts_as_configured():
    states = torch.tensor([[[0.0, 10.0, 10.0, 2.0]]])
    optimizer = mmpc.BatchOptimizer()
    goals = mmpc.CruiseGoals(horizon=optimizer.config.horizon)
    make = lambda prediction: mmpc.MPC(optimizer, goals, mmpc.CruiseCost(), ROAD, mmpc.MPCConfig(prediction=prediction))  # noqa: E731
    torch.testing.assert_close(make("lanes").predict(states, TIMES), mmpc.predict_within_lanes(states, TIMES, ROAD))
    torch.testing.assert_close(make("constant_velocity").predict(states, TIMES), mmpc.predict_constant_velocity(states, TIMES))
    assert mmpc.MPCConfig().prediction == "lanes"
