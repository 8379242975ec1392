"""GPU benchmark, one command: the solver (eager and compiled), the batched simulator alone, the
MPC in the loop (its decision checked or at fixed shapes, alone or behind the check), and the wall
time of a full evaluation per scenario; a table per section and ``bench_gpu.json`` (rewritten after
every section, so a run stopped by its time limit keeps what it measured). ``--sections decision``
(any device) counts the graph breaks of the expert's decision, as shipped and at fixed shapes.

    python scripts/bench_gpu.py --out benchmarks            # on a machine with CUDA
    python scripts/bench_gpu.py --all --profile --out runs/gpu   # a lent GPU: the -m gpu tests too

Every timing synchronises the device before reading the clock. The solver rows use
:func:`bench_solver.benchmark_problem` (one problem with B goals, 10 obstacles); the compiled
column includes nothing of the first call of each shape (compiling and the CUDA-graph capture),
which ``compile_s`` reports. The evaluation runs ``mmpc.evaluate`` in this process with the
whole seed range in one lockstep group.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, Optional, Sequence

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import CONSTANT_COMMAND, _closed_loop  # noqa: E402
from bench_solver import benchmark_problem, time_solver  # noqa: E402

from mmpc.cli.arguments import compile_at_once, int_list, seed_list  # noqa: E402
from mmpc.device import DEVICE_ENV  # noqa: E402
from mmpc.scenario import ScenarioConfig, build_mpc, load_scenario  # noqa: E402
from mmpc.solver.optimizer import BatchOptimizer  # noqa: E402

SECTIONS = ("solver", "sim", "mpc", "evaluate")
#: ``--all``: the ``-m gpu`` tests first, then every section.
ALL = ("tests",) + SECTIONS
#: Sections only ``--sections`` names: what needs no GPU (dynamo's tracing of the decision).
EXTRA = ("decision",)
#: Modes of the solver and simulator rows.
MODES = ("compiled", "eager")
#: Modes of the MPC rows: the solver compiled or eager; "-fixed": ``build_mpc(fixed_shapes=True)``;
#: "-verified": behind the check (the expert, ``verified:mpc``; with "-fixed", a fixed-shape check too).
MPC_MODES = tuple(f"{solver}{fixed}{verified}" for verified in ("", "-verified") for solver in ("compiled", "eager")
                  for fixed in ("", "-fixed"))
#: Where ``--all`` keeps inductor's compiled kernels (``TORCHINDUCTOR_CACHE_DIR``), under ``--out``:
#: a second run on the same machine compiles from it in seconds.
COMPILE_CACHE = "inductor_cache"
#: ``--all``'s default budget [s]: a lent GPU's 10-minute call, less the start and the copies back.
ALL_BUDGET_S = 540.0
#: The share of the budget the ``-m gpu`` tests may take at most.
TESTS_SHARE = 0.35


class Budget:
    """A run's time limit: rows not started before it are skipped (and logged), so that a run
    stopped by its caller's limit never loses the JSON of what it measured."""

    def __init__(self, seconds: Optional[float]) -> None:
        self.deadline = None if seconds is None else time.perf_counter() + seconds

    def left(self) -> float:
        """Seconds left (inf without a limit)."""
        return math.inf if self.deadline is None else self.deadline - time.perf_counter()

    def over(self, what: str, log: Callable[[str], None]) -> bool:
        """Whether the budget is spent; if so, ``what`` is logged as skipped."""
        if self.left() > 0:
            return False
        log(f"{what}: skipped (the --budget is spent)")
        return True


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


#: Profiler events that make the host wait for the device (a read of a device value, a blocking copy).
HOST_WAITS = ("cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize")
#: CPU operators that read device values on the host (on a GPU each waits for the device): a value
#: read, a data-dependent size.
HOST_READS = ("aten::_local_scalar_dense", "aten::nonzero")
#: CPU operators that launch no kernel of their own (allocations and views).
NO_KERNEL = frozenset(f"aten::{name}" for name in (
    "empty", "empty_strided", "empty_like", "as_strided", "as_strided_", "view", "_unsafe_view", "reshape", "_reshape_alias",
    "alias", "slice", "select", "narrow", "unsqueeze", "squeeze", "expand", "expand_as", "permute", "t", "transpose",
    "detach", "lift_fresh", "resolve_conj", "resolve_neg", "unbind", "chunk", "split", "split_with_sizes", "set_",
    "resize_", "view_as", "unflatten", "flatten", "contiguous", "_to_copy", "to", "result_type", "is_nonzero"))


