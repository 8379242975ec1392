"""Ours against the baselines on the same episodes, the paper's tables and figures.

Every method (a driver spec, :func:`mmpc.drivers.make_driver`) drives every (scenario, seed)
episode of the same duration, one episode at a time (E = 1, so a step's time is one MPC step's).
Ours runs the paper's schedule (:data:`mmpc.scenario.PAPER_SCHEDULE`: every step cold, all 100
iterations), not the shipped scenarios' warm starts and early exit.
Per (method, scenario) the per-step values of all its episodes are summarised as mean / min / max:
the scenario's meta-cost term at the driven state, |linear acceleration|, |angular acceleration|
(the change of heading rate per control period), speed, distance to the right lane and the
driver's computation time per step; plus collisions and fallback steps. Outputs in ``out``:

* ``results.json``: ``entries`` (one per (method, scenario) with ``meta_cost_mean``,
  ``collisions``, ``solve_ms_mean``, ``solve_ms_max`` and the rest), ``episodes`` (every
  episode's metrics), ``scaling`` and ``residuals`` (the figures' data), the run's settings.
  It is rewritten after every (method, scenario), so an interrupted run keeps what it finished.
* ``tables.md``: one table per scenario.
* ``scaling.png``: ms per MPC step vs batch size, ours (one batched optimizer call) against the
  batch NLP (one IPOPT solve per goal on the worker pool), same problems.
* ``residuals.png``: residuals vs iteration of the best trajectory of one MPC cycle.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import platform
import sys
import statistics
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Optional, Sequence

from mmpc.cli.arguments import compile_at_once, seed_list
from mmpc.config import require_int, require_positive
from mmpc.scenario import PAPER_SCHEDULE, SIMULATORS

logger = logging.getLogger(__name__)

#: The methods of the paper's comparison, ours first.
DEFAULT_METHODS = ("mpc", "standard-mpc", "batch-nlp:6", "batch-nlp:11", "frenet")
#: Per-step quantities summarised as mean / min / max: (key, table header, format).
COLUMNS = (
    ("meta_cost", "meta cost", "{:.2f}"),
    ("lin_acc", "abs(a) [m/s²]", "{:.2f}"),
    ("ang_acc", "abs(ψ̈) [rad/s²]", "{:.3f}"),
    ("speed", "v [m/s]", "{:.2f}"),
    ("right_lane_distance", "right-lane dist. [m]", "{:.2f}"),
    ("solve_ms", "time per step [ms]", "{:.1f}"),
)


@dataclass(frozen=True)
class BenchSpec:
    """What ``mmpc bench`` runs.

    Attributes:
        scenarios: scenario names or YAML paths.
        seeds: episode seeds, the same for every method and scenario.
        methods: driver specs (``mpc`` is ours).
        duration: episode length, the same for every method [s] (the scenarios' own 40 s would
            make the batch NLP's share of the run hours long on a small machine).
        scaling_batches: batch sizes of ours in the scaling figure.
        scaling_nlp_batches: batch sizes of the batch NLP in the scaling figure.
        scaling_repeats: timed calls per point of the scaling figure.
        nlp_workers: worker processes of the batch NLP in the scaling figure.
        threads: torch threads.
        sim: the world the episodes run in (``highway-env``, the reference, or ``batched``).
    """

    scenarios: tuple[str, ...] = ("cruise", "high_speed")
    seeds: tuple[int, ...] = tuple(range(10))
    methods: tuple[str, ...] = DEFAULT_METHODS
    duration: float = 15.0
    scaling_batches: tuple[int, ...] = (1, 6, 11, 26, 64, 256)
    scaling_nlp_batches: tuple[int, ...] = (1, 6, 11)
    scaling_repeats: int = 5
    nlp_workers: int = 2
    threads: int = 1
    sim: str = "highway-env"

    def __post_init__(self) -> None:
        if not self.scenarios or not all(isinstance(s, str) and s for s in self.scenarios):
            raise ValueError(f"`scenarios` must be non-empty names; got {self.scenarios!r}")
        if not self.seeds or len(set(self.seeds)) != len(self.seeds) or min(self.seeds) < 0:
            raise ValueError(f"`seeds` must be distinct ints >= 0, at least one; got {self.seeds!r}")
        if not self.methods or len(set(self.methods)) != len(self.methods):
            raise ValueError(f"`methods` must be distinct driver specs, at least one; got {self.methods!r}")
        require_positive("", duration=self.duration)
        for name in ("scaling_batches", "scaling_nlp_batches"):
            if any(not isinstance(b, int) or b < 1 for b in getattr(self, name)):
                raise ValueError(f"`{name}` must hold ints >= 1; got {getattr(self, name)!r}")
        require_int("", low=1, scaling_repeats=self.scaling_repeats, nlp_workers=self.nlp_workers, threads=self.threads)


QUICK = dict(seeds=(0,), duration=1.0, scaling_batches=(1, 11), scaling_nlp_batches=(1, 6), scaling_repeats=1)


# ------------------------------------------------------------------------------- summaries


def _stats(values: Sequence[float]) -> tuple[float, float, float]:
    finite = [v for v in values if math.isfinite(v)]
    if not finite:
        return float("nan"), float("nan"), float("nan")
    return statistics.fmean(finite), min(finite), max(finite)


def step_values(records, dt: float, right_lane_y: float) -> dict[str, list[float]]:
    """Per-step quantities of one episode's :class:`mmpc.metrics.StepRecord` list."""
    rates = [r.heading_rate for r in records]
    return {
        "meta_cost": [r.meta_cost for r in records],
        "lin_acc": [abs(r.acceleration) for r in records],
        "ang_acc": [abs(b - a) / dt for a, b in zip(rates, rates[1:])],
        "speed": [r.v for r in records],
        "right_lane_distance": [abs(r.y - right_lane_y) for r in records],
        "solve_ms": [r.solve_ms for r in records],
    }


def summarize(method: str, scenario: str, episodes: Sequence[dict], steps: dict[str, list[float]]) -> dict:
    """One (method, scenario) entry: ``KEY_mean / _min / _max`` over every step of its episodes
    for every :data:`COLUMNS` key, plus counts."""
    entry: dict = {
        "method": method,
        "scenario": scenario,
        "episodes": len(episodes),
        "steps": sum(e["steps"] for e in episodes),
        "collisions": sum(e["collisions"] for e in episodes),
        "collision_seeds": [e["seed"] for e in episodes if e["collisions"]],
        "fallback_steps": sum(e["fallback_steps"] for e in episodes),
        "lane_changes_mean": statistics.fmean(e["lane_changes"] for e in episodes),
    }
    for key, _, _ in COLUMNS:
        entry[f"{key}_mean"], entry[f"{key}_min"], entry[f"{key}_max"] = _stats(steps[key])
    return entry


def format_tables(entries: Sequence[dict], spec: BenchSpec) -> str:
    """Markdown: one table per scenario, methods as rows, ``mean [min, max]`` cells."""
    lines = [
        f"Episodes of {spec.duration:g} s, seeds {_seed_text(spec.seeds)}, one episode at a time; every cell is "
        "mean [min, max] over all control steps of the method's episodes (time per step: the driver's whole "
        "decision, CPU, one torch thread).",
        "",
    ]
    for scenario in dict.fromkeys(e["scenario"] for e in entries):
        mine = [e for e in entries if e["scenario"] == scenario]
        lines += [f"### {scenario}", ""]
        header = ["method", *(title for _, title, _ in COLUMNS), "collisions", "fallback steps"]
        lines.append("| " + " | ".join(header) + " |")
        lines.append("|" + "---|" * len(header))
        for e in mine:
            cells = [e["method"]]
            for key, _, fmt in COLUMNS:
                cells.append(f"{fmt.format(e[key + '_mean'])} [{fmt.format(e[key + '_min'])}, {fmt.format(e[key + '_max'])}]")
            cells += [f"{e['collisions']} / {e['episodes']}", str(e["fallback_steps"])]
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def _seed_text(seeds: Sequence[int]) -> str:
    seeds = list(seeds)
    if seeds == list(range(seeds[0], seeds[0] + len(seeds))) and len(seeds) > 2:
        return f"{seeds[0]}-{seeds[-1]}"
    return ",".join(map(str, seeds))


# ------------------------------------------------------------------------------- the run


def run_bench(spec: BenchSpec, out: Path, log: Callable[[str], None] = print,
              on_episode: Optional[Callable[[dict], None]] = None) -> dict:
    """Run every method on every episode, then the two figures; write ``results.json``,
    ``tables.md``, ``scaling.png`` and ``residuals.png`` into ``out``. Returns the report."""
    import torch

    from mmpc.highway.runner import run_episode
    from mmpc.drivers import make_driver
    from mmpc.scenario import load_scenario

    torch.set_num_threads(spec.threads)
    out.mkdir(parents=True, exist_ok=True)
    scenarios = [load_scenario(name, {"sim": spec.sim, **PAPER_SCHEDULE}).replace(duration=spec.duration)
                 for name in spec.scenarios]
    report: dict = {
        "spec": asdict(spec),
        "machine": {"processor": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
                    "load_average_start": _load()},
        "entries": [],
        "episodes": [],
    }
    load = report["machine"]["load_average_start"]
    if load is not None and load > (os.cpu_count() or 1):
        logger.warning("load average %.1f exceeds the %s CPUs: timings include waiting for the CPU; compare them "
                       "only within this run", load, os.cpu_count())
    for scenario in scenarios:
        for method in spec.methods:
            driver = make_driver(method, scenario)
            steps: dict[str, list[float]] = {key: [] for key, _, _ in COLUMNS}
            episodes = []
            try:
                for seed in spec.seeds:
                    start = time.perf_counter()
                    result = run_episode(scenario, seed, driver=driver)
                    values = step_values(result.records, 1.0 / scenario.frequency, scenario.road.right_lane_y)
                    for key in steps:
                        steps[key].extend(values[key])
                    row = {"method": method, **result.metrics, "wall_s": time.perf_counter() - start}
                    episodes.append(row)
                    if on_episode is not None:
                        on_episode(row)
            finally:
                close = getattr(driver, "close", None)
                if close is not None:
                    close()
            entry = summarize(method, scenario.name, episodes, steps)
            report["entries"].append(entry)
            report["episodes"].extend(episodes)
            log(f"{scenario.name:<12} {method:<14} meta cost {entry['meta_cost_mean']:8.2f}  collisions "
                f"{entry['collisions']}/{entry['episodes']}  {entry['solve_ms_mean']:8.1f} ms/step "
                f"(max {entry['solve_ms_max']:.1f})")
            _write(report, spec, out)
    report["residuals"] = residual_history(scenarios[0], spec.seeds[0], out / "residuals.png")
    report["scaling"] = batch_scaling(scenarios[0], spec, out / "scaling.png", log)
    report["machine"]["load_average_end"] = _load()
    _write(report, spec, out)
    return report


def _load() -> Optional[float]:
    try:
        return os.getloadavg()[0]
    except OSError:  # pragma: no cover - platform without it
        return None


def _write(report: dict, spec: BenchSpec, out: Path) -> None:
    (out / "results.json").write_text(json.dumps(report, indent=2, default=_json_default) + "\n")
    (out / "tables.md").write_text(format_tables(report["entries"], spec))


def _json_default(value):
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


# ------------------------------------------------------------------------------- figures


def residual_history(scenario, seed: int, path: Path, cycles: int = 30) -> dict:
    """Residuals vs iteration of the best trajectory of one MPC cycle.

    Ours drives the episode for up to ``cycles`` steps; the cycle whose chosen (feasible)
    trajectory passes closest to an obstacle ellipse is solved again with the iteration history
    (the first cycle often has no obstacle near the chosen path, and its obstacle residual is 0
    throughout).
    """
    import torch

    from mmpc.highway import HighwayEpisode
    from mmpc.scenario import build_mpc

    mpc = build_mpc(scenario)
    episode = HighwayEpisode(scenario, seed)
    chosen = None
    try:
        for cycle in range(cycles):
            if episode.done:
                break
            observation = episode.observe()
            plan = mpc.plan(observation.ego, observation.vehicles)
            best = int(plan.selection.index[0])
            closest = float(plan.result.min_obstacle_distance[0, best])
            if bool(plan.selection.feasible[0]) and (chosen is None or closest < chosen[0]):
                chosen = (closest, cycle, plan, best)
            episode.apply(float(plan.acceleration[0]), float(plan.steering[0]))
    finally:
        episode.close()
    if chosen is None:
        raise RuntimeError(f"scenario {scenario.name}, seed {seed}: no cycle with a feasible plan in {cycles} cycles")
    closest, cycle, plan, best = chosen
    with torch.no_grad():
        result = mpc.optimizer(plan.problem, history=True)
    history = result.history[:, 0, best].double()  # (I, 3)
    names = ("obstacle", "acceleration", "non-holonomic")
    series = {name: history[:, k].tolist() for k, name in enumerate(names)}
    plot_residual_history(path, series, title=f"{scenario.name}, seed {seed}, cycle {cycle}: best of "
                                              f"{plan.problem.goals.shape[1]} goals (goal {best})")
    return {"scenario": scenario.name, "seed": seed, "cycle": cycle, "goal": best,
            "min_obstacle_distance": closest, "history": series, "figure": str(path)}


def batch_scaling(scenario, spec: BenchSpec, path: Path, log: Callable[[str], None] = print) -> dict:
    """ms per MPC step vs batch size on the same highway problems: ours (one optimizer call) and
    the batch NLP (B IPOPT solves on ``spec.nlp_workers`` processes, cold-started)."""
    import torch

    from mmpc.drivers.batch_nlp import BatchNLPSolver
    from bench_solver import benchmark_problem, time_solver
    from mmpc.scenario import build_mpc

    mpc = build_mpc(scenario)
    optimizer = mpc.optimizer
    rows = []
    for batch in spec.scaling_batches:
        problem = benchmark_problem(batch, mpc.config.num_obstacles, optimizer.times)
        with torch.no_grad():
            samples = time_solver(lambda: optimizer(problem), torch.device("cpu"), spec.scaling_repeats, 1, 30.0)
        rows.append({"method": "ours", "batch": batch, "ms_median": statistics.median(samples), "ms_min": min(samples)})
        log(f"scaling: ours       B={batch:<4} {rows[-1]['ms_median']:9.1f} ms")
    solver = BatchNLPSolver(mpc, spec.nlp_workers)
    try:
        times = torch.as_tensor(solver.times, dtype=torch.float64)
        for batch in spec.scaling_nlp_batches:
            problem = benchmark_problem(batch, mpc.config.num_obstacles, times)
            mask = torch.ones(problem.obstacles.shape[1], dtype=torch.bool).numpy()
            tasks = [(problem.ego[0].numpy(), problem.obstacles[0].numpy(), mask, problem.goals[0, g].numpy())
                     for g in range(batch)]
            samples = []
            feasible = 0
            for _ in range(spec.scaling_repeats):
                start = time.perf_counter()
                results = solver.solve(tasks)
                samples.append((time.perf_counter() - start) * 1e3)
                feasible = sum(r[1] for r in results)
            rows.append({"method": "batch-nlp", "batch": batch, "ms_median": statistics.median(samples),
                         "ms_min": min(samples), "feasible": feasible, "workers": spec.nlp_workers})
            log(f"scaling: batch-nlp  B={batch:<4} {rows[-1]['ms_median']:9.1f} ms ({spec.nlp_workers} processes)")
    finally:
        solver.close()
    plot_batch_scaling(path, rows, workers=spec.nlp_workers)
    return {"rows": rows, "figure": str(path)}


def plot_residual_history(path: Path, series: dict[str, list[float]], title: str = "") -> Path:
    """Semi-log plot of residual norms (one curve per constraint family) vs iteration."""
    import matplotlib.pyplot as plt

    from mmpc.plotting import save_figure

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for name, values in series.items():
        if max(values) <= 0:  # a log axis cannot show it
            ax.plot([], [], label=f"{name} (0 throughout)")
            continue
        ax.semilogy(range(1, len(values) + 1), values, label=name)
    ax.set_xlabel("iteration")
    ax.set_ylabel("residual norm")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    return save_figure(fig, path)


def plot_batch_scaling(path: Path, rows: Sequence[dict], workers: int) -> Path:
    """Log-log plot of ms per MPC step vs batch size for ours and the batch NLP."""
    import matplotlib.pyplot as plt

    from mmpc.plotting import save_figure

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for method, label, marker in (("ours", "ours (one batched optimizer call)", "o"),
                                  ("batch-nlp", f"batch NLP (IPOPT, {workers} processes)", "s")):
        mine = [r for r in rows if r["method"] == method]
        if mine:
            ax.loglog([r["batch"] for r in mine], [r["ms_median"] for r in mine], marker=marker, label=label)
    ax.set_xlabel("batch size (goals)")
    ax.set_ylabel("ms per MPC step (median)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    return save_figure(fig, path)


# ------------------------------------------------------------------------------- CLI


def _bench(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    values: dict = {}
    if args.quick:
        values.update(QUICK)
    if args.scenarios is not None:
        values["scenarios"] = tuple(s for s in args.scenarios.split(",") if s)
    if args.seeds is not None:
        values["seeds"] = seed_list(args.seeds)
    if args.methods is not None:
        values["methods"] = tuple(m for m in args.methods.split(",") if m)
    if args.duration is not None:
        values["duration"] = args.duration
    if args.nlp_workers is not None:
        values["nlp_workers"] = args.nlp_workers
    if args.sim is not None:
        values["sim"] = args.sim
    try:
        spec = BenchSpec(**values)
        from mmpc.scenario import load_scenario

        for name in spec.scenarios:  # fail before anything runs
            load_scenario(name, {"sim": spec.sim, **PAPER_SCHEDULE})
    except (ValueError, FileNotFoundError) as error:
        print(f"bench_closed_loop: error: {error}", file=sys.stderr)
        return 2
    out = Path(args.out)
    total = len(spec.scenarios) * len(spec.methods) * len(spec.seeds)
    with tqdm(total=total, desc="episodes", unit="ep") as bar:
        def progress(row: dict) -> None:
            bar.update(1)
            bar.set_postfix_str(f"{row['method']} {row['scenario']} seed {row['seed']}")

        run_bench(spec, out, log=tqdm.write, on_episode=progress)
    print((out / "tables.md").read_text())
    print(f"wrote {out / 'results.json'}, {out / 'tables.md'}, {out / 'scaling.png'}, {out / 'residuals.png'}")
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    bench = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    bench.add_argument("--scenarios", default=None, help="comma-separated scenarios (default cruise,high_speed)")
    bench.add_argument("--seeds", default=None, help="seeds, e.g. 0-9 (default 0-9; --quick: 0)")
    bench.add_argument("--methods", default=None,
                       help=f"comma-separated driver specs (default {','.join(DEFAULT_METHODS)})")
    bench.add_argument("--duration", type=float, default=None, help="episode length [s] (default 15; --quick: 1)")
    bench.add_argument("--nlp-workers", type=int, default=None, help="batch-NLP processes in the scaling figure (default 2)")
    bench.add_argument("--sim", choices=SIMULATORS, default=None,
                       help="the world: highway-env (default, the reference) or batched (mmpc.sim)")
    bench.add_argument("--quick", action="store_true", help="a small run: one seed, 1 s episodes, small scaling figure")
    bench.add_argument("--out", default="runs/bench", help="output folder (default runs/bench)")
    args = bench.parse_args(argv)
    compile_at_once()
    return _bench(args)


if __name__ == "__main__":
    sys.exit(main())
