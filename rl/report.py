"""Results of training runs side by side: TensorBoard curves as an image, the evaluations as a
table (``mmpc rl report``)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Mapping

#: Curves drawn, by TensorBoard tag, with their axis labels.
CURVES = {
    "rollout/ep_rew_mean": "episode return",
    "safety/crashes": "collisions since the start",
    "driving/mean_speed": "mean speed [m/s]",
    "safety/intervention_rate": "intervention rate (frames)",
}


def read_scalars(run: str | Path) -> dict[str, list[tuple[int, float]]]:
    """Every scalar of a run's TensorBoard event files (``RUN/tb/*``), by tag: (step, value) pairs."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    folders = sorted((Path(run) / "tb").glob("*"))
    if not folders:
        raise FileNotFoundError(f"no TensorBoard folder under {Path(run) / 'tb'}; was {run} written by `mmpc rl train`?")
    scalars: dict[str, list[tuple[int, float]]] = {}
    for folder in folders:
        events = EventAccumulator(str(folder))
        events.Reload()
        for tag in events.Tags()["scalars"]:
            scalars.setdefault(tag, []).extend((event.step, event.value) for event in events.Scalars(tag))
    return scalars


def training_crashes_per_1e5_steps(run: str | Path) -> float | None:
    """Collisions while training per 10^5 agent steps, from the run's last ``safety/crashes`` scalar
    (None for runs written before the count was logged)."""
    points = read_scalars(run).get("safety/crashes")
    if not points:
        return None
    step, crashes = max(points)
    return crashes / step * 1e5 if step > 0 else None


def plot_curves(runs: Mapping[str, str | Path], path: str | Path) -> Path:
    """One panel per :data:`CURVES` tag, one line per run (label -> run directory)."""
    import matplotlib.pyplot as plt

    from mmpc.plotting import save_figure

    fig, axes = plt.subplots(1, len(CURVES), figsize=(4.2 * len(CURVES), 3.4))
    for label, run in runs.items():
        scalars = read_scalars(run)
        for axis, (tag, name) in zip(axes, CURVES.items()):
            points = sorted(scalars.get(tag, []))
            if points:
                axis.plot([p[0] for p in points], [p[1] for p in points], label=label)
    for axis, (tag, name) in zip(axes, CURVES.items()):
        axis.set_title(tag, fontsize=9)
        axis.set_xlabel("agent steps")
        axis.set_ylabel(name)
        axis.grid(alpha=0.3)
    axes[0].legend()
    return save_figure(fig, path)


def results_table(runs: Mapping[str, str | Path]) -> tuple[str, dict]:
    """A markdown table of the runs' ``eval.json`` and the figures as a dict (label -> summary); its
    train steps are the steps trained (``trained_timesteps``, the budget rounded up to whole rollouts)."""
    rows = ["| agent | algorithm | env | train steps | train time [min] | training crashes per 10^5 steps | episodes | "
            "collision rate | mean speed [m/s] | mean return | intervention rate |",
            "|---|---|---|---|---|---|---|---|---|---|---|"]
    figures = {}
    for label, run in runs.items():
        path = Path(run) / "eval.json"
        if not path.is_file():
            raise FileNotFoundError(f"no {path}: train the run with its evaluation (without --no-eval)")
        summary = json.loads(path.read_text())
        figures[label] = {key: summary.get(key) for key in ("algo", "env", "timesteps", "trained_timesteps", "train_seconds",
                                                            "episodes", "collision_rate", "mean_speed", "mean_return",
                                                            "intervention_rate")}
        figures[label]["training_crashes_per_1e5_steps"] = crashes = training_crashes_per_1e5_steps(run)
        rate = summary.get("intervention_rate")
        minutes = summary.get("train_seconds", float("nan")) / 60
        steps = summary.get("trained_timesteps", summary.get("timesteps"))  # older runs recorded the budget alone
        rows.append(f"| {label} | {summary.get('algo')} | {summary.get('env')} | {steps} | {minutes:.0f} | "
                    f"{'n/a' if crashes is None else f'{crashes:.1f}'} | "
                    f"{summary['episodes']} | {summary['collision_rate']:.0%} | {summary['mean_speed']:.2f} | "
                    f"{summary['mean_return']:.1f} | {'n/a' if rate is None else f'{rate:.1%}'} |")
    return "\n".join(rows), figures
