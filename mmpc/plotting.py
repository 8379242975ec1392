"""Figures: candidate trajectories of one solve, solver scaling, a closed-loop episode."""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import Ellipse  # noqa: E402
import torch  # noqa: E402

from mmpc.obstacles.shape import HIGHWAY_VEHICLE  # noqa: E402
from mmpc.problem import ProblemBatch  # noqa: E402
from mmpc.result import SolveResult  # noqa: E402
from mmpc.road import Road  # noqa: E402


def save_figure(fig: plt.Figure, path: str | Path, dpi: int = 120) -> Path:
    """Write ``fig`` to ``path`` (folders created) and close it."""
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def plot_candidates(
    path: str | Path,
    problem: ProblemBatch,
    result: SolveResult,
    road: Road,
    *,
    ellipse: tuple[float, float],
    best: Optional[int] = None,
    vehicle: tuple[float, float] = HIGHWAY_VEHICLE,
    problem_index: int = 0,
    title: str = "",
) -> Path:
    """Top-down plot of the G candidate trajectories of problem ``problem_index``.

    Feasible candidates are solid, infeasible ones dotted grey, the ``best`` one thick red;
    obstacles are drawn as their ellipses (semi-axes ``ellipse`` [m], the optimizer's
    :attr:`mmpc.OptimizerConfig.ellipse`) at t = 0 with their
    predicted paths, the ego as a ``vehicle`` = (length, width) [m] rectangle (a scenario's
    ``ScenarioConfig.vehicle``; highway-env's by default).
    """
    e = problem_index
    x = result.trajectories.x[e].detach().cpu()
    y = result.trajectories.y[e].detach().cpu()
    feasible = result.feasible[e].cpu()
    obstacles = problem.obstacles[e].detach().cpu()
    mask = problem.obstacle_mask[e].cpu() if problem.obstacle_mask is not None else torch.ones(obstacles.shape[0], dtype=torch.bool)
    ego = problem.ego[e].detach().cpu()

    fig, ax = plt.subplots(figsize=(12, 4.2))
    x_min = float(min(x.min(), obstacles[mask][..., 0].min() if mask.any() else x.min())) - 10
    x_max = float(max(x.max(), obstacles[mask][..., 0].max() if mask.any() else x.max())) + 10
    low, high = road.bounds
    ax.axhspan(low, high, color="0.93", zorder=0)
    for k in range(road.num_lanes + 1):
        ax.axhline(low + k * road.lane_width, color="0.6", lw=1, ls="-" if k in (0, road.num_lanes) else "--", zorder=1)
    colors = plt.cm.viridis(torch.linspace(0, 1, x.shape[0]).numpy())
    for g in range(x.shape[0]):
        if g == best:
            continue
        style = dict(lw=1.4, color=colors[g]) if feasible[g] else dict(lw=1.0, color="0.55", ls=":")
        ax.plot(x[g], y[g], zorder=3, **style)
    if best is not None:
        ax.plot(x[best], y[best], color="crimson", lw=3.0, zorder=5, label="best (lowest meta cost)")
    for j in range(obstacles.shape[0]):
        if not mask[j]:
            continue
        ax.plot(obstacles[j, :, 0], obstacles[j, :, 1], color="tab:blue", lw=0.8, alpha=0.5, zorder=2)
        ax.add_patch(Ellipse((float(obstacles[j, 0, 0]), float(obstacles[j, 0, 1])), 2 * ellipse[0], 2 * ellipse[1],
                             facecolor="tab:blue", alpha=0.35, zorder=4))
        ax.add_patch(Ellipse((float(obstacles[j, -1, 0]), float(obstacles[j, -1, 1])), 2 * ellipse[0], 2 * ellipse[1],
                             facecolor="none", edgecolor="tab:blue", ls="--", alpha=0.6, zorder=4))
    length, width = vehicle
    ax.add_patch(plt.Rectangle((float(ego[0]) - length / 2, float(ego[1]) - width / 2), length, width, color="crimson",
                               zorder=6))
    ax.plot([], [], color="0.55", ls=":", label="infeasible")
    ax.plot([], [], color=colors[0], label="feasible")
    ax.set_xlim(x_min, x_max)
    ax.set_ylim(high + 1, low - 1)  # lane 0 (left) on top, as highway-env draws it
    ax.set_xlabel("x along the road [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title or "candidate trajectories (obstacles: filled at t=0, dashed at t_f)")
    ax.legend(loc="upper left", fontsize=8)
    return save_figure(fig, path)


def plot_scaling(path: str | Path, rows: Sequence[dict], title: str = "") -> Path:
    """ms per solve vs batch size, one line per (device, variant, obstacles) as in the rows."""
    fig, ax = plt.subplots(figsize=(6, 4))
    keys = sorted({(r["device"], r.get("variant", ""), r["obstacles"]) for r in rows})
    for device, variant, obstacles in keys:
        key = (device, variant, obstacles)
        sel = sorted((r for r in rows if (r["device"], r.get("variant", ""), r["obstacles"]) == key), key=lambda r: r["batch"])
        label = f"{device} {variant} M={obstacles}".replace("  ", " ")
        ax.plot([r["batch"] for r in sel], [r["ms_median"] for r in sel], marker="o", label=label)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("batch size (goals)")
    ax.set_ylabel("ms per solve (100 iterations)")
    ax.set_title(title or "batch optimizer: computation time vs batch size")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def plot_episode(path: str | Path, records: Sequence, road: Road, *, v_ref: Optional[float] = None, title: str = "") -> Path:
    """Top-down view of a closed-loop episode and its speed and lane over time.

    Args:
        path: output image.
        records: :class:`mmpc.metrics.StepRecord` rows, in order.
        road: the road (lanes are drawn).
        v_ref: the objective's reference speed [m/s], drawn as a dashed line.
        title: figure title.
    """
    x = [r.x for r in records]
    y = [r.y for r in records]
    t = [r.time for r in records]
    v = [r.v for r in records]
    low, high = road.bounds
    fig, (top, speed, lateral) = plt.subplots(3, 1, figsize=(12, 7.5), gridspec_kw={"height_ratios": [1.3, 1, 1]})
    top.axhspan(low, high, color="0.93", zorder=0)
    for k in range(road.num_lanes + 1):
        top.axhline(low + k * road.lane_width, color="0.6", lw=1, ls="-" if k in (0, road.num_lanes) else "--", zorder=1)
    path_plot = top.scatter(x, y, c=v, s=4, cmap="viridis", zorder=3)
    fig.colorbar(path_plot, ax=top, label="speed [m/s]", pad=0.01)
    crashed = [r for r in records if r.crashed]
    if crashed:
        top.plot(crashed[0].x, crashed[0].y, "x", color="crimson", ms=12, mew=3, zorder=5, label="collision")
        top.legend(loc="upper left", fontsize=8)
    fallback = [r for r in records if r.fallback]
    if fallback:
        top.plot([r.x for r in fallback], [r.y for r in fallback], ".", color="orange", ms=4, zorder=4, label="no feasible candidate")
        top.legend(loc="upper left", fontsize=8)
    top.set_ylim(high + 1, low - 1)  # lane 0 (left) on top, as highway-env draws it
    top.set_xlabel("x along the road [m]")
    top.set_ylabel("y [m]")
    top.set_title(title or "closed-loop episode")
    speed.plot(t, v, color="tab:blue", label="speed")
    if v_ref is not None:
        speed.axhline(v_ref, color="0.3", ls="--", lw=1, label=f"reference {v_ref:g} m/s")
    speed.set_ylabel("v [m/s]")
    speed.legend(loc="lower right", fontsize=8)
    speed.grid(alpha=0.3)
    lateral.plot(t, y, color="tab:green")
    for k in range(road.num_lanes):
        lateral.axhline(k * road.lane_width, color="0.8", lw=0.8, zorder=0)
    lateral.set_ylim(high, low)
    lateral.set_xlabel("time [s]")
    lateral.set_ylabel("y [m]")
    lateral.grid(alpha=0.3)
    return save_figure(fig, path, dpi=110)