def kernel_calls(events) -> int:
    """Kernels a CPU run launches, as a GPU would count them: a compiled graph's fused kernels
    (inductor's ``cpp_fused`` calls, profiled with ``cpp.enable_kernel_profile``) and every
    operator that does work and is not called by another operator (allocations and views left out)."""
    count = 0
    for event in events:
        if "cpp_fused" in event.name:
            count += 1
        elif event.name.startswith("aten::") and event.name not in NO_KERNEL:
            parent = event.cpu_parent
            count += parent is None or not parent.name.startswith("aten::")
    return count


def device_profile(run: Callable[[], None], steps: int, device: torch.device) -> dict:
    """Per step of ``run`` (``steps`` steps), under torch's profiler: kernels launched, the
    device's busy time [ms] (the sum of its kernels and copies) and the host's waits for it;
    against the step's wall time these say whether it is bound by launches or by work. On
    the CPU: the kernels a GPU would launch (:func:`kernel_calls`) and the host's reads of
    device values (:data:`HOST_READS`)."""
    from torch.profiler import ProfilerActivity, profile

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    with profile(activities=activities) as profiler:
        run()
        _sync(device)
    events = profiler.key_averages()
    if device.type != "cuda":
        return {"ops_per_step": kernel_calls(profiler.events()) / steps,
                "host_reads_per_step": sum(e.count for e in events if e.key in HOST_READS) / steps}
    on_device = [e for e in events if e.device_type == torch.autograd.DeviceType.CUDA]
    return {"kernels_per_step": sum(e.count for e in on_device) / steps,
            "device_busy_ms_per_step": sum(e.self_device_time_total for e in on_device) / 1e3 / steps,
            "host_waits_per_step": sum(e.count for e in events if e.key in HOST_WAITS) / steps}


def solver_rows(device: torch.device, batches: Sequence[int], obstacles: int, repeats: int, modes: Sequence[str],
                profiled: bool, budget: Budget, log: Callable[[str], None]) -> list[dict]:
    """ms per solve of one problem with B goals: eager and compiled (on CUDA the captured graph's
    replay); ``profiled``: and :func:`device_profile` of one compiled solve."""
    optimizers = {mode: BatchOptimizer(device=device, compile=mode == "compiled") for mode in modes}
    times = next(iter(optimizers.values())).times.cpu()
    rows = []
    for batch in batches:
        if budget.over(f"solver B={batch}", log):
            break
        problem = benchmark_problem(batch, obstacles, times)
        problem = problem._replace(**{name: getattr(problem, name).to(device) for name in ("ego", "goals", "obstacles")})
        row = {"table": "solver", "batch": batch, "obstacles": obstacles}
        for name, optimizer in optimizers.items():
            try:
                start = time.perf_counter()
                optimizer(problem)
                _sync(device)
                row[f"{name}_first_s"] = time.perf_counter() - start
                wall = time_solver(lambda: optimizer(problem), device, repeats, 2, budget=10.0)
                row[f"{name}_ms"] = statistics.median(wall)
            except RuntimeError as error:  # out of memory at the largest B: recorded, the rest goes on
                row[f"{name}_error"] = f"{type(error).__name__}: {str(error)[:200]}"
                if device.type == "cuda":
                    torch.cuda.empty_cache()
        if "eager_ms" in row and "compiled_ms" in row:
            row["speedup"] = row["eager_ms"] / row["compiled_ms"]
        if profiled and "compiled_ms" in row:
            row.update(device_profile(lambda: optimizers["compiled"](problem), 1, device))
        log(f"solver B={batch:>6}: eager {row.get('eager_ms', float('nan')):8.2f} ms, compiled "
            f"{row.get('compiled_ms', float('nan')):8.2f} ms (first call {row.get('compiled_first_s', float('nan')):.1f} s)"
            + _profile_text(row, "solve")
            + "".join(f"  {k}: {v}" for k, v in row.items() if k.endswith("_error")))
        rows.append(row)
    return rows


