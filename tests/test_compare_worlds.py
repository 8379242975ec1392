"""scripts/compare_worlds.py: intervals, agreement, and a comparison of two evaluation folders read from disk."""

import csv
import json

import pytest

from compare_worlds import difference_interval, main, mean_interval, wilson_interval
from mmpc.evaluate.store import COLUMNS


def test_intervals():
    mean, low, high = mean_interval([1.0, 2.0, 3.0, 4.0])
    assert mean == 2.5 and high - mean == pytest.approx(1.959964 * 1.290994 / 2, rel=1e-5)
    share, low, high = wilson_interval(0, 200)
    assert share == 0.0 and low == pytest.approx(0.0, abs=1e-12) and high == pytest.approx(0.0188, abs=1e-4)
    difference, low, high = difference_interval([1.0, 2.0, 3.0], [2.0, 3.0, 4.0])
    assert difference == 1.0 and low < 0 < high


def _folder(path, speeds, collisions):
    path.mkdir()
    with open(path / "episodes.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, COLUMNS)
        writer.writeheader()
        for seed, (speed, collided) in enumerate(zip(speeds, collisions)):
            row = {column: 0 for column in COLUMNS}
            row.update(driver="mpc", scenario="cruise", seed=seed, status="ok", error="", worker="w", mean_speed=speed,
                       collisions=collided, meta_cost_mean=speed / 10, short_ttc_steps=int(speed) % 3,
                       verified_share="")  # a driver not verified: no such metric
            writer.writerow(row)
    return path


def test_two_folders_agree_or_not(tmp_path, capsys):
    reference = _folder(tmp_path / "highway-env", [14.0, 15.0, 16.0, 15.0] * 10, [0] * 40)
    close = _folder(tmp_path / "batched", [14.1, 15.1, 15.9, 15.0] * 10, [0] * 39 + [1])
    far = _folder(tmp_path / "slow", [10.0, 11.0, 12.0, 11.0] * 10, [1] * 40)
    assert main([str(reference), str(close), "--out", str(tmp_path / "out")]) == 0
    rows = json.loads((tmp_path / "out" / "compare_worlds.json").read_text())["rows"]
    assert [r["metric"] for r in rows] == ["collisions", "fallback_steps", "failsafe_steps", "short_ttc_steps",
                                           "near_lane_change_steps", "min_clearance", "mean_speed", "meta_cost_mean"]
    assert all(r["agree"] for r in rows)
    assert "| mpc | cruise | mean speed [m/s] | 40 / 40 |" in capsys.readouterr().out
    assert main([str(reference), str(far), "--out", str(tmp_path / "out")]) == 0
    rows = json.loads((tmp_path / "out" / "compare_worlds.json").read_text())["rows"]
    disagree = {r["metric"] for r in rows if not r["agree"]}
    assert disagree == {"collisions", "short_ttc_steps", "mean_speed", "meta_cost_mean"}, disagree
    assert main([str(reference), str(tmp_path / "out")]) == 2
