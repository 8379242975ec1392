"""Episodes on the batched simulator: traffic placed like highway-env's, the window, time
limits, per-environment resets, the runner's batched world, and refused scenarios."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math

import numpy as np
import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from mmpc.config import to_dict
from mmpc.evaluate.store import scenario_fingerprint
from mmpc.highway import HighwayEpisode, run_lockstep
from mmpc.highway.batched_world import BatchedWorld
from mmpc.highway.worlds import make_world
from mmpc.scenario import ScenarioConfig, load_scenario
from mmpc.traffic_config import IDMTraffic, NGSIMTraffic, ScriptedTraffic, ScriptedVehicle
from mmpc.sim import SimConfig, SimEpisodes, kinematics_observation, lane_keeping_steering, pair_collisions, vehicle_state
from mmpc.sim.random import integers, uniform
from mmpc.sim.traffic import PLACEMENT_GAP, initial_state, keep_in_window, sim_config

CRUISE = load_scenario("cruise")


def test_draws_depend_on_seed_and_indices_only():
    seeds = torch.arange(6)[:, None]
    draws = uniform(seeds, 3, torch.arange(1000))
    assert torch.equal(draws[2], uniform(torch.tensor([[2]]), 3, torch.arange(1000))[0])  # alone = in a batch
    assert not torch.equal(draws[0], draws[1]) and not torch.equal(draws[0], uniform(seeds, 4, torch.arange(1000))[0])
    assert 0.0 <= float(draws.min()) and float(draws.max()) < 1.0
    assert abs(float(draws.mean()) - 0.5) < 0.01 and abs(float(draws.std()) - 12 ** -0.5) < 0.01
    counts = torch.bincount(integers(seeds, 0, torch.arange(6000), high=6).flatten(), minlength=6)
    assert int(counts.min()) > 5500 and int(counts.max()) < 6500  # 6000 expected each


def _placement_statistics(states: list[tuple[float, int, np.ndarray, np.ndarray, np.ndarray]]) -> dict[str, float]:
    """Per-start summaries: ego x, ego lane, vehicles ahead of the ego, their mean gap, their speeds."""
    ego_x = np.array([s[0] for s in states])
    ahead = np.array([float((s[2] > s[0]).mean()) for s in states])
    spread = np.array([float(s[2].max() - s[2].min()) for s in states])
    speeds = np.concatenate([s[4] for s in states])
    lanes = np.concatenate([s[3] for s in states])
    return {"ego_x": ego_x.mean(), "ahead": ahead.mean(), "spread": spread.mean(), "speed": speeds.mean(),
            "lane_spread": np.bincount(lanes, minlength=CRUISE.lanes).std() / len(lanes)}


def test_initial_traffic_is_distributed_as_highway_env_places_it():
    """100 starts of the cruise scenario in each: the same means within a few standard errors."""
    seeds = list(range(100))
    highway = []
    for seed in seeds:
        episode = HighwayEpisode(CRUISE, seed)
        others = [v for v in episode.unwrapped.road.vehicles if v is not episode.ego]
        highway.append((float(episode.ego.position[0]), int(episode.ego.lane_index[2]), np.array([v.position[0] for v in others]),
                        np.array([v.lane_index[2] for v in others]), np.array([v.speed for v in others])))
        episode.close()
    state = initial_state(CRUISE, torch.tensor(seeds), dtype=torch.float64)
    batched = [(float(state.x[e, 0]), int(state.lane[e, 0]), state.x[e, 1:].numpy(), state.lane[e, 1:].numpy(),
                state.speed[e, 1:].numpy()) for e in range(len(seeds))]
    reference, ours = _placement_statistics(highway), _placement_statistics(batched)
    assert ours["ego_x"] == pytest.approx(reference["ego_x"], abs=2.0)  # 3 o U(0.9, 1.1) + o: sd ~1.5 m, se 0.15 m
    assert ours["ahead"] == pytest.approx(reference["ahead"], abs=0.03)
    assert ours["spread"] == pytest.approx(reference["spread"], rel=0.05)
    assert ours["speed"] == pytest.approx(reference["speed"], abs=0.15)  # U(7, 12): se 0.035 m/s
    assert ours["lane_spread"] == pytest.approx(reference["lane_spread"], abs=0.02)


def test_start_keeps_the_ego_lane_clear_ahead():
    state = initial_state(CRUISE, torch.arange(500))
    gap = state.x[:, 1:] - state.x[:, :1]
    same_lane = state.lane[:, 1:] == state.lane[:, :1]
    clearance = CRUISE.traffic.initial_clearance
    assert not bool((same_lane & (gap > -0.5 * clearance) & (gap < clearance)).any())
    assert bool((state.speed[:, 0] == CRUISE.ego.speed).all())
    assert float(state.speed[:, 1:].min()) >= 7.0 and float(state.speed[:, 1:].max()) <= 12.0
    assert bool((state.target_speed[:, 1:] == state.speed[:, 1:]).all())


def test_window_moves_a_vehicle_left_behind_into_a_free_gap_ahead():
    config = SimConfig(lanes=3)
    x = torch.tensor([[100.0, 20.0, 150.0, 400.0]], dtype=torch.float64)
    y = torch.tensor([[4.0, 4.0, 0.0, 8.0]], dtype=torch.float64)
    state = vehicle_state(x, y, speed=10.0, config=config)
    moved = keep_in_window(state, (60.0, 200.0), torch.tensor([7]), torch.tensor([0]), config)
    # slot 1 was 80 m behind: now in the last quarter ahead; slot 3 was 300 m ahead: now behind
    assert 100.0 + 150.0 <= float(moved.x[0, 1]) <= 100.0 + 200.0
    assert 100.0 - 60.0 <= float(moved.x[0, 3]) <= 100.0 - 45.0
    assert float(moved.x[0, 2]) == 150.0 and float(moved.x[0, 0]) == 100.0
    for slot in (1, 3):
        lane = int(moved.lane[0, slot])
        assert float(moved.y[0, slot]) == 4.0 * lane and lane == int(moved.target_lane[0, slot])
        others = [k for k in range(4) if k != slot]
        near = [(abs(float(moved.x[0, k] - moved.x[0, slot])) < PLACEMENT_GAP) and abs(float(moved.y[0, k]) - 4.0 * lane) < 4.0
                for k in others]
        assert not any(near)


def test_episode_ends_at_its_duration_and_running_mask_freezes_the_others():
    scenario = dataclasses.replace(CRUISE, duration=0.5)
    episodes = SimEpisodes(scenario, [3, 4], dtype=torch.float64)
    frozen = SimEpisodes(scenario, [4], dtype=torch.float64).state
    for _ in range(5):
        assert not bool(episodes.done[0])
        episodes.step(torch.zeros(2, 2), running=torch.tensor([True, False]))
    assert episodes.done.tolist() == [True, False] and episodes.time.tolist() == [0.5, 0.0]
    assert all(torch.equal(a[1:], b) for a, b in zip(episodes.state, frozen))


def test_reset_starts_one_environment_and_leaves_the_others():
    episodes = SimEpisodes(CRUISE, [0, 1, 2])
    for _ in range(3):
        episodes.step(torch.zeros(3, 2))
    before = episodes.state
    episodes.reset(torch.tensor([1]), [9])
    fresh = initial_state(CRUISE, torch.tensor([9]))
    assert all(torch.equal(a[1], b[0]) for a, b in zip(episodes.state, fresh))
    assert all(torch.equal(a[[0, 2]], b[[0, 2]]) for a, b in zip(episodes.state, before))
    assert episodes.steps.tolist() == [3, 0, 3] and episodes.seeds.tolist() == [0, 9, 2]


def test_an_environment_runs_the_same_episode_alone_or_in_a_batch():
    commands = 0.3 * torch.sin(torch.arange(60, dtype=torch.float64))[:, None] * torch.tensor([1.0, 0.01], dtype=torch.float64)
    batch, alone = SimEpisodes(CRUISE, [5, 11, 12], dtype=torch.float64), SimEpisodes(CRUISE, [11], dtype=torch.float64)
    for command in commands:
        batch.step(command.expand(3, 2).clone())
        alone.step(command[None].clone())
    assert all(torch.equal(a[1], b[0]) for a, b in zip(batch.state, alone.state))


class ValueReads(TorchDispatchMode):
    """Counts the tensor values read on the host (each one stalls a GPU's queue)."""

    count = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.count += func is torch.ops.aten._local_scalar_dense.default
        return func(*args, **(kwargs or {}))


def test_a_step_reads_no_value_on_the_host():
    """With fixed shapes (compiled, or on a GPU): the command's finiteness is checked on the device
    (:attr:`SimEpisodes.refused`), the window moves vehicles in a fixed number of rounds, the
    compactions have fixed sizes."""
    episodes = SimEpisodes(CRUISE, [0, 1, 2], fixed_shapes=True)
    with ValueReads() as reads:
        for _ in range(3):
            episodes.step(torch.zeros(3, 2))
    assert reads.count == 0


def test_a_batched_world_observes_without_reading_values_on_the_host():
    world = BatchedWorld.start(CRUISE, [0, 1, 2])
    world.apply([0, 1, 2], torch.tensor([1.0, 0.0, -1.0]), torch.zeros(3))
    with ValueReads() as reads:
        batch, _ = world.observe([0, 1, 2])
    assert reads.count == 0
    checked = kinematics_observation(world.sim.state, world.sim.config)
    assert np.array_equal(batch.kinematics, checked.float().numpy())


def test_a_batched_world_s_single_rows_are_the_batch_s_rows_on_the_host():
    world = BatchedWorld.start(CRUISE, [0, 1, 2])
    world.apply([0, 1, 2], torch.tensor([1.0, 0.0, -1.0]), torch.zeros(3))
    batch, rows = world.observe([2, 0])
    assert len(rows) == 2
    for row, single in ((0, rows[0]), (1, rows[1]), (1, rows[-1])):
        assert single.ego.shape == (1, 6) and torch.equal(single.ego, batch.ego[row:row + 1])
        assert torch.equal(single.vehicles, batch.vehicles[row:row + 1])
        assert torch.equal(single.vehicle_mask, batch.vehicle_mask[row:row + 1])
        assert np.array_equal(single.kinematics, batch.kinematics[row:row + 1]) and single.env_ids is None
    assert torch.equal(world.episodes[0].observe().ego, rows[1].ego)
    with pytest.raises(IndexError):
        rows[2]


def test_road_state_is_the_mpc_s_frame():
    episodes = SimEpisodes(CRUISE, [0, 1])
    episodes.step(torch.tensor([[1.0, 0.05], [0.0, 0.0]]))
    ego, vehicles, mask = episodes.road_state()
    beta = math.atan(0.5 * math.tan(float(episodes.applied[0, 1])))
    assert float(ego[0, 2]) == pytest.approx(float(episodes.state.heading[0, 0]) + beta, abs=1e-6)
    assert float(ego[0, 4]) == pytest.approx(1.0, abs=1e-6)
    assert float(ego[0, 5]) == pytest.approx(float(ego[0, 3]) * math.sin(beta) / 2.5, abs=1e-5)
    assert vehicles.shape == (2, CRUISE.traffic.vehicles_count, 4) and bool(mask.all())
    state = episodes.state
    assert torch.allclose(vehicles[..., 2], state.speed[:, 1:] * torch.cos(state.heading[:, 1:]))


def test_fast_highway_checks_the_ego_s_collisions_only():
    fast = dataclasses.replace(load_scenario("rl_highway_fast"), sim="batched")
    state = initial_state(fast, torch.tensor([0]))
    assert state.check_collisions[0].tolist() == [True] + [False] * fast.traffic.vehicles_count
    x, y = torch.tensor([[0.0, 50.0, 52.0, 1.0]]), torch.tensor([[0.0, 4.0, 4.0, 0.5]])
    for others_check, expected in ((False, [[0, 3]]), (True, [[0, 3], [1, 2]])):
        overlapping = vehicle_state(x, y, speed=10.0, check_collisions=torch.tensor([[True, others_check, others_check, others_check]]))
        pairs = pair_collisions(overlapping, 0.1)[0].intersecting[0]
        assert pairs.nonzero().tolist() == expected


def test_lane_keeping_turns_towards_the_target_lane_in_float32_when_the_slip_saturates():
    """tan(asin(1)) in float32 is a large negative number: the steering must still point to the target lane."""
    for dtype in (torch.float32, torch.float64):
        state = vehicle_state(torch.tensor([[0.0, 10.0]], dtype=dtype), torch.tensor([[0.0, 10.76]], dtype=dtype),
                              heading=torch.tensor([[0.0, -0.445]], dtype=dtype), speed=8.12, config=SimConfig(lanes=6),
                              target_lane=torch.tensor([[0, 4]]))
        steering = lane_keeping_steering(state, SimConfig(lanes=6))
        assert float(steering[0, 1]) == pytest.approx(math.pi / 3, abs=1e-6)


@pytest.mark.parametrize("traffic", [ScriptedTraffic(vehicles=(ScriptedVehicle(lane=1, x=30.0, speed=10.0),)),
                                     NGSIMTraffic(path="recording.csv")])
def test_a_scenario_the_batched_simulator_cannot_run_is_refused_naming_highway_env(traffic):
    with pytest.raises(ValueError, match="--sim highway-env"):
        ScenarioConfig(traffic=traffic, sim="batched", vehicle_size=None)
    with pytest.raises(ValueError, match="--sim highway-env"):
        SimEpisodes(ScenarioConfig(traffic=traffic), [0])


def test_unknown_world_and_env_id_are_refused():
    with pytest.raises(ValueError, match="`sim` must be one of"):
        ScenarioConfig(sim="carla")
    with pytest.raises(ValueError, match="--sim highway-env"):
        ScenarioConfig(env_id="merge-v0", sim="batched")


@pytest.mark.parametrize("seeds, message", [([], "at least one seed"), ([0.5], "sequence of ints"), ([-1], ">= 0")])
def test_bad_seeds_are_refused(seeds, message):
    with pytest.raises(ValueError, match=message):
        SimEpisodes(CRUISE, seeds)


def test_bad_running_mask_and_reset_are_refused():
    episodes = SimEpisodes(CRUISE, [0, 1])
    with pytest.raises(ValueError, match=r"`running` must have shape \(2,\)"):
        episodes.step(torch.zeros(2, 2), running=torch.tensor([True]))
    with pytest.raises(ValueError, match=r"must lie in \[0, 1\]"):
        episodes.reset(torch.tensor([2]), [5])
    before = episodes.state
    episodes.step(torch.tensor([[0.0, 0.0], [float("nan"), 0.0]]))
    assert episodes.refused.tolist() == [False, True] and episodes.done.tolist() == [False, True]
    assert all(torch.equal(new[1], old[1]) for new, old in zip(episodes.state, before))
    episodes.step(torch.zeros(2, 2))
    assert episodes.steps.tolist() == [2, 0]  # a refused environment stays where it stopped
    episodes.reset([1], [7])
    assert episodes.refused.tolist() == [False, False]
    world = BatchedWorld.start(CRUISE, [0, 1])
    world.apply([0, 1], torch.tensor([0.0, float("inf")]), torch.zeros(2))
    with pytest.raises(ValueError, match=r"environments \[1\] \(seeds \[1\]\) were given a command that is not finite"):
        world.status()


def test_the_runner_drives_the_mpc_on_the_batched_simulator():
    scenario = dataclasses.replace(CRUISE, sim="batched", duration=3.0)
    results = run_lockstep(scenario, [0, 1, 2])
    for result in results:
        assert result.metrics["steps"] == 30 and result.metrics["collisions"] == 0
        assert result.records[-1].v > 10.0 and 0 <= result.records[-1].lane < scenario.lanes
    world = make_world(scenario, [4])
    assert isinstance(world, BatchedWorld) and world.episodes[0].seed == 4 and not world.episodes[0].done
    with pytest.raises(ValueError, match="--sim highway-env"):
        make_world(scenario, [4], render=True)


def test_the_settings_hash_counts_the_world_only_when_batched():
    reference = CRUISE
    assert reference.sim == "highway-env"
    settings = to_dict(reference)
    del settings["sim"]
    assert scenario_fingerprint(reference) == hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]
    assert scenario_fingerprint(dataclasses.replace(reference, sim="batched")) != scenario_fingerprint(reference)


