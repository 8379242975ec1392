"""Summaries of an evaluation: per driver x scenario means with 95 % confidence intervals, a
plain-text and a markdown table, a comparison figure and TensorBoard scalars.

Intervals (:mod:`mmpc.evaluate.intervals`): Student's t for a mean over episodes (and for the
mean of paired per-seed differences), Wilson's score interval for the collision rate.
"""

from __future__ import annotations

import math
import os
import shutil
from pathlib import Path
from typing import Optional, Sequence

from mmpc.evaluate.intervals import mean_ci, wilson_ci
from mmpc.evaluate.store import NUMBER_COLUMNS
from mmpc.files import file_slug
from mmpc.metrics import OFF_CENTRE

#: Metrics averaged over episodes, with a confidence interval (``<key>_ci``).
MEAN_METRICS = (
    "mean_speed", "meta_cost_mean", "task_return", "speed_residual_mean", "right_lane_distance_mean", "lin_acc_mean", "ang_acc_mean",
    "lane_changes", "fallback_steps", "plan_cost_mean", "solve_ms_mean", "solve_ms_per_episode_mean",
    "iterations_mean", "off_centre_share", "lane_change_s_mean",
)

#: Rows of the plain-text table: (key, header, format).
TABLE = (
    ("episodes", "episodes", "{:d}"),
    ("errors", "errors", "{:d}"),
    ("collisions", "collisions", "{:d}"),
    ("ego_fault_collisions", "  ego's fault", "{:d}"),
    ("collision_rate", "collision rate", "{:.3f}"),
    ("offroad", "offroad steps", "{:d}"),
    ("mean_speed", "mean v [m/s]", "{:.2f}"),
    ("meta_cost_mean", "meta cost", "{:.3f}"),
    ("task_return", "task return", "{:.1f}"),
    ("speed_residual_mean", "(v-v_c)^2 [m2/s2]", "{:.3f}"),
    ("right_lane_distance_mean", "right-lane dist [m]", "{:.2f}"),
    ("lin_acc_mean", "|a| [m/s2]", "{:.2f}"),
    ("ang_acc_mean", "|psi''| [rad/s2]", "{:.3f}"),
    ("lane_changes", "lane changes", "{:.1f}"),
    ("fallback_steps", "fallback steps", "{:.1f}"),
    ("off_centre_share", "off-centre > 1 m", "{:.3f}"),
    ("lane_change_s_mean", "lane change [s]", "{:.2f}"),
    ("solve_ms_mean", "solve ms mean", "{:.1f}"),
    ("solve_ms_per_episode_mean", "solve ms / episode", "{:.1f}"),
    ("solve_ms_max", "solve ms max", "{:.1f}"),
    ("iterations_mean", "iterations / step", "{:.1f}"),
)

#: Rows of the markdown table and panels of the figure: (key, label).
COMPARED = (
    ("collision_rate", "collision rate"),
    ("mean_speed", "mean speed [m/s]"),
    ("meta_cost_mean", "meta cost (driven, per step)"),
    ("solve_ms_mean", "solve ms per decision"),
    ("solve_ms_per_episode_mean", "solve ms per episode-step"),
)
#: Metrics that are >= 0 by definition (a speed is not: highway-env lets a car reverse).
NON_NEGATIVE = frozenset({"collision_rate", "meta_cost_mean", "solve_ms_mean", "solve_ms_per_episode_mean"})


def _finite(value: Optional[float]) -> Optional[float]:
    return value if value is not None and math.isfinite(value) else None


