"""The issue's acceptance run: 20 seeds x both scenarios x 40 s in dense traffic (slow: ~10 min
with 2 workers). The same run from the command line:
``mmpc drive --scenario cruise,high_speed --seeds 0-19 --workers 2 --out runs/eval``."""

import pytest

from mmpc.evaluate import EvaluationConfig, evaluate, format_table
from mmpc.scenario import load_scenario


@pytest.mark.slow
def test_twenty_seeds_in_dense_traffic(tmp_path):
    scenarios = [load_scenario("cruise"), load_scenario("high_speed")]
    assert all(s.traffic.vehicles_density >= 1.5 and s.duration == 40.0 for s in scenarios)
    config = EvaluationConfig(seeds=tuple(range(20)), workers=2, episode_layout="{scenario}/seed_{seed}",
                              collision_videos=True, report=False)
    _, summary = evaluate(scenarios, tmp_path, config)
    table = format_table(summary)
    for entry in summary:  # every collision comes with its video
        for seed in entry["collision_seeds"]:
            assert (tmp_path / entry["scenario"] / f"seed_{seed}" / "episode.mp4").exists()
    cruise, high_speed = summary
    assert cruise["collisions"] == 0 and high_speed["collisions"] == 0, table
    assert cruise["offroad"] == 0 and high_speed["offroad"] == 0, table
    assert cruise["speed_residual_mean"] <= 0.1, table