def test_the_sim_config_follows_the_scenario():
    scenario = ScenarioConfig(lanes=3, frequency=15.0, traffic=IDMTraffic(vehicles_count=4))
    config = sim_config(scenario)
    assert (config.lanes, config.simulation_frequency, config.policy_frequency) == (3, 15.0, 15.0)


def test_the_simulator_benchmark_writes_its_three_tables(tmp_path, capsys):
    import bench_sim

    argv = ["--envs", "1,4", "--mpc-envs", "2", "--rl-envs", "2", "--rl-steps", "1", "--rl-warmup", "1", "--memory-envs", "4", "--steps", "2",
            "--mpc-steps", "2", "--mpc-schedules", "paper,shipped", "--highway-envs", "1", "--out", str(tmp_path)]
    assert bench_sim.main(argv) == 0
    rows = json.loads((tmp_path / "bench_sim.json").read_text())["rows"]
    assert [(r["table"], r["world"], r["num_envs"]) for r in rows if r["table"] not in ("memory", "rl")] == [
        ("world", "highway-env", 1), ("world", "batched", 1), ("world", "batched", 4),
        ("mpc", "highway-env", 2), ("mpc", "batched", 2), ("mpc", "highway-env", 2), ("mpc", "batched", 2)]
    # after the untimed first step (cold): the paper's rows run the whole schedule; the shipped rows warm-start
    # (10 iterations where no environment fell back, found no feasible goal warm or solved cold) at the timed steps
    mpc = [r for r in rows if r["table"] == "mpc"]
    assert [r["schedule"] for r in mpc] == ["paper", "paper", "shipped", "shipped"]
    assert [r["iterations_per_step"] for r in mpc[:2]] == [100, 100] and all(10 <= r["iterations_per_step"] < 100 for r in mpc[2:])
    assert [(r["warm_iterations"], r["exit_checks"]) for r in mpc] == [(0, [])] * 2 + [(10, [])] * 2
    for r in mpc:  # the projection of 1,024 episodes x 40 s at the row's rate, one process
        assert r["evaluation_minutes"] == pytest.approx(1024 * 400 / r["env_steps_per_s"] / 60)
    assert [(r["world"], r["replan"], r["verify"], r["num_envs"]) for r in rows if r["table"] == "rl"] == [
        (world, replan, verify, 2) for world in ("highway-env", "batched") for replan in ("frame", "decision")
        for verify in (True, False)]  # the check's cost: with and without it, side by side
    # at every frame a solve served every environment when replanning at every frame; at the decision at least with decisions
    assert [r["solved_frame_share"] == 1.0 for r in rows if r["table"] == "rl"] == [True, True, False, False] * 2
    assert all(0.2 <= r["solved_frame_share"] <= 1 for r in rows if r["table"] == "rl")
    assert all(r["env_steps_per_s"] > 0 for r in rows if r["table"] in ("world", "mpc"))
    assert all(r["agent_steps_per_s"] > 0 for r in rows if r["table"] == "rl")
    assert all(0 < r["solve_share"] <= 1 for r in rows if r["table"] == "mpc")
    memory = [r for r in rows if r["table"] == "memory"]
    assert memory[0]["num_envs"] == 4 and memory[0]["state_bytes_per_env"] > 20 * 4 * 16  # 20 vehicles x 16 fields
    assert "MPC in the loop" in capsys.readouterr().out
    with pytest.raises(ValueError, match="--sim highway-env"):
        bench_sim.main(["--scenario", "cruise_ngsim", "--out", str(tmp_path)])
    with pytest.raises(SystemExit):
        bench_sim.main(["--mpc-schedules", "warm", "--out", str(tmp_path)])
    assert "--mpc-schedules takes names of ['paper', 'shipped']" in capsys.readouterr().err
    # a recipe with the expert action: it stays in the decision rows (frame replanning cannot have it)
    recipe = bench_sim.rl_rows([2], steps=1, replans=("frame", "decision"), warmup=0, rl_config="high_speed", verify=(True,))
    assert [(r["world"], r["replan"], r["expert_action"], r["config"]) for r in recipe] == [
        ("highway-env", "frame", False, "high_speed"), ("highway-env", "decision", True, "high_speed"),
        ("batched", "frame", False, "high_speed"), ("batched", "decision", True, "high_speed")]