def summarize(rows: Sequence[dict]) -> list[dict]:
    """One entry per (driver, scenario), in order of first appearance.

    Args:
        rows: episode rows (:data:`mmpc.evaluate.store.COLUMNS`); rows without ``status`` count as
            finished, rows without ``driver`` are grouped under ``driver = None``.

    Returns:
        Entries with ``driver``, ``scenario``, ``episodes`` (finished ones), ``errors`` and
        ``error_seeds``, ``collisions`` and ``collision_seeds``, ``ego_fault_collisions`` and
        ``ego_fault_seeds`` (the ego's front or side struck; rows from before the split count
        as the ego's fault), ``collision_parts`` (seed -> part struck), ``collision_rate`` and
        ``collision_rate_ci`` (Wilson), ``offroad`` (steps, summed), ``solve_ms_max``,
        ``min_clearance`` (smallest), and for each of :data:`MEAN_METRICS` the mean over the
        finished episodes where it is finite and ``<key>_ci`` (t interval, ``None`` for fewer
        than two). Missing values are ``None`` (JSON ``null``).
    """
    summary = []
    for driver, scenario in dict.fromkeys((row.get("driver"), row["scenario"]) for row in rows):
        mine = [row for row in rows if row.get("driver") == driver and row["scenario"] == scenario]
        done = [row for row in mine if row.get("status", "ok") == "ok"]
        collisions = sum(int(row["collisions"]) for row in done)
        crashed = [row for row in done if row["collisions"]]
        ego_fault = [row["seed"] for row in crashed if row.get("ego_fault_collisions") != 0]
        entry: dict = {
            "driver": driver,
            "scenario": scenario,
            "episodes": len(done),
            "errors": len(mine) - len(done),
            "error_seeds": [row["seed"] for row in mine if row.get("status", "ok") != "ok"],
            "collisions": collisions,
            "collision_seeds": [row["seed"] for row in crashed],
            "ego_fault_collisions": len(ego_fault),
            "ego_fault_seeds": ego_fault,
            "collision_parts": {row["seed"]: row.get("collision_part") or "unknown" for row in crashed},
            "collision_rate": collisions / len(done) if done else None,
            "collision_rate_ci": wilson_ci(collisions, len(done)),
            "offroad": sum(int(row["offroad"]) for row in done),
            "solve_ms_max": _finite(max((row["solve_ms_max"] for row in done), default=None)),
            "min_clearance": _finite(min((row["min_clearance"] for row in done if row.get("min_clearance") is not None),
                                         default=None)),
        }
        for key in MEAN_METRICS:
            entry[key], entry[f"{key}_ci"] = mean_ci([row.get(key) for row in done])
        summary.append(entry)
    return summary


#: Metrics :func:`paired_differences` compares by default.
PAIRED_METRICS = ("task_return", "mean_speed", "meta_cost_mean", "fallback_steps", "right_lane_distance_mean", "min_clearance")


def check_paired_metrics(keys: Sequence[str]) -> None:
    """Refuse ``keys`` for :func:`paired_differences` unless they are one or more of the number
    columns of ``episodes.csv`` (:data:`mmpc.evaluate.store.NUMBER_COLUMNS`)."""
    unknown = [key for key in keys if key not in NUMBER_COLUMNS]
    if not keys or unknown:
        raise ValueError(f"the metrics must be one or more of the number columns of episodes.csv "
                         f"({', '.join(NUMBER_COLUMNS)}); got {list(keys)}"
                         + (f", of which {', '.join(map(repr, unknown))} not" if unknown else ""))