def sim_rows(device: torch.device, scenario: ScenarioConfig, envs: Sequence[int], steps: int, modes: Sequence[str],
             profiled: bool, budget: Budget, log: Callable[[str], None]) -> list[dict]:
    """The batched simulator alone: env-steps/s of ``SimEpisodes.step`` under a constant command, with
    the GPU's fixed shapes on any device, per mode of ``modes`` ("compiled": one graph per step,
    its first call's compiling in ``first_step_s`` and dynamo's graph breaks counted; "eager");
    ``profiled``: and :func:`device_profile` of 3 more steps."""
    from torch._dynamo.utils import counters

    from mmpc.sim import SimEpisodes

    rows = []
    for mode in modes:
        for num_envs in envs:
            if budget.over(f"sim {mode} E={num_envs}", log):
                return rows
            row = {"table": "sim", "mode": mode, "num_envs": num_envs}
            breaks = sum(counters["graph_break"].values())
            sim = SimEpisodes(scenario.replace(duration=1e4), list(range(num_envs)), device=device,
                              compile=mode == "compiled", fixed_shapes=True)
            command = torch.tensor(CONSTANT_COMMAND, device=device).expand(num_envs, 2).contiguous()
            start = time.perf_counter()
            sim.step(command)
            _sync(device)
            row["first_step_s"] = time.perf_counter() - start
            for _ in range(2):
                sim.step(command)
            _sync(device)
            start = time.perf_counter()
            for _ in range(steps):
                sim.step(command)
            _sync(device)
            seconds = (time.perf_counter() - start) / steps
            row.update(step_ms=seconds * 1e3, env_steps_per_s=num_envs / seconds,
                       graph_breaks=sum(counters["graph_break"].values()) - breaks)
            if profiled:
                row.update(device_profile(lambda: [sim.step(command) for _ in range(3)], 3, device))
            rows.append(row)
            log(f"sim {mode:>8} E={num_envs:>6}: {seconds * 1e3:7.2f} ms per step, {num_envs / seconds:,.0f} env-steps/s "
                f"(first step {row['first_step_s']:.1f} s, {row['graph_breaks']} graph breaks)" + _profile_text(row))
    return rows


def mpc_rows(device: torch.device, scenario: ScenarioConfig, envs: Sequence[int], steps: int, modes: Sequence[str],
             profiled: bool, budget: Budget, log: Callable[[str], None]) -> list[dict]:
    """The MPC in the loop on the batched world, both on ``device`` (the runner's loop body, as
    bench_sim; ``profiled``: and :func:`device_profile` of 3 more steps), per mode of ``modes``
    (:data:`MPC_MODES`: the solver compiled or eager, "-fixed": the MPC's fixed-shape decision,
    "-verified": behind the check)."""
    from mmpc.highway.batched_world import BatchedWorld

    rows = []
    for mode in modes:
        compiled, fixed, verified = mode.startswith("compiled"), "-fixed" in mode, mode.endswith("-verified")
        driver = _mpc_driver(scenario, device, compiled, fixed, verified)
        for num_envs in envs:
            if budget.over(f"mpc {scenario.name} E={num_envs}", log):
                return rows
            row = {"table": "mpc", "scenario": scenario.name, "compiled": compiled, "fixed_shapes": fixed,
                   "verified": verified, "num_envs": num_envs}
            try:
                world = BatchedWorld.start(scenario, list(range(num_envs)), device=device)
                _closed_loop(world, driver, num_envs, 1)  # compiles (and on CUDA captures) this E
                world = BatchedWorld.start(scenario, list(range(num_envs)), device=device)
                step_s, solve_s, iterations = _closed_loop(world, driver, num_envs, steps)
                row.update(step_ms=step_s * 1e3, solve_share=solve_s / step_s, env_steps_per_s=num_envs / step_s,
                           iterations_per_step=iterations)
                if profiled:
                    row.update(device_profile(lambda: _closed_loop(world, driver, num_envs, 2), 3, device))
                log(f"mpc {scenario.name} {mode:>14} E={num_envs:>6}: {step_s * 1e3:8.2f} ms per "
                    f"step, {num_envs / step_s:,.0f} env-steps/s (solve {solve_s / step_s:.0%})" + _profile_text(row))
            except RuntimeError as error:
                row["error"] = f"{type(error).__name__}: {str(error)[:200]}"
                log(f"mpc {scenario.name} E={num_envs}: {row['error']}")
                if device.type == "cuda":
                    torch.cuda.empty_cache()
            rows.append(row)
    return rows


