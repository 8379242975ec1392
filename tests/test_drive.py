"""Episode outputs, metrics and ``mmpc drive``."""

import argparse
import dataclasses
import csv
import json
import math
import re

import imageio.v2 as imageio
import pytest
import torch

from mmpc.cli.arguments import seed_list
from mmpc.cli.main import main
from mmpc.highway.runner import traffic_near, run_episode, write_outputs
from mmpc.evaluate import format_table, read_episodes, summarize
from mmpc.metrics import StepRecord, episode_metrics, lane_change_durations
from mmpc.scenario import ScenarioConfig, load_scenario

REQUIRED_METRICS = {
    "collisions", "offroad", "steps", "mean_speed", "meta_cost_mean", "meta_cost_max", "speed_residual_mean",
    "right_lane_distance_mean", "lin_acc_mean", "ang_acc_mean", "solve_ms_mean", "solve_ms_max", "lane_changes",
}


def record(step, *, y=8.0, v=15.0, a=0.0, rate=0.0, lane=2, crashed=False, on_road=True, fallback=False, iterations=100):
    return StepRecord(step, step * 0.1, 10.0 * step, y, 0.0, v, a, rate, lane, a, 0.0, 0, 0.0, 0.0, 5, fallback,
                      float(step), float("nan"), 20.0 + step, iterations, 2.0, crashed, on_road, 0.8)


def test_episode_metrics_follow_their_definitions():
    records = [record(0, v=14.0, rate=0.0), record(1, v=16.0, a=-1.0, rate=0.1, lane=3, y=12.0),
               record(2, v=15.0, a=2.0, rate=0.0, lane=3, y=12.0, fallback=True, on_road=False)]
    metrics = episode_metrics(records, dt=0.1, right_lane_y=20.0, v_cruise=15.0)
    assert metrics["speed_residual_mean"] == pytest.approx((1 + 1 + 0) / 3)
    assert metrics["mean_speed"] == pytest.approx(15.0)
    assert metrics["right_lane_distance_mean"] == pytest.approx((12 + 8 + 8) / 3)
    assert metrics["lin_acc_mean"] == pytest.approx(1.0)
    assert metrics["ang_acc_mean"] == pytest.approx(1.0)  # |0.1 - 0| / 0.1 twice
    assert metrics["lane_changes"] == 1 and metrics["offroad"] == 1 and metrics["fallback_steps"] == 1
    assert metrics["meta_cost_max"] == 2.0 and metrics["solve_ms_max"] == 22.0 and metrics["collisions"] == 0
    assert metrics["iterations_mean"] == 100
    assert metrics["task_return"] == pytest.approx(3 * 0.8)
    assert "speed_residual_mean" not in episode_metrics(records, dt=0.1, right_lane_y=20.0)
    warm = [record(0), record(1, iterations=20), record(2, iterations=20)]
    assert episode_metrics(warm, dt=0.1, right_lane_y=20.0)["iterations_mean"] == pytest.approx(140 / 3)
    assert episode_metrics([record(0, iterations=-1)], dt=0.1, right_lane_y=20.0)["iterations_mean"] is None  # not reported
    assert episode_metrics([record(0, crashed=True)], dt=0.1, right_lane_y=20.0)["collisions"] == 1
    with pytest.raises(ValueError, match="records"):
        episode_metrics([], dt=0.1, right_lane_y=20.0)


def test_the_statistics_that_lead_to_crashes_come_from_the_traffic_around_the_ego():
    ego = torch.tensor([[0.0, 8.0, 0.0, 20.0, 0.0, 0.0]]).repeat(2, 1)
    vehicles = torch.tensor([[[25.0, 9.0, 10.0, 0.0],  # ahead, overlapping across: 20 m closed at 10 m/s
                              [10.0, 12.0, 20.0, 1.0],  # changing lane, one lane over
                              [-20.0, 4.0, 25.0, -2.0],  # changing lane behind, within 30 m
                              [60.0, 8.0, 30.0, 0.0]],  # ahead but pulling away
                             [[4.0, 8.5, 25.0, 0.0],  # touching
                              [50.0, 14.0, 5.0, 0.0],  # ahead two lanes over: not closing on the ego's path
                              [20.0, 20.0, 5.0, 3.0],  # changing lane three lanes over
                              [0.0, 0.0, 0.0, 0.0]]])  # absent
    mask = torch.tensor([[True] * 4, [True, True, True, False]])
    ttc, changing = traffic_near(ego, vehicles, mask, load_scenario("high_speed"))
    assert ttc.tolist() == [2.0, 0.0] and changing.tolist() == [2, 0]
    _, alone = traffic_near(ego[:1], vehicles[:1, :0], None, load_scenario("high_speed"))
    assert alone.tolist() == [0]
    records = [record(0)._replace(ttc=3.0, lane_changes_near=1), record(1)._replace(ttc=1.5, lane_changes_near=2),
               record(2)]
    metrics = episode_metrics(records, dt=0.1, right_lane_y=20.0)
    assert metrics["min_ttc"] == 1.5 and metrics["short_ttc_steps"] == 1 and metrics["near_lane_change_steps"] == 3
    assert episode_metrics([record(0)], dt=0.1, right_lane_y=20.0)["min_ttc"] is None  # nobody closing in


