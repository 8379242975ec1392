"""The ceiling's beam search (:mod:`mmpc.evaluate.ceiling`) and its script: a clone of an episode
steps as its original, the search's best episode replays from its commands, every command of the
verified ceiling keeps a verified way out (or continues the fail-safe verified last), the ceiling
is at or above the driver it bounds, and the driver's node drives as the driver alone does."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest
import torch

from mmpc.drivers import make_driver
from mmpc.evaluate.ceiling import CeilingConfig, search_ceiling
from mmpc.highway.runner import run_lockstep
from mmpc.scenario import load_scenario
from mmpc.sim import SimEpisodes
from mmpc.sim.reward import highway_reward
from mmpc.verify import Verifier

ROOT = Path(__file__).resolve().parents[1]
SEEDS = [7, 8]


def scenario(name: str = "high_speed", duration: float = 1.5):
    return load_scenario(name, {"duration": duration, "sim": "batched"})


@pytest.fixture(scope="module")
def verified_ceiling():
    return search_ceiling(scenario(), SEEDS, CeilingConfig(beam=6, siblings=3, branch_period=0.3))


def test_a_clone_steps_as_its_original():
    threats = load_scenario("high_speed_threats", {"duration": 2.0})
    episodes = SimEpisodes(threats, [3, 4])
    command = torch.tensor([[1.0, 0.01], [-2.0, -0.02]])
    for _ in range(3):
        episodes.step(command)
    clone = episodes.take(torch.tensor([1, 0, 1]))
    for _ in range(5):
        episodes.step(command)
        clone.step(command[[1, 0, 1]])
    for field, (original, copy) in zip(episodes.state._fields, zip(episodes.state, clone.state)):
        assert torch.equal(original[[1, 0, 1]], copy), field
    assert clone.steps.tolist() == [8, 8, 8] and clone.seeds.tolist() == [4, 3, 4]


@pytest.mark.parametrize("rows, message", [([0, 1], "1-D int64 tensor"), (torch.tensor([0.0]), "1-D int64 tensor"),
                                           (torch.tensor([2]), r"in \[0, 1\]"),
                                           (torch.tensor([], dtype=torch.int64), "at least one")])
def test_take_refuses_bad_rows(rows, message):
    with pytest.raises(ValueError, match=message):
        SimEpisodes(scenario(), [1, 2]).take(rows)


def replay(name: str, seed: int, commands: list) -> tuple[SimEpisodes, list]:
    """Drive ``commands`` from ``seed``: the episodes and the road states before each command."""
    episodes = SimEpisodes(scenario(name), [seed])
    states = []
    for acceleration, steering in commands:
        states.append(tuple(field.clone() for field in episodes.road_state()))
        episodes.step(torch.tensor([[acceleration, steering]]))
    return episodes, states


def replayed_task_return(name: str, seed: int, commands) -> float:
    """highway-env's reward of the states after each of ``commands``, summed (the evaluation's task return)."""
    episodes = SimEpisodes(scenario(name), [seed])
    total = 0.0
    for acceleration, steering in commands:
        episodes.step(torch.tensor([[acceleration, steering]]))
        total += float(highway_reward(episodes.state, episodes.config)[0])
    return total


def test_the_verified_ceiling_replays_and_keeps_a_way_out_at_every_step(verified_ceiling):
    checker = Verifier.for_scenario(scenario(), compile=False)
    for result in verified_ceiling:
        assert not result.crashed and len(result.commands) == 15
        episodes, states = replay("high_speed", result.seed, result.commands)
        assert not bool(episodes.crashed[0])
        start_x = float(states[0][0][0, 0])
        assert float(episodes.state.x[0, 0]) - start_x == pytest.approx(result.distance, abs=1e-3)
        speeds = torch.stack([state[0][0, 3] for state in states]).double()
        assert float(speeds.mean()) == pytest.approx(result.mean_speed, abs=1e-4)
        assert replayed_task_return("high_speed", result.seed, result.commands) == pytest.approx(result.task_return, abs=1e-6)
        stored = None
        for (ego, vehicles, mask), (acceleration, steering) in zip(states, result.commands):
            verdict = checker.check(ego, vehicles, mask, torch.tensor([[acceleration]]), torch.tensor([[steering]]))
            if bool(verdict.verified[0, 0]):
                stored = verdict.lane[:, 0], verdict.deceleration[:, 0]
                continue
            assert stored is not None, "the first command must verify: there is no fail-safe to continue"
            held = checker.failsafe_command(ego, *stored)
            assert (acceleration, steering) == pytest.approx((float(held[0]), float(held[1])), abs=1e-5)


def test_the_ceiling_is_at_or_above_its_driver(verified_ceiling):
    for result in verified_ceiling:
        assert result.score >= result.driver_score - 1e-9
        assert result.distance >= result.driver_distance - 1e-9
        assert not result.driver_crashed


def test_the_drivers_node_drives_as_the_driver_alone(verified_ceiling):
    alone = run_lockstep(scenario(), SEEDS, driver=make_driver("verified:mpc", scenario()))
    for result, episode in zip(verified_ceiling, alone):
        assert result.driver_mean_speed == pytest.approx(episode.metrics["mean_speed"], abs=1e-4)
        assert result.driver_meta_cost == pytest.approx(episode.metrics["meta_cost_mean"], rel=1e-4)
        assert result.driver_task_return == pytest.approx(episode.metrics["task_return"], rel=1e-4)


def test_the_unprotected_ceiling_in_cruise_ranks_by_the_meta_cost():
    found = search_ceiling(scenario("cruise", 1.0), [5], CeilingConfig(beam=4, verify=False, siblings=2))
    (result,) = found
    assert result.score == pytest.approx(-result.meta_cost)
    assert result.meta_cost <= result.driver_meta_cost + 1e-9
    episodes, _ = replay("cruise", 5, result.commands)
    assert not bool(episodes.crashed[0])


def test_a_cruise_search_ranked_by_distance_drives_at_least_as_far_as_its_driver():
    (result,) = search_ceiling(scenario("cruise", 1.0), [5], CeilingConfig(beam=4, verify=False, siblings=2, rank="distance"))
    assert result.score == pytest.approx(result.distance) and result.driver_score == pytest.approx(result.driver_distance)
    assert result.distance >= result.driver_distance - 1e-9


def test_a_search_ranked_by_the_task_return_finds_the_return_it_reports():
    """Cruise pays highway-env's reward only for the right lane below 20 m/s: ranked by it, the
    search finds at least the driver's return, and its episode replays to the return it reports."""
    found = search_ceiling(scenario("cruise", 1.0), [5, 6], CeilingConfig(beam=4, siblings=2, rank="task_return"))
    for result in found:
        assert not result.crashed and result.score == pytest.approx(result.task_return)
        assert result.task_return >= result.driver_task_return - 1e-9 and result.driver_score == pytest.approx(result.driver_task_return)
        assert replayed_task_return("cruise", result.seed, result.commands) == pytest.approx(result.task_return, abs=1e-6)


