"""The closed-loop benchmark (scripts/bench_closed_loop.py): summaries, tables, the spec's validation and a quick run read back from disk."""

import json
import math

import pytest

from bench_closed_loop import COLUMNS, BenchSpec, format_tables, main, step_values, summarize
from mmpc.metrics import StepRecord


def record(step, *, v, y, a, rate, solve_ms, meta_cost):
    return StepRecord(step, step * 0.1, 10.0 * step, y, 0.0, v, a, rate, 2, a, 0.0, 0, 0.0, 0.0, 5, False,
                      meta_cost, meta_cost, solve_ms, -1, 2.0, False, True, 0.8)


def test_summaries_are_mean_min_max_over_every_step_of_every_episode():
    first = [record(0, v=14.0, y=8.0, a=1.0, rate=0.0, solve_ms=10.0, meta_cost=1.0),
             record(1, v=15.0, y=12.0, a=-2.0, rate=0.1, solve_ms=30.0, meta_cost=0.0)]
    second = [record(0, v=16.0, y=20.0, a=0.0, rate=0.0, solve_ms=20.0, meta_cost=1.0)]
    steps = {key: [] for key, _, _ in COLUMNS}
    for records in (first, second):
        for key, values in step_values(records, 0.1, 20.0).items():
            steps[key].extend(values)
    episodes = [{"seed": 0, "steps": 2, "collisions": 0, "fallback_steps": 1, "lane_changes": 1},
                {"seed": 3, "steps": 1, "collisions": 1, "fallback_steps": 0, "lane_changes": 0}]
    entry = summarize("mpc", "cruise", episodes, steps)
    assert entry["solve_ms_mean"] == pytest.approx(20.0) and entry["solve_ms_min"] == 10.0 and entry["solve_ms_max"] == 30.0
    assert entry["lin_acc_mean"] == pytest.approx(1.0) and entry["lin_acc_max"] == 2.0
    assert entry["ang_acc_mean"] == pytest.approx(1.0)  # one change of 0.1 rad/s in 0.1 s
    assert entry["right_lane_distance_mean"] == pytest.approx(20.0 / 3.0) and entry["speed_max"] == 16.0
    assert entry["meta_cost_mean"] == pytest.approx(2.0 / 3.0)
    assert entry["collisions"] == 1 and entry["collision_seeds"] == [3] and entry["steps"] == 3
    table = format_tables([entry], BenchSpec(seeds=(0, 3), duration=5.0))
    assert "### cruise" in table and "| mpc | 0.67 [0.00, 1.00] |" in table and "1 / 2" in table
    assert "Episodes of 5 s, seeds 0,3" in table


@pytest.mark.parametrize("changes,match", [
    ({"seeds": (1, 1)}, "distinct"), ({"methods": ()}, "methods"), ({"duration": 0.0}, "duration"),
    ({"scaling_batches": (0,)}, "scaling_batches"), ({"nlp_workers": 0}, "nlp_workers"), ({"scenarios": ()}, "scenarios"),
])
def test_bench_spec_rejects_bad_values(changes, match):
    with pytest.raises(ValueError, match=match):
        BenchSpec(**changes)


def test_bench_cli_rejects_bad_input_before_running(tmp_path, capsys):
    assert main(["--quick", "--duration", "-1", "--out", str(tmp_path)]) == 2
    captured = capsys.readouterr()
    assert "duration" in captured.out + captured.err
    assert not (tmp_path / "results.json").exists()
    assert main(["--quick", "--scenarios", "nowhere", "--methods", "frenet", "--out", str(tmp_path)]) == 2
    assert "shipped scenarios" in capsys.readouterr().err
    assert not (tmp_path / "results.json").exists()


@pytest.mark.usefixtures("one_thread")
def test_quick_bench_writes_tables_json_and_figures(tmp_path):
    methods = ["mpc", "standard-mpc", "batch-nlp:6", "frenet"]
    code = main(["--quick", "--scenarios", "cruise", "--methods", ",".join(methods), "--out", str(tmp_path)])
    assert code == 0
    report = json.loads((tmp_path / "results.json").read_text())
    entries = report["entries"]
    assert [(e["method"], e["scenario"]) for e in entries] == [(m, "cruise") for m in methods]
    for entry in entries:
        assert {"meta_cost_mean", "collisions", "solve_ms_mean", "solve_ms_max"} <= set(entry)
        assert entry["collisions"] == 0 and entry["episodes"] == 1 and entry["steps"] == 10
        assert math.isfinite(entry["meta_cost_mean"]) and entry["meta_cost_mean"] >= 0
        assert 0 < entry["solve_ms_min"] <= entry["solve_ms_mean"] <= entry["solve_ms_max"]
        assert 13.0 < entry["speed_mean"] < 16.0  # 1 s from 14 m/s towards 15 m/s
    assert len(report["episodes"]) == 4 and {e["seed"] for e in report["episodes"]} == {0}
    scaling = report["scaling"]["rows"]
    assert [(r["method"], r["batch"]) for r in scaling] == [("ours", 1), ("ours", 11), ("batch-nlp", 1), ("batch-nlp", 6)]
    assert all(r["ms_median"] > 0 for r in scaling)
    residuals = report["residuals"]["history"]
    assert set(residuals) == {"obstacle", "acceleration", "non-holonomic"} and len(residuals["obstacle"]) == 100
    tables = (tmp_path / "tables.md").read_text()
    assert all(f"| {m} |" in tables for m in methods)
    assert (tmp_path / "scaling.png").stat().st_size > 10_000 and (tmp_path / "residuals.png").stat().st_size > 10_000
