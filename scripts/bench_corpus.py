"""The batch optimizer on the held-out problem corpus, against IPOPT's labels.

For every scenario of the corpus (``scripts/build_problem_corpus.py``) and every solver setting
(the scenario as shipped, and each ``--variant`` / ``--set`` sweep value), every labelled state
is solved with the MPC's own scoring (:meth:`mmpc.MPC.score`: the optimizer, then the MPC's filters),
one state's goals per call, after an untimed warm-up call (which compiles, when compiling).
Per scenario and setting it reports:

* goals; feasible by ours (``result.feasible`` after the road filter), by IPOPT (the label:
  the baseline's recomputed violation <= its tolerance), both, ours only, IPOPT only, neither,
  and agreement (share of goals with the same verdict);
* among the goals ours calls feasible, the largest constraint violation: obstacle
  ``1 - min normalised ellipse distance``, recomputed here from ``result.trajectories.x/y`` and
  the stored predictions at the optimizer's instants (present slots only), over the horizon and
  at t = 0 alone (the given start: where the ego starts inside an ellipse the MPC accepts a path
  that never goes deeper, :meth:`mmpc.MPC.score`; IPOPT constrains the knots after the start
  only); acceleration excess ``max_acceleration - a_max`` [m/s^2]; heading excess
  ``max_heading_deviation - band`` [deg]
  (negative values: margin to spare); the optimizer's own tolerances allow up to
  ``obstacle_tolerance`` and ``acceleration_tolerance``;
* the optimizer iterations per goal, mean (fewer than the schedule's with early exit, ``exit_checks``);
* ms per state: the median over states of :attr:`mmpc.Scored.solve_ms` (the optimizer call),
  and, in a second row per setting (batch ``all``), one call over all states of the scenario
  (median of ``--repeats`` calls) divided by their count (its verdicts are counted again from
  that call). The settings are timed side by side (each state solved by every setting in turn).

IPOPT checks its constraints at its 41 knots to 1e-3 (in each constraint's units), ours at the
optimizer's 100 instants to its own tolerances; the two verdicts are each solver's own. Settings
that change the problem itself (horizon, instants, ellipse, bounds, obstacle count, road margin,
lanes) are refused: the labels would not apply.

    python scripts/bench_corpus.py --corpus benchmarks/problem_corpus --set optimizer.iterations=50,100,200 --out runs/bench_corpus
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Sequence

import torch
import yaml

from build_problem_corpus import CorpusError, corpus_path, git_state, load_corpus
from mmpc.cli.arguments import add_compile, apply_compile, compile_at_once, override
from mmpc.config import ConfigError, to_dict
from mmpc.mpc import MPC, Scored
from mmpc.obstacles.shape import smallest_distance, squared_obstacle_distance
from mmpc.problem import ProblemBatch
from mmpc.result import Status
from mmpc.scenario import ScenarioConfig, build_mpc, load_scenario

#: Settings that define the problems (and so IPOPT's labels): a variant may not change them.
PROBLEM_KEYS = ("lanes", "optimizer.horizon", "optimizer.num_steps", "optimizer.ellipse_a", "optimizer.ellipse_b",
                "optimizer.a_max", "optimizer.v_min", "optimizer.v_max", "optimizer.max_heading_deg",
                "mpc.num_obstacles", "mpc.road_margin")
#: Table columns: (JSON key, header).
COLUMNS = (
    ("scenario", "scenario"), ("setting", "setting"), ("batch", "batch"), ("states", "states"), ("goals", "goals"),
    ("ours_feasible", "ours feas."), ("ipopt_feasible", "IPOPT feas."), ("both", "both"), ("ours_only", "ours only"),
    ("ipopt_only", "IPOPT only"), ("neither", "neither"), ("agreement", "agree"),
    ("max_obstacle_violation", "max obst. viol."), ("max_obstacle_violation_at_start", "… at t = 0"), ("max_acceleration_excess", "max acc. excess [m/s²]"),
    ("max_heading_excess_deg", "max heading excess [deg]"), ("iterations_mean", "iter. / goal"), ("ms_per_state", "ms / state"),
)


@dataclass(frozen=True)
class Variant:
    """One solver setting: a name for tables and the scenario overrides (dotted keys)."""

    name: str
    overrides: dict


def variant(text: str) -> Variant:
    """``"iterations=200 lane_weight=5"`` -> a variant; a key without a section is ``optimizer.``'s."""
    pairs = [override(part) for part in text.split()]
    if not pairs:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE pairs separated by spaces; got {text!r}")
    return Variant(text, {(k if "." in k else f"optimizer.{k}"): v for k, v in pairs})


