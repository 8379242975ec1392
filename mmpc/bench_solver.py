"""Solver benchmark: ms per solve vs batch size and obstacle count; table, JSON and plot.

Every timing follows warm-up solves; CUDA timings synchronise before reading the clock. The
numbers are medians and 90th percentiles over ``repeats`` solves.
"""

from __future__ import annotations

import json
import platform
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import torch

from mmpc.config import OptimizerConfig
from mmpc.optimizer import BatchOptimizer
from mmpc.plotting import plot_scaling
from mmpc.problem import ProblemBatch, ego_state, predict_constant_velocity


@dataclass(frozen=True)
class SolverBenchmark:
    """What to measure.

    Attributes:
        batches: batch sizes B (goals of one problem).
        obstacles: obstacle counts M.
        devices: "cpu" and/or "cuda" (cuda rows are skipped without a GPU).
        threads: CPU threads for the CPU rows.
        repeats: timed solves per row.
        warmup: untimed solves per row.
        max_seconds_per_row: stop timing a row early after this long (at least 3 solves).
    """

    batches: tuple[int, ...] = (1, 11, 64, 256, 1024, 4096)
    obstacles: tuple[int, ...] = (6, 10)
    devices: tuple[str, ...] = ("cpu", "cuda")
    threads: int = 1
    repeats: int = 20
    warmup: int = 3
    max_seconds_per_row: float = 20.0
    config: OptimizerConfig = field(default_factory=OptimizerConfig)


def benchmark_problem(batch: int, obstacles: int, times: torch.Tensor) -> ProblemBatch:
    """One highway problem with ``batch`` goals across 6 lanes and ``obstacles`` cars ahead."""
    gen = torch.Generator().manual_seed(batch * 100 + obstacles)
    ego = ego_state(0.0, 8.0, 0.0, 14.0, dtype=times.dtype)
    lateral = torch.linspace(0.0, 20.0, batch, dtype=times.dtype)
    ahead = 100.0 + 40.0 * torch.rand(batch, generator=gen, dtype=times.dtype)
    goals = torch.stack([ahead, lateral], dim=-1)[None]
    x = 15.0 + 100.0 * torch.rand(obstacles, generator=gen, dtype=times.dtype)
    y = 4.0 * torch.randint(0, 6, (obstacles,), generator=gen).to(times.dtype)
    v = 7.0 + 5.0 * torch.rand(obstacles, generator=gen, dtype=times.dtype)
    states = torch.stack([x, y, v, torch.zeros_like(v)], dim=-1)[None]
    return ProblemBatch(ego, goals, predict_constant_velocity(states, times))


def time_solver(solve: Callable[[], object], device: torch.device, repeats: int, warmup: int, budget: float) -> list[float]:
    """Wall times [ms] of ``solve()`` after ``warmup`` calls."""
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    for _ in range(warmup):
        solve()
    sync()
    samples: list[float] = []
    start = time.perf_counter()
    while len(samples) < repeats and (len(samples) < 3 or time.perf_counter() - start < budget):
        t0 = time.perf_counter()
        solve()
        sync()
        samples.append((time.perf_counter() - t0) * 1e3)
    return samples


def run(spec: SolverBenchmark, out: Path, log: Callable[[str], None] = print) -> dict:
    """Measure every row, print a table, write ``out/bench_solver.json`` and ``out/bench_solver.png``."""
    rows = []
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(spec.threads)
    try:
        for device_name in spec.devices:
            if device_name == "cuda" and not torch.cuda.is_available():
                log("cuda: no GPU available, skipped")
                continue
            device = torch.device(device_name)
            optimizer = BatchOptimizer(spec.config, device=device)
            for obstacles in spec.obstacles:
                for batch in spec.batches:
                    problem = benchmark_problem(batch, obstacles, optimizer.times.cpu())
                    problem = ProblemBatch(*(t.to(device) for t in problem[:3]))
                    with torch.inference_mode():
                        samples = time_solver(lambda: optimizer(problem), device, spec.repeats, spec.warmup,
                                              spec.max_seconds_per_row)
                    samples.sort()
                    row = {
                        "device": device_name,
                        "variant": "eager",
                        "threads": spec.threads if device_name == "cpu" else None,
                        "batch": batch,
                        "obstacles": obstacles,
                        "iterations": spec.config.iterations,
                        "ms_median": statistics.median(samples),
                        "ms_p90": samples[min(len(samples) - 1, int(0.9 * len(samples)))],
                        "solves": len(samples),
                    }
                    rows.append(row)
                    log(f"{row['device']:>5} {row['variant']:>8} M={obstacles:<3} B={batch:<6} "
                        f"median {row['ms_median']:9.2f} ms   p90 {row['ms_p90']:9.2f} ms   ({len(samples)} solves)")
    finally:
        torch.set_num_threads(previous_threads)
    device_text = torch.cuda.get_device_name() if torch.cuda.is_available() and "cuda" in spec.devices else platform.processor() or platform.machine()
    report = {
        "device": device_text,
        "torch": torch.__version__,
        "cpu_threads": spec.threads,
        "rows": rows,
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_solver.json").write_text(json.dumps(report, indent=2))
    if rows:
        plot_scaling(out / "bench_solver.png", rows)
    return report