def paired_differences(reference: Sequence[dict], rows: Sequence[dict],
                       keys: Sequence[str] = PAIRED_METRICS) -> dict:
    """Per-seed differences ``rows - reference`` over the seeds both finished: one driver on one
    scenario each (the same traffic per seed), e.g. an agent against always-defer.

    Pairing by seed takes the traffic's variance out of the comparison: the interval of the mean
    difference is much narrower than the two means' own intervals.

    Args:
        reference, rows: episode rows (:data:`mmpc.evaluate.store.COLUMNS`) of one driver each;
            seeds must not repeat within either.
        keys: metric columns to compare.

    Returns:
        ``episodes`` (paired seeds), ``unpaired_seeds`` (finished in one only), ``collisions`` and
        ``reference_collisions`` over the paired seeds, and per key ``{"reference", "mean",
        "difference", "difference_ci" (95 % t interval), "relative"}`` (difference / reference
        mean; ``None`` where undefined).

    Raises:
        ValueError: a seed repeats, or ``keys`` are not number columns (:func:`check_paired_metrics`).
    """
    check_paired_metrics(keys)
    def by_seed(group: Sequence[dict], name: str) -> dict[int, dict]:
        done = [row for row in group if row.get("status", "ok") == "ok"]
        seeds = [row["seed"] for row in done]
        if len(set(seeds)) != len(seeds):
            raise ValueError(f"{name}: a seed repeats ({len(seeds)} rows, {len(set(seeds))} seeds); "
                             "pass the rows of one driver on one scenario")
        return {row["seed"]: row for row in done}

    ours, theirs = by_seed(rows, "rows"), by_seed(reference, "reference")
    paired = sorted(ours.keys() & theirs.keys())
    result: dict = {
        "episodes": len(paired),
        "unpaired_seeds": sorted(ours.keys() ^ theirs.keys()),
        "collisions": sum(int(ours[seed]["collisions"]) for seed in paired),
        "reference_collisions": sum(int(theirs[seed]["collisions"]) for seed in paired),
    }
    for key in keys:
        pairs = [(ours[seed].get(key), theirs[seed].get(key)) for seed in paired]
        pairs = [(a, b) for a, b in pairs if _finite(a) is not None and _finite(b) is not None]
        mean, _ = mean_ci([a for a, _ in pairs])
        base, _ = mean_ci([b for _, b in pairs])
        difference, interval = mean_ci([a - b for a, b in pairs])
        result[key] = {"reference": base, "mean": mean, "difference": difference, "difference_ci": interval,
                       "relative": difference / abs(base) if difference is not None and base else None}
    return result


def _labels(summary: Sequence[dict]) -> list[tuple[str, str]]:
    """(driver line, scenario line) per column; the driver line is empty for a single driver."""
    several = len({entry["driver"] for entry in summary}) > 1
    return [(str(entry["driver"]) if several else "", entry["scenario"]) for entry in summary]


def format_table(summary: Sequence[dict]) -> str:
    """Plain-text table of :func:`summarize` entries, one column per driver x scenario, then
    the seeds of collisions and errors."""
    labels = _labels(summary)
    width = max([12, *(len(part) for label in labels for part in label)])
    lines = []
    if any(driver for driver, _ in labels):
        lines.append(f"{'driver':<22}" + "".join(f"{driver:>{width + 2}}" for driver, _ in labels))
    lines.append(f"{'scenario' if lines else '':<22}" + "".join(f"{scenario:>{width + 2}}" for _, scenario in labels))
    for key, header, fmt in TABLE:
        cells = []
        for entry in summary:
            value = entry.get(key)
            cells.append("-" if value is None or (isinstance(value, float) and math.isnan(value)) else fmt.format(value))
        lines.append(f"{header:<22}" + "".join(f"{cell:>{width + 2}}" for cell in cells))
    for entry, (driver, scenario) in zip(summary, labels):
        where = f"{driver} / {scenario}" if driver else scenario
        if entry["collisions"]:
            parts = entry.get("collision_parts", {})
            seeds = ", ".join(f"{seed} ({parts.get(seed, 'unknown')})" for seed in entry["collision_seeds"])
            lines.append(f"collisions in {where} (part of the ego struck): seeds {seeds}")
        if entry.get("errors"):
            lines.append(f"errors in {where}: seeds {entry['error_seeds']}")
    return "\n".join(lines)


#: A collider moving more than this far off the road's direction was changing lanes [deg].
TURNED_DEG = 5.0