def decision_rows(device: torch.device, scenario: ScenarioConfig, num_envs: int, budget: Budget,
                  log: Callable[[str], None]) -> list[dict]:
    """Each decision traced by dynamo as one function after 2 steps of a batched episode, eager
    (what a graph of it would hold): the expert's as shipped (``verified:mpc``, the MPC behind the
    check) and at fixed shapes (``verified:mpc:fixed``: the MPC's problem building, solve, ranking,
    selection and fallback, the check and the guard). Per driver:
    graphs, graph breaks and the places that break it, most frequent first (``break_sites``:
    "file:line reason" -> count, of the reasons dynamo records: most of the breaks)."""
    from mmpc.highway.batched_world import BatchedWorld

    builders = {
        "verified:mpc": lambda: _mpc_driver(scenario, device, compiled=False, fixed=False, verified=True),
        "verified:mpc:fixed": lambda: _mpc_driver(scenario, device, compiled=False, fixed=True, verified=True),
    }
    rows = []
    for name, build in builders.items():
        if budget.over(f"decision {scenario.name} {name}", log):
            return rows
        driver = build()
        world = BatchedWorld.start(scenario, list(range(num_envs)), device=device)
        _closed_loop(world, driver, num_envs, 1)
        running = [e for e, ended in enumerate(world.done().tolist()) if not ended]
        observation, _ = world.observe(running)
        explained = torch._dynamo.explain(driver.decide)(observation)
        sites: dict[str, int] = {}
        for reason in explained.break_reasons:
            frame = reason.user_stack[-1] if reason.user_stack else None
            where = f"{Path(frame.filename).name}:{frame.lineno}" if frame is not None else "?"
            key = f"{where} {reason.reason.splitlines()[0][:80]}"
            sites[key] = sites.get(key, 0) + 1
        row = {"table": "decision", "scenario": scenario.name, "driver": name, "num_envs": len(running),
               "graphs": explained.graph_count, "graph_breaks": explained.graph_break_count,
               "break_sites": dict(sorted(sites.items(), key=lambda item: -item[1]))}
        log(f"decision {scenario.name} ({name}, E={len(running)}): {row['graphs']} graphs, "
            f"{row['graph_breaks']} graph breaks at {len(sites)} places")
        rows.append(row)
    return rows


def _mpc_driver(scenario: ScenarioConfig, device: torch.device, compiled: bool, fixed: bool, verified: bool):
    """The scenario's MPC driver on ``device``: its solver ``compiled`` or eager, its decision at
    ``fixed`` shapes or checked, behind the check (``verified``; at fixed shapes too with ``fixed``)."""
    from mmpc.drivers.mpc_driver import MPCDriver
    from mmpc.drivers.verified import VerifiedDriver
    from mmpc.verify import Verifier

    driver = MPCDriver(build_mpc(scenario, compile=compiled, device=device, fixed_shapes=fixed), period=scenario.period)
    return VerifiedDriver(driver, Verifier.for_scenario(scenario, compile=compiled, fixed_shapes=fixed)) if verified else driver


def _profile_text(row: dict, unit: str = "step") -> str:
    """The row's :func:`device_profile` figures per ``unit`` (what a row times), or nothing."""
    if "kernels_per_step" in row:
        return (f"; per {unit} {row['kernels_per_step']:,.0f} kernels, device busy {row['device_busy_ms_per_step']:.1f} ms, "
                f"{row['host_waits_per_step']:.0f} host waits")
    if "ops_per_step" in row:
        return f"; per {unit} {row['ops_per_step']:,.0f} kernels (CPU count), {row['host_reads_per_step']:.0f} host reads"
    return ""