def sweep(text: str) -> list[Variant]:
    """``"optimizer.iterations=50,100,200"`` -> one variant per value."""
    key, sep, values = text.partition("=")
    if not sep or not key or not values:
        raise argparse.ArgumentTypeError(f"expected KEY=V1,V2,... such as optimizer.iterations=50,100,200; got {text!r}")
    short = key.removeprefix("optimizer.")
    return [variant(f"{short}={value}") for value in values.split(",") if value]


def checked_scenario(corpus: dict, setting: Variant) -> ScenarioConfig:
    """The corpus's scenario with the setting's overrides, refused if it changes the problems.

    Raises:
        CorpusError: a setting of :data:`PROBLEM_KEYS` differs from the corpus's.
    """
    name = corpus["recording"]["scenario"]
    scenario = load_scenario(name, setting.overrides)
    now, then = to_dict(scenario, complete=True), corpus["scenario_config"]
    for dotted in PROBLEM_KEYS:
        a, b = now, then
        for part in dotted.split("."):
            a, b = a[part], b[part]
        if a != b:
            raise CorpusError(f"scenario {name}, setting {setting.name!r}: `{dotted}` is {a!r} but the corpus was built "
                              f"with {b!r}; IPOPT's labels only hold for the corpus's problems")
    return scenario


def problems(corpus: dict, states: Sequence[int], dtype: torch.dtype) -> ProblemBatch:
    """The stored :class:`mmpc.ProblemBatch` rows ``states``."""
    index = torch.as_tensor(list(states), dtype=torch.long)
    return ProblemBatch(corpus["ego"][index].to(dtype), corpus["goals"][index].to(dtype),
                        corpus["obstacles"][index].to(dtype), corpus["obstacle_mask"][index])


def obstacle_distance(scored: Scored, problem: ProblemBatch, ellipse: tuple[float, float]) -> torch.Tensor:
    """(E, G, N) smallest normalised ellipse distance of each returned trajectory to the present
    predicted obstacles at every instant (+inf without any), recomputed from ``x``, ``y`` and
    ``problem.obstacles``."""
    trajectories = scored.result.trajectories
    trajectories = trajectories._replace(x=trajectories.x.to(torch.float64), y=trajectories.y.to(torch.float64))
    squared = squared_obstacle_distance(trajectories, problem.obstacles.to(torch.float64), ellipse)  # (E, G, M, N)
    return smallest_distance(squared, problem.obstacle_mask[:, None, :, None], 2)


def verdicts(scored: Scored, problem: ProblemBatch, scenario: ScenarioConfig) -> dict[str, torch.Tensor]:
    """(E, G) ours-feasible, the three constraint margins, the reported obstacle distance, the
    status bits and the iterations of every candidate."""
    opt = scenario.optimizer
    result = scored.result
    distance = obstacle_distance(scored, problem, opt.ellipse)  # (E, G, N)
    return {
        "ours": result.feasible,
        "obstacle": 1.0 - distance.amin(dim=-1),
        "obstacle_start": 1.0 - distance[..., 0],
        "acceleration": result.max_acceleration.to(torch.float64) - opt.a_max,
        "heading_deg": torch.rad2deg(result.max_heading_deviation.to(torch.float64)) - opt.max_heading_deg,
        "reported_distance": result.min_obstacle_distance.to(torch.float64),
        "status": result.status,
        "iterations": result.iterations,
    }


