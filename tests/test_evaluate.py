"""``mmpc evaluate``: episodes.csv, summary with intervals, report, TensorBoard, error rows,
resuming after a killed worker or a killed coordinator, Ray vs the local backend."""

import dataclasses
import fcntl
import json
import math
import multiprocessing
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import torch

from mmpc.cli.main import main
from mmpc.highway.runner import run_episode
from mmpc.drivers import Decision, Driver, Observation, registry
from mmpc.evaluate import METRIC_COLUMNS, Backend, EvaluationConfig, evaluate, read_episodes, run_tasks
from mmpc.evaluate.intervals import mean_ci, t_quantile_975, welch_ci, wilson_ci
from mmpc.evaluate.report import summarize
from mmpc.highway import HighwayEpisode
from mmpc.problem import EGO_V, EGO_Y
from mmpc.scenario import load_scenario
from mmpc.solver.execution import COMPILE_ENV

REPO = Path(__file__).resolve().parents[1]
#: The per-episode results (what must not depend on the backend); timings excluded.
RESULT_COLUMNS = [c for c in METRIC_COLUMNS if not c.startswith("solve_ms")]


class KeepLane(Driver):
    """Holds the start lane at 14 m/s (proportional control); with ``fail_below`` it raises on
    its third decision when an episode of the batch is left of ``y = fail_below``."""

    name = "keep-lane"
    episodes_started = 0

    def __init__(self, fail_below=None):
        self.fail_below = fail_below
        self.calls = 0
        self.lane_y = None

    def reset(self, num_envs):
        KeepLane.episodes_started += num_envs
        self.calls = 0
        self.lane_y = None

    def decide(self, observation: Observation) -> Decision:
        self.calls += 1
        ego = observation.ego
        if self.lane_y is None:
            self.lane_y = torch.round(ego[:, EGO_Y] / 4.0) * 4.0
        if self.fail_below is not None and self.calls == 3 and bool((ego[:, EGO_Y] < self.fail_below).any()):
            raise RuntimeError(f"test driver: an episode left of y = {self.fail_below}")
        lane_y = self.lane_y[observation.ids()]
        acceleration = 0.8 * (14.0 - ego[:, EGO_V])
        steering = (-0.02 * (ego[:, EGO_Y] - lane_y)).clamp(-0.05, 0.05)
        return Decision.command_only(acceleration, steering, solve_ms=0.1)


@pytest.fixture
def keep_lane_drivers(monkeypatch):
    monkeypatch.setitem(registry._registered, "keep-lane", lambda scenario, argument: KeepLane())
    monkeypatch.setitem(registry._registered, "flaky", lambda scenario, argument: KeepLane(fail_below=float(argument)))
    KeepLane.episodes_started = 0


def short(name="cruise", duration=1.0):
    return load_scenario(name).replace(duration=duration)


