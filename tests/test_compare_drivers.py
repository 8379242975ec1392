"""Paired (per-seed) differences between two drivers: mmpc.evaluate.paired_differences and
scripts/compare_drivers.py over evaluation folders read from disk."""

import csv
import json

import pytest

from compare_drivers import main
from mmpc.evaluate import paired_differences
from mmpc.evaluate.intervals import mean_ci
from mmpc.evaluate.store import COLUMNS, check_inputs
from mmpc.scenario import load_scenario


def _rows(driver, returns, collisions=None, status=None):
    rows = []
    for seed, value in enumerate(returns):
        row = {column: 0 for column in COLUMNS}
        row.update(driver=driver, scenario="cruise", seed=seed, status="ok" if status is None else status[seed], error="",
                   worker="w", task_return=value, mean_speed=value / 20, collisions=0 if collisions is None else collisions[seed])
        rows.append(row)
    return rows


def test_pairing_removes_the_traffics_variance():
    traffic = [250.0, 300.0, 280.0, 320.0, 260.0, 310.0] * 5  # seeds differ a lot
    reference = _rows("defer", traffic)
    agent = _rows("agent", [value + 6.0 + (0.5 if i % 2 else -0.5) for i, value in enumerate(traffic)], [0] * 29 + [1])
    result = paired_differences(reference, agent, ("task_return",))
    entry = result["task_return"]
    assert result["episodes"] == 30 and result["collisions"] == 1 and result["reference_collisions"] == 0
    assert entry["difference"] == pytest.approx(6.0) and entry["relative"] == pytest.approx(6.0 / entry["reference"])
    low, high = entry["difference_ci"]
    _, unpaired = mean_ci([row["task_return"] for row in agent])
    assert 5.5 < low < 6.0 < high < 6.5 and high - low < (unpaired[1] - unpaired[0]) / 10


def test_only_seeds_both_finished_are_paired_and_repeated_seeds_are_refused():
    reference = _rows("defer", [1.0, 2.0, 3.0, 4.0], status=["ok", "ok", "ok", "error"])
    agent = _rows("agent", [2.0, 3.0, 4.0, 5.0, 6.0])
    result = paired_differences(reference, agent, ("task_return",))
    assert result["episodes"] == 3 and result["unpaired_seeds"] == [3, 4]
    assert result["task_return"]["difference"] == 1.0 and result["task_return"]["difference_ci"] == [1.0, 1.0]
    with pytest.raises(ValueError, match="a seed repeats"):
        paired_differences(reference, agent + _rows("other", [1.0]), ("task_return",))


def _folder(path, rows):
    """An evaluation folder of the rows, on the scenario cruise (its scenarios.json as `mmpc evaluate` writes it)."""
    path.mkdir()
    with open(path / "episodes.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    check_inputs(path, [load_scenario("cruise")], ())
    return path


def test_script_compares_folders_and_narrows_to_one_driver(tmp_path, capsys):
    traffic = [250.0, 300.0, 280.0, 320.0] * 5
    reference = _folder(tmp_path / "defer", _rows("safe-expert:cruise_task", traffic))
    both = _folder(tmp_path / "both", _rows("agent", [v + 10 for v in traffic]) + _rows("mpc", traffic))
    out = tmp_path / "out"
    assert main([str(reference), f"agent={both}#agent", "--metrics", "task_return,mean_speed", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "| agent | 20 | 0 (0) | +10 ± 0 (+3.5%) | +0.5 ± 0 (+3.5%) |" in printed
    written = json.loads((out / "compare_drivers.json").read_text())
    assert written["reference"] == "safe-expert:cruise_task on cruise" and written["results"]["agent"]["episodes"] == 20
    assert main([str(reference), str(both)]) == 2  # two drivers in one folder: name one
    assert "name one as FOLDER#DRIVER#SCENARIO" in capsys.readouterr().err
    assert main([str(reference), f"{both}#nobody"]) == 2