def test_reward_is_highway_env_s_along_episodes_that_crash_or_leave_the_road():
    from mmpc.sim.reward import highway_reward

    scenario = dataclasses.replace(CRUISE, lanes=3, traffic=IDMTraffic(vehicles_count=6, window=None))
    config = sim_config(scenario)
    compared = crashed_or_off = 0
    for seed, steering in ((0, 0.02), (1, -0.02), (2, 0.0)):
        episode = HighwayEpisode(scenario, seed)
        for _ in range(60):
            episode.apply(4.0, steering)
            ego = episode.ego
            state = vehicle_state(torch.tensor([[ego.position[0]]], dtype=torch.float64), torch.tensor([[ego.position[1]]], dtype=torch.float64),
                                  heading=float(ego.heading), speed=float(ego.speed), config=config)
            state = state._replace(crashed=torch.tensor([[bool(ego.crashed)]]))
            assert float(highway_reward(state, config)[0]) == pytest.approx(episode.reward, abs=1e-9)
            compared += 1
            crashed_or_off += bool(ego.crashed) or not ego.on_road
            if episode.done:
                break
        episode.close()
    assert compared > 60 and crashed_or_off > 0


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_episodes_on_cuda_match_cpu():
    """Placement, window draws and 100 steps of 64 environments (float64) on CUDA equal CPU's."""
    commands = 0.5 * torch.sin(torch.arange(100, dtype=torch.float64))[:, None] * torch.tensor([1.0, 0.004], dtype=torch.float64)
    cpu = SimEpisodes(CRUISE, list(range(64)), dtype=torch.float64)
    cuda = SimEpisodes(CRUISE, list(range(64)), dtype=torch.float64, device="cuda")
    for command in commands:
        cpu.step(command.expand(64, 2).clone())
        cuda.step(command.expand(64, 2).clone().cuda())
    for name, a, b in zip(cpu.state._fields, cuda.state, cpu.state):
        assert a.device.type == "cuda", name
        torch.testing.assert_close(a.cpu(), b, rtol=0, atol=1e-6, msg=name)


