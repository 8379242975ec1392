"""Solver benchmark: ms per solve vs batch size and obstacle count; table, JSON and plot.

Every timing follows warm-up solves; CUDA timings synchronise before reading the clock. The
variants (eager, compiled) of one row are timed in turn, one solve of each per round, so that
a change of machine load hits both alike. The numbers are medians and 90th percentiles over
``repeats`` rounds, of wall time and (on the CPU) of the solving thread's CPU time, which a
busy shared machine inflates less; each row records the 1-minute load average.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import statistics
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Optional, Sequence

import torch

from mmpc.cli.arguments import int_list
from mmpc.config import require, require_int, require_positive
from mmpc.obstacles.prediction import predict_constant_velocity
from mmpc.obstacles.shape import covering_semi_axes
from mmpc.plotting import plot_scaling
from mmpc.drivers.mpc_driver import MPCDriver
from mmpc.highway.batched_world import BatchedWorld
from mmpc.problem import ProblemBatch, ego_state
from mmpc.scenario import ScenarioConfig, build_mpc, load_scenario
from mmpc.solver.config import OptimizerConfig
from mmpc.solver.optimizer import BatchOptimizer


@dataclass(frozen=True)
class SolverBenchmark:
    """What to measure.

    Attributes:
        batches: batch sizes B (goals of one problem).
        obstacles: obstacle counts M.
        devices: "cpu" and/or "cuda" (cuda rows are skipped without a GPU).
        variants: "eager" (reference) and/or "compiled" (``BatchOptimizer(compile=True)``); with
            the suffix "-turned" the problem gives every obstacle its own ellipse
            (:attr:`mmpc.ProblemBatch.obstacle_axes` of :func:`turned_axes`), as the expert's
            ``obstacle_shape: heading`` does; with the suffix "-warmK" (e.g. "compiled-warm10") each
            solve starts from the final iterates of a cold solve of the same problem and runs the
            schedule's last K iterations (the solve of a warm-started MPC step); with the suffix
            "-exitA.B..." (e.g. "compiled-exit10") the optimizer has ``exit_checks`` (A, B, ...): early exit.
        threads: CPU threads for the CPU rows.
        repeats: timed solves per row.
        warmup: untimed solves per row.
        max_seconds_per_row: stop timing a row early after this long (at least 3 solves).
        environments: E for the vectorized comparison (E problems x 11 goals in one call vs E
            calls of one problem); 0 skips it.
        in_loop: a scenario whose MPC's solves in its closed loop are compared, per goal-iteration,
            with the benchmark problem of the same B and M (:func:`in_loop_comparison`), for each
            plain variant ("eager", "compiled"); ``None`` skips it.
        in_loop_environments: E of that loop (its batched simulator's episodes).
        in_loop_first_seed: the first of their seeds (then one each, in order).
        in_loop_steps: control steps recorded after :data:`IN_LOOP_WARMUP_STEPS`.
    """

    batches: tuple[int, ...] = (1, 11, 64, 256, 1024, 4096)
    obstacles: tuple[int, ...] = (6, 10)
    devices: tuple[str, ...] = ("cpu", "cuda")
    variants: tuple[str, ...] = ("eager", "compiled")
    threads: int = 1
    repeats: int = 20
    warmup: int = 3
    max_seconds_per_row: float = 20.0
    environments: int = 64
    in_loop: Optional[str] = None
    in_loop_environments: int = 64
    in_loop_first_seed: int = 0
    in_loop_steps: int = 10
    config: OptimizerConfig = field(default_factory=OptimizerConfig)

    def __post_init__(self) -> None:
        require(bool(self.batches) and all(isinstance(b, int) and b >= 1 for b in self.batches),
                f"`batches` must be batch sizes >= 1; got {self.batches!r}")
        require(bool(self.obstacles) and all(isinstance(m, int) and m >= 0 for m in self.obstacles),
                f"`obstacles` must be obstacle counts >= 0; got {self.obstacles!r}")
        require(bool(self.devices) and set(self.devices) <= {"cpu", "cuda"},
                f"`devices` must be 'cpu' and/or 'cuda'; got {self.devices!r}")
        require(bool(self.variants) and len(set(self.variants)) == len(self.variants),
                f"`variants` must be distinct and at least one; got {self.variants!r}")
        for variant in self.variants:
            check_variant(variant)
            replace(self.config, exit_checks=exit_checks(variant))  # checks fit the schedule
        require_int("", low=1, threads=self.threads, repeats=self.repeats)
        require_int("", low=0, warmup=self.warmup, environments=self.environments)
        require_int("", low=1, in_loop_environments=self.in_loop_environments, in_loop_steps=self.in_loop_steps)
        require_int("", low=0, in_loop_first_seed=self.in_loop_first_seed)
        require_positive("", max_seconds_per_row=self.max_seconds_per_row)


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


def turned_axes(obstacles: int, config: OptimizerConfig) -> torch.Tensor:
    """(1, M, 2) per-obstacle semi-axes of cars turned by 0-20 deg (:func:`mmpc.obstacles.shape.covering_semi_axes`)."""
    headings = torch.deg2rad(torch.linspace(0.0, 20.0, obstacles))[None]
    return covering_semi_axes(headings, config.ellipse, config.max_heading_deg)


def bytes_per_solve(batch: int, obstacles: int, config: OptimizerConfig, element_size: int = 4,
                    iterations: Optional[int] = None) -> float:
    """Least memory traffic of one solve of ``iterations`` (default: the schedule's) [bytes]:
    what an ideal implementation must move.

    Per iteration the samples (3N x 2B) are written by one product and read by the
    elementwise steps, whose residual (3N x 2B) is written and read by the next product; the
    heading target and heading (N x B) go the same way; the obstacle predictions (M x N x 2)
    are read once per problem. Coefficient-sized arrays are negligible.
    """
    n = config.num_steps
    per_iteration = 4 * 3 * n * 2 * batch + 4 * n * batch + 2 * obstacles * n
    return float(per_iteration * (iterations or config.iterations) * element_size)


def memory_bandwidth(device: torch.device, megabytes: int = 256) -> float:
    """Measured copy bandwidth [bytes/s] (read + write) with the current thread setting."""
    count = megabytes * 2**20 // 4
    source = torch.ones(count, device=device)
    target = torch.empty_like(source)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    best = float("inf")
    for _ in range(5):
        sync()
        start = time.perf_counter()
        target.copy_(source)
        sync()
        best = min(best, time.perf_counter() - start)
    return 2 * count * 4 / best


def time_solver(solve: Callable[[], object], device: torch.device, repeats: int, warmup: int, budget: float) -> list[float]:
    """Wall times [ms] of ``solve()`` after ``warmup`` calls (:func:`time_interleaved` of one solve)."""
    wall, _ = time_interleaved({"solve": solve}, device, repeats, warmup, budget)["solve"]
    return wall


def time_interleaved(
    solves: dict[str, Callable[[], object]], device: torch.device, repeats: int, warmup: int, budget: float
) -> dict[str, tuple[list[float], list[float]]]:
    """Wall and thread CPU times [ms] of each ``solves[name]()``, called in turn every round.

    Returns:
        name -> (wall times, CPU times of the calling thread), one entry per round; at least 3
        rounds, then up to ``repeats`` while the rounds so far took less than ``budget`` seconds.
    """
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    for solve in solves.values():
        for _ in range(warmup):
            solve()
    sync()
    times: dict[str, tuple[list[float], list[float]]] = {name: ([], []) for name in solves}
    start = time.perf_counter()
    rounds = 0
    while rounds < repeats and (rounds < 3 or time.perf_counter() - start < budget):
        for name, solve in solves.items():
            wall, cpu = time.perf_counter(), time.thread_time()
            solve()
            sync()
            times[name][0].append((time.perf_counter() - wall) * 1e3)
            times[name][1].append((time.thread_time() - cpu) * 1e3)
        rounds += 1
    return times


def run(spec: SolverBenchmark, out: Path, log: Callable[[str], None] = print) -> dict:
    """Measure every row, print a table, write ``out/bench_solver.json`` and ``out/bench_solver.png``.

    Each row: device, variant, batch, obstacles, ms_median, ms_p90, cpu_ms_median (CPU rows),
    solves, load_1min, and ``roofline_fraction`` = (least bytes per solve / median time) /
    measured copy bandwidth; compiled rows also ``speedup_vs_eager`` (wall) and
    ``cpu_speedup_vs_eager``, "-turned" rows ``time_vs_shared_axes``, from the same interleaved rounds.
    """
    rows = []
    bandwidths = {}
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(spec.threads)
    try:
        for device_name in spec.devices:
            if device_name == "cuda" and not torch.cuda.is_available():
                log("cuda: no GPU available, skipped")
                continue
            device = torch.device(device_name)
            bandwidths[device_name] = memory_bandwidth(device)
            log(f"{device_name}: copy bandwidth {bandwidths[device_name] / 1e9:.1f} GB/s")
            optimizers = {
                variant: BatchOptimizer(replace(spec.config, exit_checks=exit_checks(variant)), device=device,
                                        compile=variant.startswith("compiled"))
                for variant in spec.variants
            }
            for obstacles in spec.obstacles:
                for batch in spec.batches:
                    measured = _measure(spec, optimizers, device, batch, obstacles, bandwidths[device_name])
                    for row in measured:
                        cpu = "" if row["cpu_ms_median"] is None else f" (cpu {row['cpu_ms_median']:9.2f})"
                        log(f"{row['device']:>5} {row['variant']:>9} M={obstacles:<3} B={batch:<6} median "
                            f"{row['ms_median']:9.2f} ms{cpu}   p90 {row['ms_p90']:9.2f} ms   roofline "
                            f"{100 * row['roofline_fraction']:5.1f} %   ({row['solves']} solves, load {row['load_1min']:.1f})")
                    rows.extend(measured)
    finally:
        torch.set_num_threads(previous_threads)
    _log_speedups(rows, log)
    vectorized = _vectorized_comparison(spec, log) if spec.environments else None
    in_loop = []
    if spec.in_loop is not None:
        for variant in (v for v in spec.variants if v in ("eager", "compiled")):
            in_loop.append(in_loop_comparison(spec, variant == "compiled", log))
    device_text = torch.cuda.get_device_name() if torch.cuda.is_available() and "cuda" in spec.devices else platform.processor() or platform.machine()
    report = {
        "device": device_text,
        "torch": torch.__version__,
        "cpu_threads": spec.threads,
        "bandwidth_bytes_per_s": bandwidths,
        "rows": rows,
        "vectorized": vectorized,
        "in_loop": in_loop,
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_solver.json").write_text(json.dumps(report, indent=2))
    if rows:
        plot_scaling(out / "bench_solver.png", rows)
    return report


def _measure(spec: SolverBenchmark, optimizers: dict[str, BatchOptimizer], device: torch.device,
             batch: int, obstacles: int, bandwidth: float) -> list[dict]:
    """One row per variant, timed in the same interleaved rounds.

    Compiled code is dropped first (``torch.compiler.reset()``), so that every row compiles for
    its own shape, as a process that solves one batch shape does: otherwise the second shape
    a compiled function sees makes its dims dynamic, and those kernels are 5-15 % slower.
    """
    torch.compiler.reset()
    first = next(iter(optimizers.values()))
    problem = benchmark_problem(batch, obstacles, first.times.cpu())
    problem = ProblemBatch(*(t.to(device) for t in problem[:3]))
    turned = problem._replace(obstacle_axes=turned_axes(obstacles, first.config).to(device))
    mean_iterations = {}  # per variant, over the (problem, goal) elements: fewer than the schedule's with early exit
    with torch.inference_mode():
        solves = {}
        for variant, optimizer in optimizers.items():
            p = turned if "-turned" in variant else problem
            iterations = warm_iterations(variant)
            if iterations is None:
                solves[variant] = lambda optimizer=optimizer, p=p: optimizer(p)
            else:
                warm = optimizer(p).warm
                solves[variant] = lambda optimizer=optimizer, p=p, warm=warm, k=iterations: optimizer(p, warm=warm,
                                                                                                     warm_iterations=k)
            mean_iterations[variant] = float(solves[variant]().iterations.float().mean())
        times = time_interleaved(solves, device, spec.repeats, spec.warmup, spec.max_seconds_per_row)
    load = os.getloadavg()[0]
    rows = []
    for variant, (wall, cpu) in times.items():
        wall = sorted(wall)
        median = statistics.median(wall)
        iterations = mean_iterations[variant]
        least_bytes = bytes_per_solve(batch, obstacles, spec.config, iterations=iterations)
        rows.append({
            "device": device.type,
            "variant": variant,
            "threads": spec.threads if device.type == "cpu" else None,
            "batch": batch,
            "obstacles": obstacles,
            "iterations": iterations,
            "ms_median": median,
            "ms_p90": wall[min(len(wall) - 1, int(0.9 * len(wall)))],
            "cpu_ms_median": statistics.median(cpu) if device.type == "cpu" else None,
            "solves": len(wall),
            "load_1min": load,
            "roofline_fraction": least_bytes / (median * 1e-3) / bandwidth,
        })
    return rows


def _suffix(variant: str, name: str) -> Optional[str]:
    """What follows ``name`` in the variant's suffix that starts with it ("compiled-warm10", "warm" -> "10")."""
    return next((part[len(name):] for part in variant.split("-")[1:] if part.startswith(name)), None)


#: A variant: an optimizer kind, then suffixes, each kind of suffix at most once (:class:`SolverBenchmark`).
VARIANT = re.compile(r"(eager|compiled)(-turned|-warm[^-]*|-exit[^-]*)*")


def check_variant(variant: str) -> None:
    """Refuse a variant the benchmark does not know (``ValueError`` naming the allowed form), so
    that a misspelled one is not timed as eager under its own label."""
    suffixes = [re.match(r"[a-z]*", part).group() for part in variant.split("-")[1:]]
    if not VARIANT.fullmatch(variant) or len(set(suffixes)) != len(suffixes):
        raise ValueError(f"variant {variant!r} is not one the benchmark knows: expected 'eager' or 'compiled', then "
                         "optionally each at most once '-turned', '-warmK' (K >= 1) and '-exitA.B...' "
                         "(e.g. 'compiled-turned-warm10', 'eager-exit10.30')")
    warm_iterations(variant)


def warm_iterations(variant: str) -> Optional[int]:
    """K of a "-warmK" variant (:class:`SolverBenchmark`), else ``None``."""
    iterations = _suffix(variant, "warm")
    if iterations is None:
        return None
    if not iterations.isdigit() or int(iterations) < 1:
        raise ValueError(f"variant {variant!r}: '-warm' must be followed by the iterations, e.g. 'compiled-warm10'")
    return int(iterations)


def exit_checks(variant: str) -> tuple[int, ...]:
    """The early-exit checks of a "-exitA.B..." variant (:class:`SolverBenchmark`), else ``()``."""
    checks = _suffix(variant, "exit")
    if checks is None:
        return ()
    if not all(part.isdigit() for part in checks.split(".")):
        raise ValueError(f"variant {variant!r}: '-exit' must be followed by iterations separated by dots, "
                         f"e.g. 'compiled-exit10.30'")
    return tuple(int(part) for part in checks.split("."))


def _log_speedups(rows: list[dict], log: Callable[[str], None]) -> None:
    """Compiled over eager speed-up and warm over cold time, side by side from the same interleaved rounds."""
    eager = {(r["device"], r["batch"], r["obstacles"]): r for r in rows if r["variant"] == "eager"}
    for row in rows:
        key = (row["device"], row["batch"], row["obstacles"])
        if row["variant"] == "compiled" and key in eager:
            row["speedup_vs_eager"] = eager[key]["ms_median"] / row["ms_median"]
            text = f"{row['speedup_vs_eager']:.2f}x"
            if row["cpu_ms_median"] is not None:
                row["cpu_speedup_vs_eager"] = eager[key]["cpu_ms_median"] / row["cpu_ms_median"]
                text += f" (cpu time {row['cpu_speedup_vs_eager']:.2f}x)"
            log(f"{row['device']:>5} M={row['obstacles']:<3} B={row['batch']:<6} compiled is {text} faster than eager")
    plain = {(r["device"], r["batch"], r["obstacles"], r["variant"]): r for r in rows}
    for row in rows:  # a warm start or early exit against the whole cold schedule, same optimizer kind, same rounds
        cold = plain.get((row["device"], row["batch"], row["obstacles"], row["variant"].split("-")[0]))
        if (warm_iterations(row["variant"]) is not None or exit_checks(row["variant"])) and cold is not None:
            row["time_vs_cold"] = row["ms_median"] / cold["ms_median"]
            log(f"{row['device']:>5} M={row['obstacles']:<3} B={row['batch']:<6} {row['variant']} takes "
                f"{row['time_vs_cold']:.2f}x the time of {cold['variant']}")
    # per-obstacle ellipses against the shared ones, same optimizer kind, same rounds
    for row in rows:
        shared = plain.get((row["device"], row["batch"], row["obstacles"], row["variant"].replace("-turned", "", 1)))
        if "-turned" in row["variant"] and shared is not None:
            row["time_vs_shared_axes"] = row["ms_median"] / shared["ms_median"]
            log(f"{row['device']:>5} M={row['obstacles']:<3} B={row['batch']:<6} {row['variant']} takes "
                f"{row['time_vs_shared_axes']:.2f}x the time of {shared['variant']}")


def _vectorized_comparison(spec: SolverBenchmark, log: Callable[[str], None]) -> dict:
    """E environments' problems (11 goals, 6 obstacles each) in one call vs one call each (CPU, eager)."""
    optimizer = BatchOptimizer(spec.config)
    single = [benchmark_problem(11, 6, optimizer.times) for _ in range(spec.environments)]
    single = [ProblemBatch(p.ego + torch.tensor([[3.0 * e, 0, 0, 0, 0, 0]]), p.goals + 3.0 * e, p.obstacles)
              for e, p in enumerate(single)]
    batched = ProblemBatch(*(torch.cat(parts) for parts in zip(*(p[:3] for p in single))))
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(spec.threads)
    try:
        with torch.inference_mode():
            one_call = time_solver(lambda: optimizer(batched), torch.device("cpu"), max(3, spec.repeats // 4), 1,
                                   spec.max_seconds_per_row)
            per_env = time_solver(lambda: [optimizer(p) for p in single], torch.device("cpu"), 3, 1,
                                  spec.max_seconds_per_row)
    finally:
        torch.set_num_threads(previous_threads)
    result = {
        "environments": spec.environments,
        "goals": 11,
        "obstacles": 6,
        "ms_one_batched_call": statistics.median(one_call),
        "ms_one_call_per_environment": statistics.median(per_env),
    }
    result["speedup"] = result["ms_one_call_per_environment"] / result["ms_one_batched_call"]
    log(f"vectorized: {spec.environments} environments x 11 goals: one call {result['ms_one_batched_call']:.1f} ms, "
        f"one call per environment {result['ms_one_call_per_environment']:.1f} ms ({result['speedup']:.1f}x)")
    return result


#: Control steps of the in-loop comparison's episodes before its solves are recorded: the first
#: steps solve cold and compile the warm and cold rows' layouts.
IN_LOOP_WARMUP_STEPS = 3


def record_loop_solves(scenario: ScenarioConfig, optimizer_compile: bool, environments: int, steps: int,
                       first_seed: int = 0) -> tuple:
    """The optimizer calls of ``scenario``'s MPC driving ``environments`` batched-simulator episodes
    (seeds ``first_seed`` on) for :data:`IN_LOOP_WARMUP_STEPS` + ``steps`` control steps: its optimizer
    and the (problem, keyword arguments) of the calls of the last ``steps`` steps, as the loop made them."""
    mpc = build_mpc(scenario, compile=optimizer_compile)
    driver = MPCDriver(mpc, period=scenario.period)
    world = BatchedWorld.start(scenario, list(range(first_seed, first_seed + environments)))
    calls: list[tuple[ProblemBatch, dict]] = []
    recording = False

    def record(module, args, kwargs):
        if recording:
            problem = args[0] if args else kwargs["problem"]
            rest = {name: _copied(value) for name, value in kwargs.items() if name != "problem"}
            calls.append((_copied(problem), rest))

    hook = mpc.optimizer.register_forward_pre_hook(record, with_kwargs=True)
    try:
        driver.reset(environments)
        for step in range(IN_LOOP_WARMUP_STEPS + steps):
            recording = step >= IN_LOOP_WARMUP_STEPS
            running = [e for e, ended in enumerate(world.done().tolist()) if not ended]
            if not running:
                break
            observation, _ = world.observe(running)
            decision = driver.decide(observation)
            world.apply(running, decision.acceleration, decision.steering)
    finally:
        hook.remove()
        world.close()
    return mpc.optimizer, calls


def _copied(value):
    """A copy of a tensor or of a named tuple of tensors (``None`` fields kept); other values as they are."""
    if isinstance(value, torch.Tensor):
        return value.clone()
    if isinstance(value, tuple) and hasattr(value, "_fields"):
        return type(value)(*(None if field is None else field.clone() for field in value))
    return value


def in_loop_comparison(spec: SolverBenchmark, optimizer_compile: bool, log: Callable[[str], None] = print) -> dict:
    """ns per goal-iteration of the MPC's solves in its closed loop (recorded, then replayed: warm
    starts, the rows that solve cold, tiles and padding as the loop has them) against the solver
    benchmark's problem with the loop's B (problems x goals) and M (each obstacle its own ellipse,
    :func:`turned_axes`, where the loop's problems have theirs), one cold solve of the whole
    schedule, in the same interleaved rounds on the CPU (``spec.threads``). Goal-iterations:
    the iterations each (problem, goal) element ran, summed (a warm start runs the schedule's last few)."""
    scenario = load_scenario(spec.in_loop, {"sim": "batched"})
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(spec.threads)
    try:
        with torch.inference_mode():
            optimizer, calls = record_loop_solves(scenario, optimizer_compile, spec.in_loop_environments,
                                                  spec.in_loop_steps, spec.in_loop_first_seed)
            if not calls:
                raise RuntimeError(f"in-loop comparison: the {spec.in_loop!r} loop made no solve in "
                                   f"{spec.in_loop_steps} steps")
            batch = max(problem.goals.shape[0] * problem.goals.shape[1] for problem, _ in calls)
            obstacles = max(problem.obstacles.shape[1] for problem, _ in calls)
            benchmark = BatchOptimizer(optimizer.config, compile=optimizer_compile)
            problem = benchmark_problem(batch, obstacles, benchmark.times)
            turned = calls[0][0].obstacle_axes is not None
            if turned:
                problem = problem._replace(obstacle_axes=turned_axes(obstacles, optimizer.config))

            def replay() -> int:
                return sum(int(optimizer(p, **kwargs).iterations.sum()) for p, kwargs in calls)

            goal_iterations = {"loop": replay(), "benchmark": int(benchmark(problem).iterations.sum())}
            solves = {"loop": replay, "benchmark": lambda: benchmark(problem)}
            times = time_interleaved(solves, torch.device("cpu"), spec.repeats, spec.warmup, 2 * spec.max_seconds_per_row)
    finally:
        torch.set_num_threads(previous_threads)
    ns = {name: statistics.median(wall) * 1e6 / goal_iterations[name] for name, (wall, _) in times.items()}
    steps = spec.in_loop_steps
    result = {
        "scenario": spec.in_loop,
        "variant": "compiled" if optimizer_compile else "eager",
        "environments": spec.in_loop_environments,
        "first_seed": spec.in_loop_first_seed,
        "steps": steps,
        "batch": batch,
        "obstacles": obstacles,
        "obstacle_axes": "per obstacle" if turned else "shared",
        "solves_per_step": len(calls) / steps,
        "loop_ms_per_step": statistics.median(times["loop"][0]) / steps,
        "loop_iterations_per_goal": goal_iterations["loop"] / (batch * steps),
        "loop_ns_per_goal_iteration": ns["loop"],
        "benchmark_ms": statistics.median(times["benchmark"][0]),
        "benchmark_ns_per_goal_iteration": ns["benchmark"],
        "ratio": ns["loop"] / ns["benchmark"],
        "rounds": len(times["loop"][0]),
    }
    log(f"in loop ({spec.in_loop}, {result['variant']}, E={spec.in_loop_environments}, B={batch}, M={obstacles}): "
        f"{result['loop_ns_per_goal_iteration']:.0f} ns per goal-iteration ({result['loop_iterations_per_goal']:.1f} "
        f"iterations per goal) vs the benchmark's {result['benchmark_ns_per_goal_iteration']:.0f}: "
        f"{result['ratio']:.2f}x ({result['rounds']} rounds)")
    return result


def main(argv: Optional[Sequence[str]] = None) -> int:
    bench = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    bench.add_argument("--batches", type=int_list, default=(1, 11, 64, 256, 1024, 4096), help="comma-separated batch sizes")
    bench.add_argument("--obstacles", type=int_list, default=(6, 10), help="comma-separated obstacle counts")
    bench.add_argument("--devices", default="cpu,cuda", help="cpu and/or cuda (cuda skipped without a GPU)")
    bench.add_argument("--variants", default="eager,compiled",
                       help="eager and/or compiled (torch.compile), each optionally with -turned (per-obstacle ellipses) "
                            "and/or -warmK (K iterations from a cold solve's iterates) or -exitA.B... (early exit checks), "
                            "e.g. compiled,compiled-warm10,compiled-exit10")
    bench.add_argument("--threads", type=int, default=1, help="CPU threads (default 1)")
    bench.add_argument("--repeats", type=int, default=20, help="timed solves per row")
    bench.add_argument("--max-seconds-per-row", type=float, default=20.0, help="time budget per row")
    bench.add_argument("--environments", type=int, default=64,
                       help="E for the one-call-vs-one-call-per-environment comparison (0 skips)")
    bench.add_argument("--in-loop", default=None, metavar="SCENARIO",
                       help="compare the solves of this scenario's MPC in its closed loop with the benchmark problem of "
                            "the same B and M, per goal-iteration (e.g. high_speed)")
    bench.add_argument("--in-loop-environments", type=int, default=64, help="E of the in-loop comparison")
    bench.add_argument("--in-loop-steps", type=int, default=10, help="control steps the in-loop comparison records")
    bench.add_argument("--in-loop-seed", type=int, default=0, help="first seed of the in-loop comparison's episodes")
    bench.add_argument("--out", default="runs/bench_solver", help="output folder")
    args = bench.parse_args(argv)
    try:  # every value checked before any work
        spec = SolverBenchmark(
            batches=args.batches, obstacles=args.obstacles, devices=tuple(args.devices.split(",")),
            variants=tuple(args.variants.split(",")), threads=args.threads, repeats=args.repeats,
            max_seconds_per_row=args.max_seconds_per_row, environments=args.environments, in_loop=args.in_loop,
            in_loop_environments=args.in_loop_environments, in_loop_steps=args.in_loop_steps,
            in_loop_first_seed=args.in_loop_seed,
        )
    except ValueError as error:  # a ConfigError too
        bench.error(str(error))
    report = run(spec, Path(args.out))
    print(f"wrote {Path(args.out) / 'bench_solver.json'} ({len(report['rows'])} rows) and bench_solver.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