def test_plan_cost_mean_is_over_the_steps_with_a_plan():
    # a driver that plans at some steps only (e.g. the safe layer tracking a plan between decisions)
    records = [record(0)._replace(plan_cost=3.0), record(1), record(2)._replace(plan_cost=5.0)]
    assert episode_metrics(records, dt=0.1, right_lane_y=20.0)["plan_cost_mean"] == pytest.approx(4.0)
    assert math.isnan(episode_metrics([record(0)], dt=0.1, right_lane_y=20.0)["plan_cost_mean"])


@pytest.mark.usefixtures("one_thread")
@pytest.mark.parametrize("sim", ["highway-env", "batched"])
def test_the_task_reward_is_highway_envs_reward_of_the_driven_states(sim):
    """Each step's task reward is HighwayEnv's default reward of the state after its frame (the
    next record's state), recomputed here: (1 + 0.1 lane / 5 + 0.4 clip((v cos(heading) - 20) / 10))
    / 1.5 on the road without a collision (the body heading differs from the record's direction of
    motion by the slip angle: cos of either within 1e-3 in lane keeping)."""
    base = load_scenario("high_speed")
    scenario = base.replace(duration=3.0, sim=sim, ego=dataclasses.replace(base.ego, speed=24.0))
    result = run_episode(scenario, seed=3)
    rewards = [r.task_reward for r in result.records]
    after = [(1.0 + 0.1 * r.lane / 5 + 0.4 * min(max((r.v * math.cos(r.psi) - 20.0) / 10.0, 0.0), 1.0)) / 1.5
             for r in result.records[1:]]
    assert not any(r.crashed for r in result.records) and len(rewards) == 30
    assert rewards[:-1] == pytest.approx(after, abs=1e-3)
    assert result.metrics["task_return"] == pytest.approx(sum(rewards))


@pytest.mark.usefixtures("one_thread")
def test_episode_outputs_and_video(tmp_path):
    scenario = ScenarioConfig(duration=2.0)
    result = run_episode(scenario, seed=1, video=tmp_path / "episode.mp4")
    assert len(result.records) == 20 and result.metrics["steps"] == 20
    assert REQUIRED_METRICS <= set(result.metrics)
    paths = write_outputs(result, tmp_path)
    assert [p.name for p in paths] == ["metrics.json", "steps.csv", "topdown.png"]
    assert json.loads((tmp_path / "metrics.json").read_text())["seed"] == 1
    rows = list(csv.DictReader(open(tmp_path / "steps.csv")))
    assert len(rows) == 20 and list(rows[0]) == list(StepRecord._fields)
    assert float(rows[-1]["time"]) == pytest.approx(1.9)
    frames = imageio.mimread(tmp_path / "episode.mp4", memtest=False)
    assert len(frames) == 20 and frames[0].shape == (192, 960, 3)
    assert (tmp_path / "topdown.png").stat().st_size > 20_000