def format_crashes(rows: Sequence[dict]) -> str:
    """Markdown: one line per collision with its scene (:data:`mmpc.collisions.CRASH_COLUMNS`),
    per driver x scenario, and a tally of the typical causes; empty without collisions."""
    crashed = [row for row in rows if row.get("status", "ok") == "ok" and row.get("collisions")]
    if not crashed:
        return ""

    def number(value: object, digits: int) -> str:
        return "-" if value is None else f"{value:.{digits}f}"

    lines = ["### Collisions", "",
             "The collider's position in the ego's frame (ahead, and toward +y: the right in highway-env), its "
             "heading to the road (+: toward +y), the ego's closing "
             "speed on it and offset from its lane centre, and the steps of the last second a fallback drove. "
             "The ego's fault: it struck the collider with its front or a side.", ""]
    for driver, scenario in dict.fromkeys((row.get("driver"), row["scenario"]) for row in crashed):
        mine = [row for row in crashed if row.get("driver") == driver and row["scenario"] == scenario]
        turned = sum(1 for row in mine if row.get("crash_other_heading_deg") is not None
                     and abs(row["crash_other_heading_deg"]) > TURNED_DEG)
        astride = sum(1 for row in mine if row.get("crash_ego_offset") is not None and abs(row["crash_ego_offset"]) > OFF_CENTRE)
        fallback = sum(1 for row in mine if row.get("crash_fallback_steps"))
        parts = {part: sum(1 for row in mine if row.get("collision_part") == part) for part in ("front", "side", "rear")}
        lines += [f"`{driver}` / {scenario}: {len(mine)} collisions; struck " + ", ".join(f"{n} {part}" for part, n in parts.items())
                  + f"; collider turned > {TURNED_DEG:g} deg in {turned}, ego > {OFF_CENTRE:g} m off its lane centre in "
                  f"{astride}, a fallback drove in the last second in {fallback}", "",
                  "| seed | t [s] | part | ahead [m] | +y [m] | heading [deg] | speed [m/s] | closing [m/s] | ego offset [m] "
                  "| ego speed [m/s] | fallback steps |", "|" + "---|" * 11]
        for row in mine:
            lines.append(" | ".join([
                f"| {row['seed']}", number(row.get("crash_time"), 1), row.get("collision_part") or "unknown",
                number(row.get("crash_along"), 1), number(row.get("crash_across"), 1),
                number(row.get("crash_other_heading_deg"), 1), number(row.get("crash_other_speed"), 1),
                number(row.get("crash_closing_speed"), 1), number(row.get("crash_ego_offset"), 2),
                number(row.get("crash_ego_speed"), 1), "-" if row.get("crash_fallback_steps") is None
                else str(row["crash_fallback_steps"])]) + " |")
        lines.append("")
    return "\n".join(lines)


def _cell(entry: dict, key: str) -> str:
    value, interval = entry.get(key), entry.get(f"{key}_ci")
    if value is None:
        return "-"
    digits = 3 if abs(value) < 10 else 2 if abs(value) < 100 else 1
    if interval is None:
        return f"{value:.{digits}f}"
    if key == "collision_rate":
        return f"{value:.{digits}f} [{interval[0]:.{digits}f}, {interval[1]:.{digits}f}]"
    return f"{value:.{digits}f} ± {(interval[1] - interval[0]) / 2:.{digits}f}"


def format_markdown(summary: Sequence[dict]) -> str:
    """Markdown: per scenario a table with the drivers side by side; means ± the half-width of
    their 95 % interval, the collision rate with its Wilson interval."""
    parts = []
    for scenario in dict.fromkeys(entry["scenario"] for entry in summary):
        mine = [entry for entry in summary if entry["scenario"] == scenario]
        header = "| " + " | ".join(["", *(f"`{entry['driver']}`" for entry in mine)]) + " |"
        lines = [f"### {scenario}", "", header, "|" + "---|" * (len(mine) + 1)]
        lines.append("| episodes (errors) | " + " | ".join(f"{e['episodes']} ({e['errors']})" for e in mine) + " |")
        lines.append("| collisions (ego's fault) | " + " | ".join(f"{e['collisions']} ({e['ego_fault_collisions']})"
                                                                   for e in mine) + " |")
        for key, label in COMPARED:
            lines.append(f"| {label} | " + " | ".join(_cell(entry, key) for entry in mine) + " |")
        parts.append("\n".join(lines))
    return "\n\n".join(parts) + "\n\n95 % intervals: t interval of the mean (±: half-width); Wilson for the collision rate.\n"