def test_the_gpu_benchmark_runs_all_its_sections_on_the_cpu(tmp_path, capsys, monkeypatch):
    """scripts/bench_gpu.py --all with --device cpu at small sizes: the -m gpu tests (skipped here),
    every section eager (compiling takes minutes here), one JSON; without CUDA the default device
    is refused."""
    import bench_gpu
    from torch._inductor.runtime.cache_dir_utils import cache_dir

    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", cache_dir())  # --all keeps a cache already named (the suite's)
    argv = ["--all", "--device", "cpu", "--tests", "tests/test_sim.py", "--solver-modes", "eager", "--batches", "4",
            "--repeats", "1", "--sim-modes", "eager", "--sim-envs", "2", "--mpc-modes", "eager,eager-fixed,eager-fixed-verified",
            "--mpc-envs", "2",
            "--steps", "1",
            "--scenarios", "high_speed", "--seeds", "0-1", "--duration", "0.3", "--profile", "--out", str(tmp_path)]
    assert bench_gpu.main(argv) == 0
    report = json.loads((tmp_path / "bench_gpu.json").read_text())
    assert report["device"] == "cpu" and report["args"] == " ".join(argv)
    rows = report["rows"]
    assert [row["table"] for row in rows] == ["tests", "solver", "sim", "mpc", "mpc", "mpc", "evaluate"]
    tests = rows[0]
    assert tests["returncode"] == 0 and tests["failed"] == tests["error"] == 0 and tests["skipped"] >= 1
    assert rows[1]["batch"] == 4 and rows[1]["eager_ms"] > 0 and "compiled_ms" not in rows[1]
    sim_row, mpc_row = rows[2], rows[3]
    assert (sim_row["mode"], sim_row["num_envs"], mpc_row["num_envs"]) == ("eager", 2, 2)
    assert sim_row["env_steps_per_s"] > 0 and mpc_row["env_steps_per_s"] > 0
    assert sim_row["ops_per_step"] > 100 and sim_row["host_reads_per_step"] == 0 and sim_row["graph_breaks"] == 0
    assert mpc_row["ops_per_step"] > 100 and mpc_row["host_reads_per_step"] >= 1  # the checked decision
    fixed_row = rows[4]
    assert (fixed_row["fixed_shapes"], mpc_row["fixed_shapes"]) == (True, False) and fixed_row["env_steps_per_s"] > 0
    # The loop body (the world's observation and apply too) still reads; the decision itself no more.
    assert fixed_row["host_reads_per_step"] < mpc_row["host_reads_per_step"]
    expert_row = rows[5]  # behind the check at fixed shapes: the check reads nothing more
    assert (expert_row["fixed_shapes"], expert_row["verified"], fixed_row["verified"]) == (True, True, False)
    assert expert_row["host_reads_per_step"] == fixed_row["host_reads_per_step"]
    assert expert_row["ops_per_step"] > fixed_row["ops_per_step"]
    (evaluation,) = [r for r in rows if r["table"] == "evaluate"]
    assert evaluation["episodes"] == 2 and evaluation["errors"] == 0 and evaluation["collisions"] == 0
    assert evaluation["mean_speed"] > 0 and evaluation["wall_s"] > 0
    assert "evaluate high_speed: 2 episodes" in capsys.readouterr().out
    if not torch.cuda.is_available():
        assert bench_gpu.main(["--out", str(tmp_path)]) == 2
    with pytest.raises(SystemExit):
        bench_gpu.main(["--device", "cpu", "--sections", "solver,gpu", "--out", str(tmp_path)])