@pytest.mark.parametrize("settings, message", [({"beam": 0}, "beam"), ({"screened": 0}, "screened"),
                                               ({"siblings": 0}, "siblings"), ({"branch_period": 0.0}, "branch_period"),
                                               ({"cell": (0.1, 0.0, 0.1)}, "cell_y"), ({"beam": "8"}, "beam"), ({"driver": "nope"}, "nope"),
                                               ({"rank": "reward"}, "rank")])
def test_bad_settings_are_refused(settings, message):
    with pytest.raises(ValueError, match=message):
        CeilingConfig(**settings)


def test_seeds_must_be_distinct():
    with pytest.raises(ValueError, match="each once"):
        search_ceiling(scenario(), [1, 1])


def load_script():
    spec = importlib.util.spec_from_file_location("ceiling_script", ROOT / "scripts" / "ceiling.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_script_keeps_its_rows_resumes_and_refuses_other_settings(tmp_path, capsys):
    script = load_script()
    argv = ["--scenarios", "high_speed", "--seeds", "3", "--duration", "0.3", "--beam", "2", "--kinds", "unprotected",
            "--compile", "off", "--out", str(tmp_path)]
    assert script.main(argv) == 0
    rows = (tmp_path / "ceiling.jsonl").read_text().splitlines()
    assert len(rows) == 1 and json.loads(rows[0])["kind"] == "unprotected"
    with (tmp_path / "ceiling.jsonl").open("a") as file:
        file.write('{"scenario": "high_')  # a row cut short by an interruption
    assert script.main(argv) == 0  # nothing searched again: the seed is done
    assert "unfinished row" in capsys.readouterr().err
    assert (tmp_path / "ceiling.jsonl").read_text().splitlines() == rows  # the cut row is gone, the kept one stays
    summary = json.loads((tmp_path / "summary.json").read_text())
    (entry,) = summary["table"]
    assert entry["seeds"] == 1 and entry["at_or_above_driver"] == 1
    assert script.main([*argv[:-2], "--beam", "3", "--out", str(tmp_path)]) == 2
    assert "other settings" in capsys.readouterr().err
    settings = json.loads((tmp_path / "settings.json").read_text())
    assert settings.pop("rank") == "scenario"
    (tmp_path / "settings.json").write_text(json.dumps(settings))  # a folder written before `rank` existed
    assert script.main(argv) == 0  # read as ranked by the scenario's score
    assert script.main([*argv[:-2], "--rank", "task_return", "--out", str(tmp_path)]) == 2
    assert "'rank': ('scenario', 'task_return')" in capsys.readouterr().err