def tally(ours: torch.Tensor, ipopt: torch.Tensor, margins: dict[str, torch.Tensor]) -> dict[str, Any]:
    """Counts, agreement, the largest margins among ours-feasible goals (``None`` without any) and
    why ours refused the goals only IPOPT solved (goals per :class:`mmpc.Status` bit)."""
    ours, ipopt = ours.flatten(), ipopt.flatten()
    counts = {
        "goals": int(ours.numel()), "ours_feasible": int(ours.sum()), "ipopt_feasible": int(ipopt.sum()),
        "both": int((ours & ipopt).sum()), "ours_only": int((ours & ~ipopt).sum()),
        "ipopt_only": int((~ours & ipopt).sum()), "neither": int((~ours & ~ipopt).sum()),
    }
    counts["agreement"] = (counts["both"] + counts["neither"]) / max(counts["goals"], 1)
    counts["iterations_mean"] = float(margins["iterations"].double().mean())  # per goal: fewer with early exit

    def largest(name: str) -> Optional[float]:
        values = margins[name].flatten()[ours]
        return float(values.max()) if values.numel() else None

    counts["max_obstacle_violation"] = largest("obstacle")
    counts["max_obstacle_violation_at_start"] = largest("obstacle_start")
    counts["max_acceleration_excess"] = largest("acceleration")
    counts["max_heading_excess_deg"] = largest("heading_deg")
    counts["max_obstacle_violation_ours_only"] = (float(margins["obstacle"].flatten()[ours & ~ipopt].max())
                                                  if bool((ours & ~ipopt).any()) else None)
    missed = margins["status"].flatten()[~ours & ipopt]
    counts["ipopt_only_status_bits"] = {flag.name: int(((missed & int(flag)) != 0).sum()) for flag in Status
                                        if flag and bool(((missed & int(flag)) != 0).any())}
    return counts


def distance_mismatch(margins: dict[str, torch.Tensor]) -> float:
    """Largest |recomputed - reported| smallest obstacle distance over finite values."""
    recomputed, reported = 1.0 - margins["obstacle"], margins["reported_distance"]
    finite = torch.isfinite(recomputed) & torch.isfinite(reported)
    return float((recomputed - reported)[finite].abs().max()) if bool(finite.any()) else 0.0


def run_scenario(corpus: dict, settings: Sequence[Variant], compile: str, all_batch: bool, limit: Optional[int],
                 repeats: int) -> list[dict]:
    """The rows of one scenario: per setting, batch ``state`` and (with ``all_batch``) ``all``.

    The settings are timed side by side, after a warm-up call of each layout: every state is
    solved by each setting in turn, and the all-states call of each setting ``repeats`` times in
    turn (median), so that a change of machine load hits them alike.
    """
    states = corpus["labelled"].nonzero().flatten().tolist()[:limit]
    if not states:
        raise CorpusError(f"scenario {corpus['recording']['scenario']}: no labelled state; label the corpus first")
    ipopt = corpus["ipopt_feasible"][states]
    solvers: list[tuple[Variant, ScenarioConfig, MPC]] = []
    for setting in settings:
        scenario = checked_scenario(corpus, setting)
        mpc = build_mpc(scenario, compile={"auto": "auto", "on": True, "off": False}[compile])
        mpc.score(problems(corpus, states[:1], mpc.optimizer.dtype))  # warm-up (compiles the one-state layout)
        solvers.append((setting, scenario, mpc))
    parts: list[list[dict]] = [[] for _ in solvers]
    times: list[list[float]] = [[] for _ in solvers]
    for s in states:
        for i, (_, scenario, mpc) in enumerate(solvers):
            problem = problems(corpus, [s], mpc.optimizer.dtype)
            scored = mpc.score(problem)
            times[i].append(scored.solve_ms)
            parts[i].append(verdicts(scored, problem, scenario))
    rows: list[list[dict]] = []
    for i, (setting, _, mpc) in enumerate(solvers):
        margins = {key: torch.cat([p[key] for p in parts[i]]) for key in parts[i][0]}
        parts[i] = margins
        base = {"scenario": corpus["recording"]["scenario"], "setting": setting.name, "overrides": setting.overrides,
                "states": len(states), "compiled": bool(mpc.optimizer.compiled)}
        ordered = sorted(times[i])
        rows.append([{**base, "batch": "state", **tally(margins["ours"], ipopt, margins),
                      "ms_per_state": statistics.median(ordered), "ms_per_state_p90": ordered[int(0.9 * (len(ordered) - 1))],
                      "ms_per_state_mean": statistics.fmean(ordered), "distance_mismatch": distance_mismatch(margins)}])
    if all_batch:
        batches = [problems(corpus, states, mpc.optimizer.dtype) for _, _, mpc in solvers]
        for (_, _, mpc), problem in zip(solvers, batches):
            mpc.score(problem)  # warm-up (compiles the all-states layout)
        calls: list[list[float]] = [[] for _ in solvers]
        last: list[Optional[Scored]] = [None] * len(solvers)
        for _ in range(repeats):
            for i, (_, _, mpc) in enumerate(solvers):
                last[i] = mpc.score(batches[i])
                calls[i].append(last[i].solve_ms)
        for i, (_, scenario, _) in enumerate(solvers):
            margins = verdicts(last[i], batches[i], scenario)
            rows[i].append({**{k: rows[i][0][k] for k in ("scenario", "setting", "overrides", "states", "compiled")},
                            "batch": "all", **tally(margins["ours"], ipopt, margins),
                            "ms_per_state": statistics.median(calls[i]) / len(states), "ms_calls": calls[i],
                            "distance_mismatch": distance_mismatch(margins),
                            "verdicts_differ_from_state_batch": int((margins["ours"] != parts[i]["ours"]).sum())})
    return [row for group in rows for row in group]