def test_the_gpu_benchmark_counts_the_graph_breaks_of_the_decisions(tmp_path):
    import bench_gpu

    argv = ["--device", "cpu", "--sections", "decision", "--scenarios", "cruise", "--mpc-envs", "2", "--out", str(tmp_path)]
    assert bench_gpu.main(argv) == 0
    expert, fixed = json.loads((tmp_path / "bench_gpu.json").read_text())["rows"]
    assert (expert["table"], expert["driver"], expert["num_envs"]) == ("decision", "verified:mpc", 2)
    assert expert["graph_breaks"] == expert["graphs"] - 1 >= 1  # the check as shipped runs on the host
    assert 1 <= sum(expert["break_sites"].values()) <= expert["graph_breaks"]  # dynamo keeps the reasons of most
    assert any(site.startswith("verifier.py:") for site in expert["break_sites"])
    assert fixed["driver"] == "verified:mpc:fixed"
    assert (fixed["graphs"], fixed["graph_breaks"], fixed["break_sites"]) == (1, 0, {})


def test_the_gpu_benchmark_skips_the_rows_past_its_budget(tmp_path, capsys):
    import bench_gpu

    assert bench_gpu.main(["--device", "cpu", "--sections", "sim,evaluate", "--sim-modes", "eager", "--sim-envs", "2",
                           "--scenarios", "high_speed", "--budget", "0", "--out", str(tmp_path)]) == 0
    assert json.loads((tmp_path / "bench_gpu.json").read_text())["rows"] == []
    logged = capsys.readouterr().out
    assert "sim eager E=2: skipped (the --budget is spent)" in logged and "evaluate high_speed: skipped" in logged


