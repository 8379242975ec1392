"""scripts/compare_worlds.py: intervals, agreement, and a comparison of two evaluation folders read from disk."""

import csv
import json
import re

from compare_worlds import compare, main
from mmpc.evaluate.intervals import mean_ci, welch_ci, wilson_ci
from mmpc.evaluate.store import COLUMNS


def test_intervals_are_those_of_the_evaluation(tmp_path):
    """A mean's t interval, the collision share's Wilson interval, Welch's t interval of the difference."""
    rows = compare(_folder(tmp_path / "a", [14.0, 15.0, 16.0, 15.0], [0, 0, 0, 1]),
                   _folder(tmp_path / "b", [14.5, 15.0, 15.5], [0, 0, 0]))
    speed = next(row for row in rows if row["metric"] == "mean_speed")
    collisions = next(row for row in rows if row["metric"] == "collisions")
    mean, interval = mean_ci([14.0, 15.0, 16.0, 15.0])
    difference, difference_interval = welch_ci([14.0, 15.0, 16.0, 15.0], [14.5, 15.0, 15.5])
    assert speed["reference"] == (mean, *interval) and speed["difference"] == (difference, *difference_interval)
    assert collisions["reference"] == (0.25, *wilson_ci(1, 4)) and collisions["other"][1] == 0.0


def _folder(path, speeds, collisions, *, sim="highway-env", duration=10.0):
    path.mkdir()
    settings = {"name": "cruise", "sim": sim, "duration": duration}
    (path / "scenarios.json").write_text(json.dumps({"format": 2, "scenarios": {"cruise": f"{sim}-{duration}"},
                                                     "settings": {"cruise": settings}, "drivers": {}}))
    with open(path / "episodes.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, COLUMNS)
        writer.writeheader()
        for seed, (speed, collided) in enumerate(zip(speeds, collisions)):
            row = {column: 0 for column in COLUMNS}
            row.update(driver="mpc", scenario="cruise", seed=seed, status="ok", error="", worker="w", mean_speed=speed,
                       collisions=collided, meta_cost_mean=speed / 10, short_ttc_steps=int(speed) % 3, task_return=20 * speed,
                       verified_share="")  # a driver not verified: no such metric
            writer.writerow(row)
    return path


def test_two_folders_agree_or_not(tmp_path, capsys):
    reference = _folder(tmp_path / "highway-env", [14.0, 15.0, 16.0, 15.0] * 10, [0] * 40)
    close = _folder(tmp_path / "batched", [14.1, 15.1, 15.9, 15.0] * 10, [0] * 39 + [1], sim="batched")
    far = _folder(tmp_path / "slow", [10.0, 11.0, 12.0, 11.0] * 10, [1] * 40, sim="batched")
    assert main([str(reference), str(close), "--out", str(tmp_path / "out")]) == 0
    rows = json.loads((tmp_path / "out" / "compare_worlds.json").read_text())["rows"]
    assert [r["metric"] for r in rows] == ["collisions", "fallback_steps", "failsafe_steps", "short_ttc_steps",
                                           "near_lane_change_steps", "min_clearance", "mean_speed", "meta_cost_mean",
                                           "task_return"]
    assert all(r["agree"] for r in rows)
    assert "| mpc | cruise | mean speed [m/s] | 40 / 40 |" in capsys.readouterr().out
    assert main([str(reference), str(far), "--out", str(tmp_path / "out")]) == 0
    rows = json.loads((tmp_path / "out" / "compare_worlds.json").read_text())["rows"]
    disagree = {r["metric"] for r in rows if not r["agree"]}
    assert disagree == {"collisions", "short_ttc_steps", "mean_speed", "meta_cost_mean", "task_return"}, disagree
    assert main([str(reference), str(tmp_path / "out")]) == 2


def test_unlike_runs_and_bad_folders_are_refused_in_one_line(tmp_path, capsys):
    reference = _folder(tmp_path / "highway-env", [14.0, 15.0] * 4, [0] * 8)
    longer = _folder(tmp_path / "longer", [14.0, 15.0] * 4, [0] * 8, sim="batched", duration=20.0)
    fewer = _folder(tmp_path / "fewer", [14.0, 15.0] * 3, [0] * 6, sim="batched")
    batched = _folder(tmp_path / "batched", [14.0, 15.0] * 4, [0] * 8, sim="batched")
    refusals = {
        (str(reference), str(longer)): "cruise was run with other settings .*\\(duration: 10.0 vs 20.0",
        (str(reference), str(fewer)): "mpc on cruise finished other seeds in the two folders \\(8 in .*, 6 in",
        (str(reference), str(reference)): "are one folder",
        (str(reference), str(tmp_path / "missing")): "missing holds no episodes.csv",
    }
    for (first, second), message in refusals.items():
        assert main([first, second]) == 2
        err = capsys.readouterr().err
        assert re.search(message, err) and err.count("\n") == 1, err
    assert main([str(reference), str(longer), "--allow-different-scenarios"]) == 0
    blocked = tmp_path / "file"
    blocked.write_text("not a folder")
    assert main([str(reference), str(batched), "--out", str(blocked / "out")]) == 2
    assert "--out" in capsys.readouterr().err and not (blocked / "out").exists()
