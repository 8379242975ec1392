"""The check's compiled parts (the fail-safe rollout, the occupancy sets) give the eager answers."""

import pytest
import torch

import mmpc
from mmpc.sim.config import SimConfig
from mmpc.solver.execution import COMPILE_ENV
from mmpc.verify import Verifier
from mmpc.verify.compiling import CHECK_COMPILE_AFTER_S, CheckCompiling
from mmpc.verify.failsafe import ROLLOUT_CHUNK, Body, FailSafeRollout, rollout

ROAD = mmpc.Road(num_lanes=3)
SIM = SimConfig(simulation_frequency=10.0, policy_frequency=10.0)


def _bodies(shape: tuple[int, ...], dtype: torch.dtype, seed: int = 0) -> tuple[Body, torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)

    def uniform(low: float, high: float) -> torch.Tensor:
        return low + (high - low) * torch.rand(shape, generator=generator, dtype=dtype)

    body = Body(uniform(0.0, 100.0), uniform(-1.0, 9.0), uniform(-0.3, 0.3), uniform(0.0, 30.0))
    lane = torch.randint(0, ROAD.num_lanes, shape, generator=generator)
    return body, lane, uniform(2.0, 5.0)


def test_compiled_rollout_matches_eager(dtype=torch.float32):  # one compile (~50 s cold): float32, the batched world's
    compiled = FailSafeRollout(5.0, ROAD, SIM, CheckCompiling(True))
    assert compiled.compiling.compiled
    frames = 2 * ROLLOUT_CHUNK + 1  # the last chunk's extra frames are dropped
    for shape in [(3, 4, 3), (7,), (2, 5)]:  # one compile serves every batch size (but 1: specialised)
        body, lane, deceleration = _bodies(shape, dtype)
        expected = rollout(body, lane, deceleration, frames, 5.0, ROAD, SIM)
        path = compiled(body, lane, deceleration, frames)
        for field, want in zip(path, expected):
            assert field.shape == (*shape, frames) and field.dtype == dtype
            torch.testing.assert_close(field, want, atol=1e-4 if dtype == torch.float32 else 1e-9, rtol=1e-6)


def test_compiled_check_gives_the_eager_sets_and_verdicts():
    ego = torch.cat([mmpc.ego_state(0.0, y, 0.0, v) for y, v in [(0.0, 25.0), (4.0, 12.0), (6.0, 20.0)]]).float()
    cars = torch.tensor([[[30.0, 0.0, 15.0, 0.0], [20.0, 4.5, 10.0, 0.0]]] * 3)
    mask = torch.ones(3, 2, dtype=torch.bool)
    acceleration = torch.tensor([[-5.0, 0.0, 3.0]] * 3)
    steering = torch.tensor([[0.0, 0.05, -0.05]] * 3)
    eager_check, compiled_check = Verifier(ROAD, SIM, compile=False), Verifier(ROAD, SIM, compile=True)
    eager = eager_check.check(ego, cars, mask, acceleration, steering)
    compiled = compiled_check.check(ego, cars, mask, acceleration, steering)
    assert eager.verified.any() and not eager.verified.all()  # a scene with both answers
    assert torch.equal(compiled.verified, eager.verified) and torch.equal(compiled.lane, eager.lane)
    times = torch.arange(30, dtype=ego.dtype) * 0.1
    for more_cars in (cars, torch.cat([cars, cars + torch.tensor([40.0, 4.0, 5.0, 0.0])], dim=1)):  # any car count
        sets_mask = torch.ones(more_cars.shape[:2], dtype=torch.bool)
        for got, want in zip(compiled_check._occupancy(ego, more_cars, sets_mask, times),
                             eager_check._occupancy(ego, more_cars, sets_mask, times)):
            torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-6)


def test_auto_compiles_after_eager_time(monkeypatch):
    monkeypatch.setenv(COMPILE_ENV, "0")
    assert not CheckCompiling().compiled  # --compile off
    monkeypatch.setenv(COMPILE_ENV, "1")
    assert CheckCompiling().compiled  # --compile on: at the first call
    monkeypatch.delenv(COMPILE_ENV)
    verifier = Verifier(ROAD, SIM)
    deferred = verifier.compiling
    if not deferred.compile:
        pytest.skip("no C++ compiler: 'auto' stays eager")
    assert not deferred.compiled and deferred.compile_after == CHECK_COMPILE_AFTER_S
    ego = mmpc.ego_state(0.0, 4.0, 0.0, 20.0)
    verifier.check(ego, torch.tensor([[[30.0, 4.0, 15.0, 0.0]]]), torch.ones(1, 1, dtype=torch.bool),
                   torch.zeros(1, 1), torch.zeros(1, 1))  # the rollout and the sets count their eager time together
    assert 0 < deferred.eager_seconds < CHECK_COMPILE_AFTER_S and not deferred.compiled
    deferred.eager_seconds = CHECK_COMPILE_AFTER_S  # as after that much eager checking
    assert deferred.compiled and verifier.rollout.compiling is deferred
    with pytest.raises(ValueError, match="compile"):
        CheckCompiling("sometimes")


def test_the_check_benchmark_writes_both_tables(tmp_path, capsys):
    import json

    import bench_check

    out = tmp_path / "check.json"
    argv = ["--envs", "2", "--seeds", "71168-71169", "--duration", "0.6", "--checks", "eager", "--gym-steps", "1",
            "--gym-warmup", "0", "--out", str(out)]
    assert bench_check.main(argv) == 0
    rows = json.loads(out.read_text())["rows"]
    decision = [row for row in rows if row["table"] == "decision"]
    assert [(row["envs"], row["check"], row["driver"]) for row in decision] == [(2, "eager", "verified:mpc")]
    assert decision[0]["checks_per_step"] >= 1 and 0 < decision[0]["check_share"] < 1
    assert decision[0]["check_ms"] < decision[0]["decision_ms"]  # the check is part of the decision's time
    assert [(row["world"], row["verify"], row["replan"]) for row in rows if row["table"] == "gym"] == [
        (world, verify, replan) for world in ("highway-env", "batched")
        for verify, replan in ((True, "frame"), (False, "frame"), (True, "decision"))]
    assert all(0 < row["world_ms_per_step"] < row["step_ms"] for row in rows if row["table"] == "gym")
    assert "share" in capsys.readouterr().out
    assert bench_check.main(["--checks", "fast", "--out", str(out)]) == 2
    assert "--checks takes names" in capsys.readouterr().err