def test_rows(device: torch.device, paths: str, timeout: float, log: Callable[[str], None]) -> list[dict]:
    """``pytest -m gpu`` on ``paths`` (space-separated) in a subprocess of at most ``timeout`` seconds:
    passed, failed, skipped and the last lines of its report (on the CPU every test skips)."""
    command = [sys.executable, "-m", "pytest", "-m", "gpu", "-q", "-p", "no:cacheprovider", *paths.split()]
    start = time.perf_counter()
    try:
        done = subprocess.run(command, cwd=Path(__file__).resolve().parent.parent, capture_output=True, text=True,
                              timeout=None if math.isinf(timeout) else max(timeout, 1.0))
    except subprocess.TimeoutExpired as expired:
        output = expired.stdout.decode() if isinstance(expired.stdout, bytes) else (expired.stdout or "")
        done = subprocess.CompletedProcess(command, returncode=124, stdout=output + f"\ntimed out after {timeout:.0f} s")
    counts = {kind: int(number) for number, kind in re.findall(r"(\d+) (passed|failed|skipped|error|deselected)", done.stdout)}
    row = {"table": "tests", "device": str(device), "returncode": done.returncode, "wall_s": time.perf_counter() - start,
           **{kind: counts.get(kind, 0) for kind in ("passed", "failed", "skipped", "error")},
           "report": done.stdout.strip().splitlines()[-5:]}
    log(f"tests -m gpu: {row['passed']} passed, {row['failed']} failed, {row['skipped']} skipped, {row['error']} errors "
        f"in {row['wall_s']:.0f} s (exit {done.returncode})")
    return [row]