def test_intervals_match_tables():
    for dof, table in ((1, 12.7062), (2, 4.3027), (3, 3.1824), (5, 2.5706), (10, 2.2281), (30, 2.0423)):
        assert t_quantile_975(dof) == pytest.approx(table, rel=2e-3)
    mean, interval = mean_ci([1.0, 2.0, 3.0, float("nan"), None])
    assert mean == 2.0 and interval == pytest.approx([2.0 - 4.3027 / math.sqrt(3), 2.0 + 4.3027 / math.sqrt(3)], rel=1e-3)
    assert mean_ci([5.0]) == (5.0, None) and mean_ci([]) == (None, None)
    assert wilson_ci(0, 10) == pytest.approx([0.0, 0.2775], abs=1e-4)  # the textbook value
    assert wilson_ci(5, 10) == pytest.approx([0.2366, 0.7634], abs=1e-4)
    assert wilson_ci(0, 0) is None
    for trials in range(1, 60):  # the rate lies inside its own interval (0 and 1 exactly at the ends)
        for successes in (0, trials // 2, trials):
            low, high = wilson_ci(successes, trials)
            assert low <= successes / trials <= high
    difference, interval = welch_ci([1.0, 2.0, 3.0], [2.0, 3.0, 4.0, float("inf")])  # 4 Welch degrees of freedom
    assert difference == 1.0 and interval == pytest.approx([1.0 - 2.7764 * math.sqrt(2 / 3), 1.0 + 2.7764 * math.sqrt(2 / 3)], rel=1e-3)
    assert welch_ci([1.0, 1.0], [2.0, 2.0]) == (1.0, [1.0, 1.0]) and welch_ci([1.0], [2.0, 3.0]) == (1.5, None)
    assert welch_ci([], [2.0]) == (None, None)
    with pytest.raises(ValueError, match="dof"):
        t_quantile_975(0)


@pytest.mark.usefixtures("one_thread", "keep_lane_drivers")
def test_two_drivers_summary_report_and_tensorboard(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    scenario = short()
    config = EvaluationConfig(drivers=("mpc", "keep-lane"), seeds=(0, 1, 2), lockstep=2)
    evaluation = evaluate([scenario], tmp_path, config)
    rows = read_episodes(tmp_path / "episodes.csv")
    assert sorted((r["driver"], r["seed"]) for r in rows) == [(d, s) for d in ("keep-lane", "mpc") for s in (0, 1, 2)]
    assert all(r["status"] == "ok" and r["steps"] == 10 for r in rows)
    assert [(r["seed"], r["group"], r["group_size"]) for r in rows if r["driver"] == "mpc"] == [(0, 0, 2), (1, 0, 2), (2, 1, 1)]
    # a lockstep group gives each episode its result alone (up to rounding)
    alone = run_episode(scenario, 1).metrics
    mpc1 = next(r for r in rows if r["driver"] == "mpc" and r["seed"] == 1)
    assert mpc1["mean_speed"] == pytest.approx(alone["mean_speed"], rel=1e-4)
    assert mpc1["solve_ms_per_episode_mean"] < mpc1["solve_ms_mean"]  # one decision served two episodes

    report = json.loads((tmp_path / "summary.json").read_text())
    assert report["summary"] == evaluation.summary and report["drivers"] == ["mpc", "keep-lane"]
    by_driver = {entry["driver"]: entry for entry in report["summary"]}
    for driver, entry in by_driver.items():
        speeds = [r["mean_speed"] for r in rows if r["driver"] == driver]
        assert entry["episodes"] == 3 and entry["errors"] == 0
        assert entry["mean_speed"] == pytest.approx(sum(speeds) / 3)
        assert entry["mean_speed_ci"] == pytest.approx(list(mean_ci(speeds)[1]))
        assert entry["mean_speed_ci"][0] <= entry["mean_speed"] <= entry["mean_speed_ci"][1]
        assert entry["collision_rate"] == 0.0 and entry["collision_rate_ci"] == pytest.approx(wilson_ci(0, 3))
        for key in ("meta_cost_mean", "solve_ms_mean"):
            assert entry[key] is not None and len(entry[f"{key}_ci"]) == 2
    assert by_driver["keep-lane"]["solve_ms_mean"] == pytest.approx(0.1, rel=1e-6)
    markdown = (tmp_path / "summary.md").read_text()
    assert "`mpc` | `keep-lane`" in markdown and "collision rate" in markdown and "±" in markdown
    assert (tmp_path / "compare.png").stat().st_size > 10_000

    for driver in ("mpc", "keep-lane"):  # TensorBoard scalars read back from the event files
        accumulator = EventAccumulator(str(tmp_path / "tensorboard" / driver)).Reload()
        speeds = {event.step: event.value for event in accumulator.Scalars("cruise/mean_speed")}
        assert speeds == pytest.approx({r["seed"]: r["mean_speed"] for r in rows if r["driver"] == driver}, rel=1e-6)
        [summary_speed] = accumulator.Scalars("summary/cruise/mean_speed")
        assert summary_speed.value == pytest.approx(by_driver[driver]["mean_speed"], rel=1e-6)

    # the same call again runs nothing and duplicates nothing (TensorBoard rebuilt, not appended)
    started = KeepLane.episodes_started
    again = evaluate([scenario], tmp_path, config)
    assert KeepLane.episodes_started == started and repr(again.rows) == repr(evaluation.rows)  # NaN-aware
    assert len(read_episodes(tmp_path / "episodes.csv")) == 6
    accumulator = EventAccumulator(str(tmp_path / "tensorboard" / "mpc")).Reload()
    assert len(accumulator.Scalars("cruise/mean_speed")) == 3
    # another scenario under the same name is refused; so is a second evaluation writing at once
    with pytest.raises(ValueError, match="another scenario named 'cruise'"):
        evaluate([short(duration=2.0)], tmp_path, config)
    with open(tmp_path / ".evaluate.lock", "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        with pytest.raises(RuntimeError, match="another evaluation"):
            evaluate([scenario], tmp_path, config)


@pytest.mark.usefixtures("one_thread", "keep_lane_drivers")
def test_failing_episodes_are_error_rows_and_a_rerun_retries_only_them(tmp_path):
    scenario = short(duration=0.6)
    seeds = tuple(range(8))
    starts = {}
    for seed in seeds:
        episode = HighwayEpisode(scenario, seed)
        starts[seed] = float(episode.observe().ego[0, EGO_Y])
        episode.close()
    failing = sorted(seed for seed, y in starts.items() if y < 10.0)
    assert 0 < len(failing) < len(seeds)  # both kinds among the seeds

    config = EvaluationConfig(drivers=("flaky:10",), seeds=seeds, lockstep=4, report=False)
    first = evaluate([scenario], tmp_path, config)
    assert sorted(r["seed"] for r in first.rows if r["status"] == "error") == failing
    assert all("RuntimeError: test driver" in r["error"] and r["group_size"] == 1 for r in first.rows if r["status"] == "error")
    entry = first.summary[0]
    assert entry["errors"] == len(failing) and entry["error_seeds"] == failing
    assert entry["episodes"] == len(seeds) - len(failing)
    lines_before = (tmp_path / "episodes.csv").read_text().splitlines()

    registry._registered["flaky"] = lambda scenario, argument: KeepLane()  # the bug fixed: re-run the same call
    started = KeepLane.episodes_started
    second = evaluate([scenario], tmp_path, config)
    assert KeepLane.episodes_started - started == len(failing)  # only the error episodes ran again
    rows = read_episodes(tmp_path / "episodes.csv")
    assert sorted(r["seed"] for r in rows) == list(seeds) and all(r["status"] == "ok" for r in rows)
    lines_after = (tmp_path / "episodes.csv").read_text().splitlines()
    kept = [line for line in lines_before[1:] if ",ok," in line]
    assert lines_after[1: 1 + len(kept)] == kept  # finished rows untouched
    assert second.summary[0]["errors"] == 0 and second.summary[0]["episodes"] == len(seeds)


@pytest.mark.usefixtures("one_thread")
def test_killed_worker_is_retried_and_every_episode_is_written_once(tmp_path):
    scenario = short(duration=1.5)
    config = EvaluationConfig(seeds=tuple(range(5)), workers=2, lockstep=1, report=False)
    killed = []

    def kill_a_worker():
        children = multiprocessing.active_children()
        if children:
            os.kill(children[0].pid, signal.SIGKILL)
            killed.extend(child.pid for child in children)

    def on_episode(row):
        if not killed and not threads:  # after the first episode, kill a worker busy with the next one
            threads.append(threading.Timer(0.4, kill_a_worker))
            threads[0].start()

    threads = []
    evaluation = evaluate([scenario], tmp_path, config, on_episode=on_episode)
    threads[0].join()
    assert killed  # a worker process did die mid-run
    rows = read_episodes(tmp_path / "episodes.csv")
    assert sorted(r["seed"] for r in rows) == list(range(5))
    assert all(r["status"] == "ok" for r in rows)
    pids = {int(r["worker"].rpartition(":")[2]) for r in rows}
    assert pids - set(killed)  # a new pool took over after the kill
    assert [r["seed"] for r in evaluation.rows] == list(range(5))


def _die():
    os.kill(os.getpid(), signal.SIGKILL)


class Poison:
    """Stands in for a scenario; the worker process that unpickles it dies at once."""

    name = "poison"

    def __reduce__(self):
        return _die, ()


@pytest.mark.slow
def test_a_group_that_always_kills_its_worker_becomes_error_rows():
    from mmpc.evaluate import Backend, GroupTask, run_group, run_tasks
    from mmpc.evaluate.tasks import error_rows

    good = GroupTask("mpc", short(duration=0.3), (0,), 0)
    poison = GroupTask("mpc", Poison(), (7, 8), 3)
    batches = run_tasks([poison, good], run_group, error_rows, Backend(workers=2, retries=1))
    rows = [row for _, batch in batches for row in batch]
    assert sorted((r["scenario"], r["seed"], r["status"]) for r in rows) == [
        ("cruise", 0, "ok"), ("poison", 7, "error"), ("poison", 8, "error")]
    assert all("worker process died 2 times" in r["error"] for r in rows if r["status"] == "error")


def test_killed_coordinator_resumes_without_loss_or_duplicates(tmp_path):
    argv = [sys.executable, "-m", "mmpc.cli", "evaluate", "--driver", "mpc", "--scenarios", "cruise", "--seeds", "0-5",
            "--duration", "1.0", "--lockstep", "1", "--out", str(tmp_path)]
    process = subprocess.Popen(argv, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                               env={**os.environ, "OMP_NUM_THREADS": "1"})
    csv_path = tmp_path / "episodes.csv"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and len(read_episodes(csv_path)) < 2:
        time.sleep(0.1)
    os.kill(process.pid, signal.SIGKILL)
    process.wait()
    before = read_episodes(csv_path)
    assert 2 <= len(before) < 6
    with open(csv_path, "a") as handle:  # a write cut short by the kill
        handle.write("mpc,cruise,5,ok,,5,1,vm:1,0.1,10,1.0,0")
    assert main(argv[3:]) == 0
    rows = read_episodes(csv_path)
    assert sorted(r["seed"] for r in rows) == list(range(6)) and all(r["status"] == "ok" for r in rows)
    assert rows[: len(before)] == before  # what was written before the kill is kept as it was
    summary = json.loads((tmp_path / "summary.json").read_text())["summary"]
    assert summary[0]["episodes"] == 6


def _compile_setting(task: str) -> str:
    return os.environ.get(COMPILE_ENV, "unset")


def _raise(task, error):
    raise error if isinstance(error, BaseException) else RuntimeError(error)


@pytest.mark.usefixtures("one_thread")
def test_ray_and_local_backends_give_identical_episodes(tmp_path, monkeypatch):
    ray = pytest.importorskip("ray")
    scenario = short()
    config = EvaluationConfig(seeds=(0, 1, 2, 3), workers=2, lockstep=2, report=False)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        on_ray = evaluate([scenario], tmp_path / "ray", dataclasses.replace(config, ray="auto"))
        ray_workers = {r["worker"] for r in on_ray.rows}
        # --compile sets MMPC_COMPILE after the cluster started: the tasks still see it
        with monkeypatch.context() as patch:
            patch.setenv(COMPILE_ENV, "1")
            seen = [value for _, value in run_tasks(["a"], _compile_setting, _raise, Backend(workers=1, ray="auto"))]
        assert seen == ["1"]
    finally:
        ray.shutdown()
    local = evaluate([scenario], tmp_path / "local", dataclasses.replace(config, workers=1))  # in this process
    assert ray_workers.isdisjoint({r["worker"] for r in local.rows})  # really two different sets of processes
    assert [r["seed"] for r in on_ray.rows] == [r["seed"] for r in local.rows] == [0, 1, 2, 3]
    for a, b in zip(on_ray.rows, local.rows):
        assert a["status"] == b["status"] == "ok"
        assert {k: a[k] for k in RESULT_COLUMNS} == {k: b[k] for k in RESULT_COLUMNS}  # bit for bit


def test_evaluate_cli_rejects_bad_arguments(tmp_path, capsys):
    assert main(["evaluate", "--lockstep", "0", "--out", str(tmp_path)]) == 2
    assert "lockstep" in capsys.readouterr().err
    assert main(["evaluate", "--collision-videos", "--out", str(tmp_path)]) == 2
    assert main(["evaluate", "--workers", "0", "--out", str(tmp_path)]) == 2
    assert main(["evaluate", "--driver", "mpc,nobody", "--out", str(tmp_path)]) == 2
    assert "unknown driver 'nobody'" in capsys.readouterr().err
    with pytest.raises(ValueError, match="seeds"):
        EvaluationConfig(seeds=(1, 1))
    with pytest.raises(ValueError, match="episode_layout"):
        EvaluationConfig(episode_layout="{nothing}")
    assert not (tmp_path / "episodes.csv").exists()


def test_summary_of_rows_with_errors():
    rows = [dict(driver="d", scenario="s", seed=s, status="ok" if s < 3 else "error", collisions=int(s == 1), offroad=0,
                 mean_speed=10.0 + s, solve_ms_max=5.0, min_clearance=2.0) for s in range(4)]
    [entry] = summarize(rows)
    assert entry["episodes"] == 3 and entry["errors"] == 1 and entry["error_seeds"] == [3]
    assert entry["collisions"] == 1 and entry["collision_rate"] == pytest.approx(1 / 3)
    assert entry["mean_speed"] == pytest.approx(11.0) and entry["speed_residual_mean"] is None


def test_crash_scenes_are_written_read_back_and_tabled(tmp_path):
    from mmpc.collisions import CRASH_COLUMNS
    from mmpc.evaluate.report import format_crashes
    from mmpc.evaluate.store import EpisodeFile, new_row

    scene = dict(zip(CRASH_COLUMNS, (12.3, 3.5, -1.4, -14.0, 8.1, 11.6, 1.35, 19.7, 4)))
    crashed = new_row(driver="mpc", scenario="high_speed", seed=7, status="ok", collisions=1, collision_part="side",
                      ego_fault_collisions=1, **scene)
    calm = new_row(driver="mpc", scenario="high_speed", seed=8, status="ok", collisions=0, ego_fault_collisions=0)
    episodes = EpisodeFile(tmp_path / "episodes.csv", [crashed])
    episodes.append([calm])
    episodes.close()
    rows = read_episodes(tmp_path / "episodes.csv")
    assert [rows[0][column] for column in CRASH_COLUMNS] == list(scene.values())
    assert isinstance(rows[0]["crash_fallback_steps"], int)
    assert all(rows[1][column] is None for column in CRASH_COLUMNS)
    table = format_crashes(rows)
    assert ("`mpc` / high_speed: 1 collisions; struck 0 front, 1 side, 0 rear; collider turned > 5 deg in 1, "
            "ego > 1 m off its lane centre in 1, a fallback drove in the last second in 1") in table
    assert "| 7 | 12.3 | side | 3.5 | -1.4 | -14.0 | 8.1 | 11.6 | 1.35 | 19.7 | 4 |" in table
    assert format_crashes(rows[1:]) == ""