@pytest.mark.usefixtures("one_thread")
def test_drive_cli_single_episode(tmp_path, capsys):
    assert main(["drive", "--duration", "1.5", "--seed", "2", "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "collisions" in printed and "speed_residual_mean" in printed
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert REQUIRED_METRICS <= set(metrics) and metrics["steps"] == 15 and metrics["scenario"] == "cruise"
    assert all(math.isfinite(metrics[key]) for key in REQUIRED_METRICS)
    assert (tmp_path / "episode.mp4").stat().st_size > 10_000 and (tmp_path / "topdown.png").exists()


@pytest.mark.usefixtures("one_thread")
def test_drive_cli_evaluates_scenarios_over_seeds(tmp_path, capsys):
    argv = ["drive", "--scenario", "cruise,high_speed", "--seeds", "0-1", "--duration", "1.0", "--out", str(tmp_path)]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "cruise" in printed and "high_speed" in printed and "collisions" in printed
    report = json.loads((tmp_path / "summary.json").read_text())
    assert [(e["scenario"], e["seed"], e["status"]) for e in read_episodes(tmp_path / "episodes.csv")] == [
        ("cruise", 0, "ok"), ("cruise", 1, "ok"), ("high_speed", 0, "ok"), ("high_speed", 1, "ok")]
    assert [s["episodes"] for s in report["summary"]] == [2, 2]
    assert (tmp_path / "high_speed" / "seed_1" / "steps.csv").exists()


def test_drive_cli_rejects_bad_arguments(tmp_path, capsys):
    assert main(["drive", "--duration", "-1", "--out", str(tmp_path)]) == 2
    assert main(["drive", "--scenario", "cruise,high_speed", "--out", str(tmp_path)]) == 2
    assert main(["drive", "--seed", "1", "--seeds", "0-3", "--out", str(tmp_path)]) == 2
    capsys.readouterr()
    assert main(["drive", "--scenario", "nowhere", "--out", str(tmp_path)]) == 2  # one line, no traceback
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("mmpc drive: error: FileNotFoundError: ScenarioConfig 'nowhere'")
    assert re.search(r"shipped scenarios: \[.*'high_speed'", err), err
    with pytest.raises(SystemExit):
        main(["drive", "--seeds", "a-b"])


def test_seed_lists():
    assert seed_list("0-3") == (0, 1, 2, 3)
    assert seed_list("5,1-2,5") == (5, 1, 2)
    for bad in ("", "x", "-1", "3-a"):
        with pytest.raises(argparse.ArgumentTypeError):
            seed_list(bad)


def test_summary_table_lists_collisions_by_seed_and_fault():
    parts = {1: "rear", 3: "front"}
    rows = [dict(scenario="cruise", seed=s, collisions=int(s in parts), collision_part=parts.get(s),
                 ego_fault_collisions=int(parts.get(s) == "front"), offroad=0, mean_speed=14.0 + s, speed_residual_mean=0.1,
                 right_lane_distance_mean=5.0, lin_acc_mean=0.5, ang_acc_mean=0.01, meta_cost_mean=1.0, lane_changes=2,
                 fallback_steps=1, solve_ms_mean=20.0, solve_ms_max=30.0 + s, min_clearance=1.5) for s in range(4)]
    rows.append({**rows[0], "seed": 4, "collisions": 1, "collision_part": None, "ego_fault_collisions": None})  # before the split
    summary = summarize(rows)
    assert summary[0]["collisions"] == 3 and summary[0]["collision_seeds"] == [1, 3, 4]
    assert summary[0]["ego_fault_collisions"] == 2 and summary[0]["ego_fault_seeds"] == [3, 4]
    assert summary[0]["mean_speed"] == pytest.approx(15.2) and summary[0]["solve_ms_max"] == 33.0
    table = format_table(summary)
    assert "seeds 1 (rear), 3 (front), 4 (unknown)" in table and "15.20" in table
    assert [line.split()[-1] for line in table.splitlines() if "ego's fault" in line] == ["2"]


@pytest.mark.usefixtures("one_thread")
def test_drive_cli_overrides_scenario_values(tmp_path, capsys):
    argv = ["drive", "--set", "traffic.target_speeds=null", "--set", "name=cruise_default_traffic", "--duration", "0.5",
            "--no-video", "--out", str(tmp_path)]
    assert main(argv) == 0
    assert json.loads((tmp_path / "metrics.json").read_text())["scenario"] == "cruise_default_traffic"
    assert not (tmp_path / "episode.mp4").exists()
    assert main(["drive", "--set", "traffic.target_sped=null", "--out", str(tmp_path)]) == 2
    assert "target_sped" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["drive", "--set", "no_equals_sign"])


def test_scenario_overrides_reach_nested_sections():
    scenario = load_scenario("cruise", {"traffic.target_speeds": None, "mpc.num_obstacles": 4, "name": "x"})
    assert scenario.traffic.target_speeds is None and scenario.mpc.num_obstacles == 4 and scenario.name == "x"
    with pytest.raises(ValueError, match="not a section"):
        load_scenario("cruise", {"name.first": "x"})


def test_lane_discipline_metrics_time_the_changes_and_the_steps_off_centre():
    # centred on lane 2 (y = 8), drift to lane 3 over 1.0 s, stay; then half a change back that never completes
    ys = [8.0, 8.2, 8.4, 9.0, 9.8, 10.6, 11.2, 11.7, 12.0, 12.0, 11.5, 11.0, 10.6, 10.6]
    records = [record(step, y=y, lane=round(y / 4.0)) for step, y in enumerate(ys)]
    metrics = episode_metrics(records, dt=0.1, right_lane_y=20.0)
    # last within 0.5 m of y = 8 at step 2 (8.4), first within 0.5 m of y = 12 at step 7 (11.7)
    assert lane_change_durations(records, 4.0, 0.1) == pytest.approx([0.5])
    assert metrics["lane_change_s_mean"] == pytest.approx(0.5)
    off = [abs(y - round(y / 4.0) * 4.0) > 1.0 for y in ys]  # 9.8, 10.6 and the last two 10.6
    assert sum(off) == 4 and metrics["off_centre_share"] == pytest.approx(4 / 14)
    assert episode_metrics(records[:3], dt=0.1, right_lane_y=20.0)["lane_change_s_mean"] is None