def format_table(rows: list[dict]) -> str:
    """Markdown table of the rows."""
    def cell(value: Any) -> str:
        if value is None:
            return "-"
        if isinstance(value, float):
            return f"{value:.3f}" if abs(value) < 100 else f"{value:.0f}"
        return str(value)

    lines = ["| " + " | ".join(header for _, header in COLUMNS) + " |",
             "|" + "|".join("---" if key in ("scenario", "setting", "batch") else "---:" for key, _ in COLUMNS) + "|"]
    lines += ["| " + " | ".join(cell(row.get(key)) for key, _ in COLUMNS) + " |" for row in rows]
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="bench_corpus.py", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--corpus", type=Path, default=Path("benchmarks/problem_corpus"), help="corpus folder (default: %(default)s)")
    parser.add_argument("--scenarios", default=None, help="comma-separated (default: every scenario of the manifest)")
    parser.add_argument("--variant", type=variant, action="append", default=[], metavar="'KEY=VALUE ...'",
                        help="a setting as one row: space-separated overrides, a key without a section is the "
                             "optimizer's (e.g. --variant iterations=200 --variant lane_weight=5); repeatable")
    parser.add_argument("--set", type=sweep, action="append", default=[], metavar="KEY=V1,V2,...",
                        help="one row per value, e.g. --set optimizer.iterations=50,100,200; repeatable")
    parser.add_argument("--no-shipped", action="store_true", help="leave out the row of the scenario as shipped")
    parser.add_argument("--no-all-batch", action="store_true", help="leave out the rows of all states in one call")
    parser.add_argument("--states", type=int, default=None, help="only the first N labelled states per scenario")
    parser.add_argument("--repeats", type=int, default=3, help="timed all-states calls per setting (default: %(default)s)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default: %(default)s)")
    add_compile(parser)
    parser.add_argument("--out", type=Path, default=Path("runs/bench_corpus"), help="writes OUT/bench_corpus.json")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    apply_compile(args.compile)
    compile_at_once()  # auto: at the first call, so that the warm-up compiles
    settings = ([] if args.no_shipped else [Variant("shipped", {})]) + args.variant + [v for values in args.set for v in values]
    if not settings:
        parser.error("no setting to run: drop --no-shipped or give --variant / --set")
    if args.states is not None and args.states < 1:
        parser.error(f"--states must be >= 1; got {args.states}")
    if args.repeats < 1:
        parser.error(f"--repeats must be >= 1; got {args.repeats}")
    try:
        manifest_path = args.corpus / "manifest.json"
        if not manifest_path.is_file():
            raise CorpusError(f"no {manifest_path}: build the corpus with scripts/build_problem_corpus.py")
        manifest = json.loads(manifest_path.read_text())
        names = args.scenarios.split(",") if args.scenarios else list(manifest["scenarios"])
        corpora = {name: load_corpus(corpus_path(args.corpus, name)) for name in names}
        rows = []
        for name, corpus in corpora.items():
            new = run_scenario(corpus, settings, args.compile, not args.no_all_batch, args.states, args.repeats)
            rows += new
            for row in new:
                print(f"{name} {row['setting']} ({row['batch']}): {row['ms_per_state']:.1f} ms / state, "
                      f"agreement {row['agreement']:.3f}", file=sys.stderr, flush=True)
    except (CorpusError, ConfigError, FileNotFoundError, yaml.YAMLError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    table = format_table(rows)
    print(table)
    report = {
        "machine": {"platform": platform.platform(), "torch": torch.__version__, "threads": args.threads,
                    "compile": args.compile},
        "code": git_state(),
        "corpus": {"folder": str(args.corpus),
                   "files": {name: {key: manifest["scenarios"].get(name, {}).get(key) for key in ("sha256", "recorded_at")}
                             for name in corpora}},
        "argv": list(sys.argv[1:] if argv is None else argv),
        "rows": rows,
        "table": table,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_corpus.json").write_text(json.dumps(report, indent=1) + "\n")
    print(f"wrote {args.out / 'bench_corpus.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
