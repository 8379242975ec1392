"""Issue acceptance on >= 30 deterministic highway scenes (mmpc.scenes.synthetic_scenes)."""

import math

import torch

from mmpc.problem import EGO_PSI, EGO_V, EGO_X, EGO_Y


def _feasible_pairs(solved_scenes):
    for scene, result in solved_scenes:
        for g in range(result.feasible.shape[1]):
            if result.feasible[0, g]:
                yield scene, result, g


def test_scene_set_covers_the_cases(scenes64):
    assert len(scenes64) >= 30
    counts = {scene.problem.obstacles.shape[1] for scene in scenes64}
    assert counts == set(range(11))
    lanes = {scene.road.num_lanes for scene in scenes64}
    assert len(lanes) >= 3
    lane_change = [scene.problem.goals[0, :, 1] != scene.problem.ego[0, EGO_Y] for scene in scenes64]
    assert all(change.any() and (~change).any() for change in lane_change)


def test_feasible_elements_satisfy_every_constraint(optimizer64, solved_scenes):
    cfg = optimizer64.config
    checked = 0
    for scene, result, g in _feasible_pairs(solved_scenes):
        traj = result.trajectories
        ego = scene.problem.ego[0]
        goal = scene.problem.goals[0, g]
        x, y, psi, v = traj.x[0, g], traj.y[0, g], traj.psi[0, g], traj.v[0, g]
        xd, yd, xdd, ydd = traj.xdot[0, g], traj.ydot[0, g], traj.xddot[0, g], traj.yddot[0, g]
        # Boundary conditions.
        start = torch.stack([x[0], y[0], xd[0], yd[0], psi[0], x[-1], y[-1]])
        expected = torch.stack([
            ego[EGO_X], ego[EGO_Y], ego[EGO_V] * torch.cos(ego[EGO_PSI]),
            ego[EGO_V] * torch.sin(ego[EGO_PSI]), ego[EGO_PSI], goal[0], goal[1],
        ])
        torch.testing.assert_close(start, expected, atol=1e-4, rtol=0)
        # Speed bounds: the speed variable and the path speed.
        assert cfg.v_min <= v.min() and v.max() <= cfg.v_max
        path_speed = torch.hypot(xd, yd)
        assert cfg.v_min - 0.1 <= path_speed.min() and path_speed.max() <= cfg.v_max + 0.1
        # Acceleration bound.
        assert torch.hypot(xdd, ydd).max() <= cfg.a_max + 0.05
        # Obstacles, recomputed from the raw predictions.
        obstacles = scene.problem.obstacles[0]
        if obstacles.shape[0]:
            dx = (x - obstacles[..., 0]) / cfg.ellipse_a
            dy = (y - obstacles[..., 1]) / cfg.ellipse_b
            assert torch.hypot(dx, dy).min() >= 0.99
        # Heading band.
        assert psi.abs().max() <= math.radians(cfg.max_heading_deg) + 1e-9
        # Unicycle re-integration with the returned v and psi (trapezoidal rule).
        dt = float(traj.times[1] - traj.times[0])
        vx, vy = v * torch.cos(psi), v * torch.sin(psi)
        x_int = x[0] + torch.cat([x.new_zeros(1), torch.cumsum(0.5 * (vx[1:] + vx[:-1]) * dt, 0)])
        y_int = y[0] + torch.cat([y.new_zeros(1), torch.cumsum(0.5 * (vy[1:] + vy[:-1]) * dt, 0)])
        assert torch.hypot(x_int - x, y_int - y).max() <= 0.5
        checked += 1
    assert checked >= 100


def test_median_residuals_after_100_iterations(solved_scenes):
    obstacle = torch.cat([r.residual_obstacle.flatten() for _, r in solved_scenes])
    nonholonomic = torch.cat([r.residual_nonholonomic.flatten() for _, r in solved_scenes])
    assert obstacle.median() <= 1e-3
    assert nonholonomic.median() <= 5e-3


def test_reachable_goals_are_mostly_feasible(solved_scenes):
    reachable = torch.cat([s.reachable.flatten() for s, _ in solved_scenes])
    feasible = torch.cat([r.feasible.flatten() for _, r in solved_scenes])
    assert reachable.sum() >= 100
    assert (feasible & reachable).sum() / reachable.sum() >= 0.9


def test_blocked_goal_is_flagged_not_feasible(optimizer64):
    """A goal that can only be reached through a slower car in the same lane."""
    import mmpc

    times = optimizer64.times
    ego = mmpc.ego_state(0.0, 4.0, 0.0, 15.0, dtype=torch.float64)
    states = torch.tensor([[[20.0, 4.0, 8.0, 0.0]]], dtype=torch.float64)
    goals = torch.tensor([[[20.0 + 8.0 * 8.0, 4.0]]], dtype=torch.float64)  # where the car ends
    obstacles = mmpc.predict_constant_velocity(states, times)
    result = optimizer64(mmpc.ProblemBatch(ego, goals, obstacles))
    assert not result.feasible.any()
    assert result.status[0, 0] & mmpc.Status.OBSTACLE


def test_heading_target_turns_the_heading_band_into_a_constraint():
    """A lane change of 8 m over 100 m: the unclipped S-curve peaks at ~8.4 deg; with the
    heading step's targets clipped to 6 deg the same goal is still reached, inside the band."""
    import mmpc

    ego = mmpc.ego_state(0.0, 0.0, 0.0, 14.0, dtype=torch.float64)
    goals = torch.tensor([[[100.0, 8.0]]], dtype=torch.float64)
    problem = mmpc.ProblemBatch(ego, goals, torch.zeros(1, 0, 100, 2, dtype=torch.float64))
    peaks = {}
    for target in (None, 6.0):
        optimizer = mmpc.BatchOptimizer(mmpc.OptimizerConfig(heading_target_deg=target), dtype=torch.float64)
        result = optimizer(problem)
        assert result.feasible.all()
        assert abs(float(result.trajectories.y[0, 0, -1]) - 8.0) < 1e-3
        peaks[target] = math.degrees(float(result.max_heading_deviation))
    assert peaks[None] > 8.0
    assert peaks[6.0] < 6.2
