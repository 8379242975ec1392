import json

import pytest

import bench_solver

import mmpc
from mmpc.cli.main import main


def test_solve_writes_table_plot_and_json(tmp_path, capsys):
    assert main(["solve", "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "<- best" in printed and "best: goal" in printed
    report = json.loads((tmp_path / "solve.json").read_text())
    assert len(report["candidates"]) == 11
    best = report["candidates"][report["best"]]
    assert best["status"] == "OK" and report["best_feasible"]
    # The best feasible candidate has the lowest meta cost among the feasible ones.
    feasible_costs = [c["meta_cost"] for c in report["candidates"] if c["status"] == "OK"]
    assert best["meta_cost"] == min(feasible_costs)
    assert (tmp_path / "solve.png").stat().st_size > 10_000


def test_solve_high_speed_prefers_the_right_lane(tmp_path, capsys):
    assert main(["solve", "--scenario", "high_speed", "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "solve.json").read_text())
    assert report["best_feasible"]
    assert report["candidates"][report["best"]]["goal_y"] >= 12.0


def test_bench_solver_writes_json_rows(tmp_path):
    assert bench_solver.main(["--batches", "1,4", "--obstacles", "0,2", "--repeats", "2",
                 "--devices", "cpu", "--variants", "eager,eager-warm10,eager-exit10", "--environments", "3",
                 "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "bench_solver.json").read_text())
    rows = report["rows"]
    assert {(r["batch"], r["obstacles"]) for r in rows} == {(1, 0), (4, 0), (1, 2), (4, 2)}
    iterations = {(r["variant"], r["iterations"]) for r in rows if r["variant"] != "eager-exit10"}
    assert iterations == {("eager", 100), ("eager-warm10", 10)}
    # early exit: the mean over the elements, between the first check and the schedule
    assert all(10 <= r["iterations"] <= 100 for r in rows if r["variant"] == "eager-exit10")
    assert all(r["time_vs_cold"] > 0 for r in rows if r["variant"] in ("eager-warm10", "eager-exit10"))
    assert all(r["ms_median"] > 0 and r["ms_p90"] >= r["ms_median"] for r in rows)
    assert all(0 < r["roofline_fraction"] < 1 for r in rows)
    config = mmpc.OptimizerConfig()
    ideal = bench_solver.bytes_per_solve(4, 2, config)  # the roofline of a warm row counts its own iterations
    assert bench_solver.bytes_per_solve(4, 2, config, iterations=10) == pytest.approx(ideal / 10)
    vectorized = report["vectorized"]
    assert vectorized["environments"] == 3 and vectorized["speedup"] > 0
    assert (tmp_path / "bench_solver.png").exists()


def test_bench_solver_compares_the_in_loop_solves_with_the_benchmark_per_goal_iteration(tmp_path):
    assert bench_solver.main(["--batches", "1", "--obstacles", "0", "--repeats", "2", "--devices", "cpu",
                              "--variants", "eager", "--environments", "0", "--in-loop", "high_speed",
                              "--in-loop-environments", "2", "--in-loop-steps", "2", "--in-loop-seed", "90100",
                              "--out", str(tmp_path)]) == 0
    (row,) = json.loads((tmp_path / "bench_solver.json").read_text())["in_loop"]
    assert row["first_seed"] == 90100
    goals = 35  # the high-speed MPC's goals per problem
    assert (row["variant"], row["batch"], row["obstacles"], row["obstacle_axes"]) == ("eager", 2 * goals, 6, "per obstacle")
    assert row["solves_per_step"] >= 1 and row["rounds"] >= 2
    # warm-started steps: the schedule's last 10 iterations, more where a problem solves cold again
    warm = bench_solver.load_scenario("high_speed").mpc.warm_iterations
    assert warm <= row["loop_iterations_per_goal"] <= 100
    assert row["ratio"] == pytest.approx(row["loop_ns_per_goal_iteration"] / row["benchmark_ns_per_goal_iteration"])
    assert row["loop_ms_per_step"] > 0 and row["benchmark_ms"] > 0


def test_bad_arguments_exit_with_usage_error():
    with pytest.raises(SystemExit):
        bench_solver.main(["--batches", "a,b"])
    with pytest.raises(SystemExit):
        bench_solver.main(["--variants", "compiled-warm"])
    for variant in ("compiled-exit", "compiled-exit10.x", "compiled-exit100"):
        with pytest.raises(SystemExit):
            bench_solver.main(["--variants", variant])


def test_drive_on_the_batched_simulator_writes_the_episode_without_a_video(tmp_path, capsys):
    assert main(["drive", "--sim", "batched", "--duration", "1", "--compile", "off", "--out", str(tmp_path)]) == 0
    assert "no video on the batched simulator" in capsys.readouterr().err
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["steps"] == 10 and metrics["collisions"] == 0
    assert not (tmp_path / "episode.mp4").exists()


def test_a_scenario_the_batched_simulator_cannot_run_is_a_usage_error(tmp_path, capsys):
    assert main(["drive", "--scenario", "cruise_ngsim", "--sim", "batched", "--out", str(tmp_path)]) == 2
    assert "mmpc drive: error: scenario 'cruise_ngsim'" in capsys.readouterr().err
    assert main(["evaluate", "--sim", "batched", "--episode-outputs", "--collision-videos", "--out", str(tmp_path)]) == 2
    assert "--sim highway-env" in capsys.readouterr().err


def test_a_bad_override_is_a_usage_error_without_a_traceback(tmp_path, capsys):
    assert main(["drive", "--set", "lanes=0", "--out", str(tmp_path)]) == 2
    assert "mmpc drive: error: scenario 'cruise': `lanes` must be an int >= 1; got 0" in capsys.readouterr().err
