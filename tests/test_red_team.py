"""The red-team environment (mmpc.rl.red_team): one car of the traffic driven by an agent, within
the rules, against a driver under test; episodes from named seeds, scored without the padding."""

import dataclasses

import numpy as np
import pytest
import torch

from mmpc.drivers import make_driver
from mmpc.rl.red_team import ACTIONS, LANE_DISTANCE, OBSERVATION_SIZE, PASSED, RED_REACH, RedTeamVecEnv, score_red_team
from mmpc.scenario import load_scenario

SCENARIO = dataclasses.replace(load_scenario("high_speed", {"sim": "batched"}), duration=2.0)


class Always:
    """A stand-in agent that always picks one action."""

    def __init__(self, action: int) -> None:
        self.action = action

    def predict(self, observations, deterministic=True):
        return np.full(len(observations), self.action), None


def test_the_red_car_obeys_within_the_rules_and_episodes_restart_with_new_ids():
    env = RedTeamVecEnv(make_driver("mpc", SCENARIO), SCENARIO, 3, seeds=[71800, 71801, 71802, 71803, 71804, 71805])
    observations = env.reset()
    assert observations.shape == (3, OBSERVATION_SIZE) and observations.dtype == np.float32
    rows = torch.arange(3)
    red = env.red.clone()
    assert bool((red > 0).all()) and env.episode_seeds == [71800, 71801, 71802]
    before = env.sim.state.speed[rows, red].clone()
    brake = ACTIONS.index((0, -1))
    _, rewards, dones, infos = env.step(np.full(3, brake))
    settled = env.sim.state.lane[rows, red] == env.sim.state.target_lane[rows, red]
    slowed = before - env.sim.state.speed[rows, red]
    assert bool(((slowed - 0.6).abs() < 1e-3)[settled].all())  # 6 m/s^2 for 0.1 s: IDM's hardest braking
    assert np.isfinite(rewards).all() and not dones.any()
    assert set(infos[0]) >= {"crashed", "red_hit", "gap", "red_left_assumptions", "episode_seed"}
    for _ in range(19):
        _, _, dones, infos = env.step(np.zeros(3, dtype=np.int64))
    assert dones.all() and all(info["TimeLimit.truncated"] and "terminal_observation" in info for info in infos)
    assert env.episode_seeds == [71803, 71804, 71805] and env.ids.tolist() == [3, 4, 5]
    with pytest.raises(ValueError, match="actions"):
        env.step_async(np.array([0, 9, 0]))


def test_the_red_car_is_the_one_the_ego_comes_to_first_and_another_once_the_ego_passed_it():
    env = RedTeamVecEnv(make_driver("mpc", SCENARIO), SCENARIO, 4, seeds=[71830, 71831, 71832, 71833])
    env.reset()
    ego, vehicles, mask = env.sim.road_state()
    road = SCENARIO.road
    for row in range(4):
        dx = vehicles[row, :, 0] - ego[row, 0]
        lanes = (road.lane_index(vehicles[row, :, 1]) - road.lane_index(ego[row:row + 1, 1])).abs()
        ahead = mask[row] & (dx > 0) & (dx < RED_REACH)
        assert bool(ahead.any())  # the placement leaves cars ahead within reach in these scenes
        expected = torch.where(ahead, dx + LANE_DISTANCE * lanes, torch.full_like(dx, float("inf"))).argmin()
        assert int(env.red[row]) == int(expected) + 1
    x = env.sim.state.x.clone()
    x[0, env.red[0]] = x[0, 0] - PASSED - 5.0  # the ego has passed row 0's red car
    env.sim.state = env.sim.state._replace(x=x)
    assert env._passed().tolist() == [0]
    env.step(np.zeros(4, dtype=np.int64))
    assert float(env.sim.state.x[0, env.red[0]]) > float(env.sim.state.x[0, 0])  # picked anew, ahead


def test_the_near_miss_reward_pays_for_an_ego_closing_fast_on_the_red_car():
    env = RedTeamVecEnv(make_driver("mpc", SCENARIO), SCENARIO, 2, seeds=[71840, 71841], near_miss=1.0)
    env.reset()
    state, red = env.sim.state, env.red.clone()
    x, y, speed = state.x.clone(), state.y.clone(), state.speed.clone()
    for row, gap in enumerate((6.0, 40.0)):  # the red car 1 m ahead of the ego's body, then 35 m: both in its lane
        x[row, red[row]] = x[row, 0] + gap
        y[row, red[row]] = y[row, 0]
        speed[row, red[row]] = speed[row, 0] - 5.0
    env.sim.state = state._replace(x=x, y=y, speed=speed)
    ttc = env._red_ttc()
    assert float(ttc[0]) == pytest.approx(1.0 / 5.0, rel=1e-3) and float(ttc[1]) == pytest.approx(35.0 / 5.0, rel=1e-3)
    _, rewards, _, _ = env.step(np.full(2, ACTIONS.index((0, 0))))
    assert rewards[0] > 0.5 and rewards[1] == 0.0  # a near miss (or a collision), against 7 s away: nothing


def test_a_score_counts_one_episode_per_named_seed():
    score = score_red_team(Always(ACTIONS.index((0, -1))), make_driver("mpc", SCENARIO), SCENARIO, [71810, 71811, 71812], 2)
    assert score.episodes == 3 and score.collisions <= 3 and score.actions["brake"] == 1.0
    assert score.red_left_assumptions == 0


@pytest.mark.slow
def test_the_red_team_script_trains_and_writes_its_score(tmp_path):
    import json
    import subprocess
    import sys

    out = tmp_path / "red"
    subprocess.run([sys.executable, "scripts/red_team.py", "--driver", "mpc", "--steps", "256", "--envs", "2",
                    "--episodes", "2", "--seeds", "71820", "--duration", "2", "--set", "traffic.ego_as_follower=true",
                    "--out", str(out)], check=True)
    row = json.loads((out / "red_team.json").read_text())
    assert row["overrides"] == {"traffic.ego_as_follower": True}
    assert row["episodes"] == 2 and row["trained_steps"] >= 256 and (out / "model.zip").is_file()
    assert list((out / "tb").rglob("events.out.tfevents.*"))
