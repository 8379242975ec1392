"""scripts/bench_rl_train.py: one row per (kind, algorithm, E), the JSON it writes read back."""

import json

import bench_rl_train


def test_the_training_benchmark_times_each_row_and_writes_its_table(tmp_path, capsys):
    out = tmp_path / "bench.json"
    assert bench_rl_train.main(["--config", "smoke", "--envs", "2", "--algos", "ppo", "--kinds", "plain,safe",
                                "--steps", "10", "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    rows = report["rows"]
    assert [(row["kind"], row["envs"]) for row in rows] == [("plain", 2), ("safe", 2)]
    assert all(row["steps"] == 16 and row["agent_steps_per_s"] > 0 for row in rows)  # whole rollouts: PPO's 8 x 2
    assert report["sim"] == "batched" and report["threads"] == 1
    assert "agent steps/s" in capsys.readouterr().out