def plot_comparison(summary: Sequence[dict], path: str | Path) -> Path:
    """Grouped bars per scenario, one bar per driver, with 95 % intervals, one panel per
    :data:`COMPARED` metric."""
    import matplotlib.pyplot as plt

    from mmpc.plotting import save_figure

    scenarios = list(dict.fromkeys(entry["scenario"] for entry in summary))
    drivers = list(dict.fromkeys(entry["driver"] for entry in summary))
    fig, axes = plt.subplots(1, len(COMPARED), figsize=(3.6 * len(COMPARED), 3.6))
    width = 0.8 / len(drivers)
    for ax, (key, label) in zip(axes, COMPARED):
        for d, driver in enumerate(drivers):
            xs, heights, errors = [], [], [[], []]
            for s, scenario in enumerate(scenarios):
                entry = next((e for e in summary if e["driver"] == driver and e["scenario"] == scenario), None)
                if entry is None or entry.get(key) is None:
                    continue
                value, interval = entry[key], entry.get(f"{key}_ci") or [entry[key], entry[key]]
                xs.append(s + (d - (len(drivers) - 1) / 2) * width)
                heights.append(value)
                # a t interval of few episodes reaches below a bound the mean cannot cross: cut it there
                errors[0].append(value - (max(interval[0], 0.0) if key in NON_NEGATIVE else interval[0]))
                errors[1].append(interval[1] - value)
            ax.bar(xs, heights, width, yerr=errors, capsize=3, label=str(driver))
        ax.set_xticks(range(len(scenarios)), scenarios)
        ax.set_title(label, fontsize=10)
    axes[0].legend(fontsize=8)
    fig.suptitle("drivers x scenarios (95 % intervals)", fontsize=11)
    return save_figure(fig, path)


def write_tensorboard(rows: Sequence[dict], summary: Sequence[dict], logdir: str | Path) -> Path:
    """TensorBoard scalars, one run per driver (``logdir/<driver>``): per finished episode
    ``<scenario>/<metric>`` at step = seed; per scenario ``summary/<scenario>/<metric>`` (and
    ``..._ci_low`` / ``..._ci_high``) at step 0. The folder is rebuilt from ``rows`` on every
    call (written aside, then swapped in), so a resumed evaluation holds each episode once."""
    from torch.utils.tensorboard import SummaryWriter


    logdir = Path(logdir)
    staging = logdir.with_name(f".{logdir.name}.tmp-{os.getpid()}")
    shutil.rmtree(staging, ignore_errors=True)
    for driver in dict.fromkeys(row["driver"] for row in rows):
        writer = SummaryWriter(log_dir=str(staging / file_slug(str(driver))))
        try:
            for row in rows:
                if row["driver"] != driver or row.get("status", "ok") != "ok":
                    continue
                for key in ("collisions", "ego_fault_collisions", *MEAN_METRICS):
                    value = row.get(key)
                    if value is not None and math.isfinite(value):
                        writer.add_scalar(f"{row['scenario']}/{key}", value, global_step=row["seed"])
            for entry in summary:
                if entry["driver"] != driver:
                    continue
                for key in ("collision_rate", "ego_fault_collisions", *MEAN_METRICS):
                    if entry.get(key) is None:
                        continue
                    writer.add_scalar(f"summary/{entry['scenario']}/{key}", entry[key], global_step=0)
                    if entry.get(f"{key}_ci") is not None:
                        writer.add_scalar(f"summary/{entry['scenario']}/{key}_ci_low", entry[f"{key}_ci"][0], global_step=0)
                        writer.add_scalar(f"summary/{entry['scenario']}/{key}_ci_high", entry[f"{key}_ci"][1], global_step=0)
        finally:
            writer.close()
    shutil.rmtree(logdir, ignore_errors=True)
    if staging.exists():
        os.replace(staging, logdir)
    return logdir


def write_report(rows: Sequence[dict], summary: Sequence[dict], out: str | Path) -> list[Path]:
    """``summary.md`` (the tables and :func:`format_crashes`), ``compare.png`` and ``tensorboard/``
    in ``out``; returns the paths."""
    out = Path(out)
    markdown = out / "summary.md"
    crashes = format_crashes(rows)
    markdown.write_text(format_markdown(summary) + ("\n" + crashes if crashes else ""))
    paths = [markdown]
    if any(entry["episodes"] for entry in summary):
        paths.append(plot_comparison(summary, out / "compare.png"))
    paths.append(write_tensorboard(rows, summary, out / "tensorboard"))
    return paths