def test_the_goal_usage_script_counts_every_labelled_goal(tmp_path, capsys):
    import goal_usage

    argv = ["--scenario", "high_speed", "--seeds", "0-1", "--duration", "0.5", "--out", str(tmp_path)]
    assert goal_usage.main(argv) == 0
    report = json.loads((tmp_path / "goal_usage_high_speed.json").read_text())
    labels = [goal["label"] for goal in report["goals"]]
    assert len(labels) == 35 and labels[0] == "base 0" and labels[11] == "near-lane slot 0 at 4 m/s"
    assert labels[-3:] == ["stop slot 0", "stop slot 1", "stop slot 2"]
    assert report["steps"] == 10 and report["episodes"] == 2
    assert sum(goal["chosen"] for goal in report["goals"]) == report["steps"] - report["fallback_steps"]
    assert all(0.0 <= goal["feasible_share"] <= 1.0 and goal["only_feasible"] >= 0 for goal in report["goals"])
    assert "| 11 | near-lane slot 0 at 4 m/s |" in capsys.readouterr().out


def test_the_offline_warm_start_study_reports_every_variant(tmp_path):
    import warm_start_offline

    rows = warm_start_offline.main(["cruise", "0,1", "0.3", str(tmp_path / "warm.json")])
    assert json.loads((tmp_path / "warm.json").read_text()) == rows
    assert {"cold10", "cold50", "warm10_keep_tail", "warm30_zero_tail"} <= set(rows)
    assert rows["cold10"]["steps"] == 3 and rows["warm10_keep_tail"]["steps"] == 2  # no warm start at the first step
    assert all(0.0 <= row["recall"] <= 1.0 and 0.0 <= row["agreement"] <= 1.0 for row in rows.values())