def evaluate_rows(scenarios: Sequence[ScenarioConfig], seeds: Sequence[int], out: Path, budget: Budget,
                  log: Callable[[str], None]) -> list[dict]:
    """Wall time of ``mmpc evaluate --sim batched`` on the run's device over ``seeds`` per scenario, one
    lockstep group, and the episodes' summary (collisions, mean speed, meta cost with intervals)."""
    from mmpc.evaluate import EvaluationConfig, evaluate

    lockstep = 1 << (max(seeds) - min(seeds)).bit_length()  # every seed in one group: seed // lockstep
    if len({seed // lockstep for seed in seeds}) > 1:
        lockstep *= 2
    rows = []
    for scenario in scenarios:
        if budget.over(f"evaluate {scenario.name}", log):
            break
        folder = out / f"evaluate_{scenario.name}"
        start = time.perf_counter()
        evaluation = evaluate([scenario], folder, EvaluationConfig(drivers=("mpc",), seeds=tuple(seeds), workers=1,
                                                                    lockstep=lockstep, report=False))
        wall = time.perf_counter() - start
        summary = evaluation.summary[0]
        row = {"table": "evaluate", "scenario": scenario.name, "episodes": summary["episodes"], "wall_s": wall,
               "seeds": f"{min(seeds)}-{max(seeds)}", "duration_s": scenario.duration,
               **{key: summary[key] for key in ("collisions", "collision_seeds", "errors", "collision_rate_ci", "mean_speed",
                                                "mean_speed_ci", "meta_cost_mean", "meta_cost_mean_ci")},
               "fallback_steps": summary.get("fallback_steps"), "fallback_steps_ci": summary.get("fallback_steps_ci")}
        log(f"evaluate {scenario.name}: {summary['episodes']} episodes x {scenario.duration:g} s in {wall:.1f} s; collisions "
            f"{summary['collisions']}, mean speed {summary['mean_speed']:.3f}, meta cost {summary['meta_cost_mean']:.3f}")
        rows.append(row)
    return rows


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="benchmarks", help="folder of bench_gpu.json (default benchmarks)")
    parser.add_argument("--device", default="cuda", help="cuda (default) or cpu (a dry run of the script at small sizes)")
    parser.add_argument("--sections", default=",".join(SECTIONS),
                        help=f"comma-separated, of {', '.join(ALL + EXTRA)} (decision: the expert's graph breaks)")
    parser.add_argument("--all", action="store_true", help="the -m gpu tests and every section, with the compile "
                        f"cache in OUT/{COMPILE_CACHE} (what a lent GPU runs)")
    parser.add_argument("--tests", default="tests", help="the tests section's pytest paths (default: tests)")
    parser.add_argument("--budget", type=float, default=None, help="seconds for the whole run: rows not started "
                        f"by then are skipped (default: none; {ALL_BUDGET_S:.0f} with --all)")
    parser.add_argument("--batches", type=int_list, default=(1, 16, 256, 1024, 4096, 16384, 65536), help="solver B")
    parser.add_argument("--obstacles", type=int, default=10, help="solver rows: obstacles M per goal (the MPC's scenarios use 6)")
    parser.add_argument("--sim-envs", type=int_list, default=(1024, 4096, 16384, 65536), help="simulator E")
    parser.add_argument("--solver-modes", default="eager,compiled", help="solver rows: eager and/or compiled")
    parser.add_argument("--sim-modes", default="compiled,eager", help="simulator rows: compiled and/or eager")
    parser.add_argument("--mpc-envs", type=int_list, default=(256, 1024, 4096, 16384), help="MPC in the loop E")
    parser.add_argument("--mpc-modes", default="compiled",
                        help=f"MPC rows, some of {', '.join(MPC_MODES)} (-fixed: the decision at fixed shapes; "
                             "default compiled, so that --all keeps its time for the evaluation)")
    parser.add_argument("--profile", action="store_true", help="profile the rows: kernels, device busy time "
                        "and host waits per solve / step (on the CPU: kernels a GPU would launch, host reads)")
    parser.add_argument("--steps", type=int, default=20, help="timed steps per simulator / MPC row")
    parser.add_argument("--repeats", type=int, default=20, help="timed solves per solver row")
    parser.add_argument("--scenarios", default="cruise,high_speed", help="scenarios of the MPC and evaluation rows")
    parser.add_argument("--seeds", type=seed_list, default=tuple(range(60000, 61024)), help="evaluation seeds")
    parser.add_argument("--duration", type=float, default=None, help="evaluation episode length [s] (default the scenario's)")
    args = parser.parse_args(argv)
    compile_at_once()
    sections = list(ALL) if args.all else [s for s in args.sections.split(",") if s]
    unknown = sorted(set(sections) - set(ALL + EXTRA))
    if unknown:
        parser.error(f"--sections: unknown {unknown}; expected some of {list(ALL + EXTRA)}")
    modes = {}
    for option, known in (("solver_modes", MODES), ("sim_modes", MODES), ("mpc_modes", MPC_MODES)):
        modes[option] = [m for m in getattr(args, option).split(",") if m]
        if not modes[option] or set(modes[option]) - set(known):
            parser.error(f"--{option.replace('_', '-')}: expected some of {', '.join(known)}; got {getattr(args, option)!r}")
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        print("bench_gpu: no CUDA device; nothing to measure (--device cpu runs the script on the CPU)", file=sys.stderr)
        return 2
    os.environ[DEVICE_ENV] = str(device)
    torch.set_num_threads(1)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.all:
        os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", str((out / COMPILE_CACHE).resolve()))
    if args.profile and device.type == "cpu":
        from torch._inductor import config as inductor

        inductor.cpp.enable_kernel_profile = True  # each fused kernel a profiler event
    scenarios = [load_scenario(name, {"sim": "batched"}) for name in args.scenarios.split(",") if name]
    if args.duration is not None:
        scenarios = [s.replace(duration=args.duration) for s in scenarios]
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    report = {"device": name, "torch": torch.__version__, "args": " ".join(sys.argv[1:] if argv is None else argv), "rows": []}
    path = out / "bench_gpu.json"

    def save(rows: list[dict]) -> None:
        report["rows"].extend(rows)
        path.write_text(json.dumps(report, indent=2) + "\n")

    log = lambda line: print(line, flush=True)  # noqa: E731
    budget = Budget(ALL_BUDGET_S if args.all and args.budget is None else args.budget)
    log(f"{report['device']}, torch {report['torch']}")
    for section in sections:
        start = time.perf_counter()
        if section == "tests":
            save(test_rows(device, args.tests, budget.left() * TESTS_SHARE, log))
        elif section == "solver":
            save(solver_rows(device, args.batches, args.obstacles, args.repeats, modes["solver_modes"], args.profile, budget,
                             log))
        elif section == "sim":
            save(sim_rows(device, scenarios[-1], args.sim_envs, args.steps, modes["sim_modes"], args.profile, budget, log))
        elif section == "mpc":
            for scenario in scenarios:
                save(mpc_rows(device, scenario, args.mpc_envs, args.steps,
                              modes["mpc_modes"], args.profile, budget, log))
        elif section == "decision":
            for scenario in scenarios:
                save(decision_rows(device, scenario, min(args.mpc_envs), budget, log))
        else:
            for scenario in scenarios:
                save(evaluate_rows([scenario], args.seeds, out, budget, log))
        log(f"-- {section}: {time.perf_counter() - start:.0f} s")
    log(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
