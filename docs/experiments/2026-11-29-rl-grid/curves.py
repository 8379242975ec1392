"""Learning curves of the grid with the across-seed band, one PNG per scenario, and the training
collisions per 10^5 steps, from the runs' TensorBoard files (runs/grid/<recipe>/<kind>_<algo>_<seed>).

    python docs/experiments/2026-11-29-rl-grid/curves.py runs/grid --out docs/experiments/2026-11-29-rl-grid
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import numpy as np

from mmpc.rl.report import read_scalars

NAME = re.compile(r"(?:(plain)_)?(ppo|dqn)_(\d+)")
TAGS = {"rollout/ep_rew_mean": "episode return (training, stochastic policy)", "driving/mean_speed": "mean speed [m/s]",
        "safety/collision_rate": "collision rate (last 100 episodes)"}


def runs_of(recipe: Path) -> dict[str, dict[int, Path]]:
    """label ("PPO behind the layer", "DQN plain", ...) -> seed -> run folder."""
    groups: dict[str, dict[int, Path]] = {}
    for folder in sorted(p for p in recipe.iterdir() if p.is_dir()):
        match = NAME.fullmatch(folder.name)
        if match and (folder / "tb").is_dir():
            plain, algo, seed = match.groups()
            label = f"{algo.upper()} {'plain' if plain else 'behind the layer'}"
            groups.setdefault(label, {})[int(seed)] = folder
    return groups


def band(curves: list[list[tuple[int, float]]], grid: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean, min and max over the seeds of curves interpolated onto ``grid`` (steps past a curve's end: NaN)."""
    values = np.full((len(curves), len(grid)), np.nan)
    for row, points in enumerate(curves):
        steps, ys = (np.array(v, dtype=float) for v in zip(*sorted(points)))
        inside = grid <= steps[-1]
        values[row, inside] = np.interp(grid[inside], steps, ys)
    return np.nanmean(values, axis=0), np.nanmin(values, axis=0), np.nanmax(values, axis=0)


def main() -> None:
    import matplotlib.pyplot as plt

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("grid", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    table = {}
    for recipe in sorted(p for p in args.grid.iterdir() if p.is_dir() and p.name.endswith("_task")):
        groups = runs_of(recipe)
        fig, axes = plt.subplots(1, len(TAGS), figsize=(5 * len(TAGS), 3.6))
        for label, seeds in groups.items():
            scalars = {seed: read_scalars(folder) for seed, folder in seeds.items()}
            scalars = {seed: s for seed, s in scalars.items() if s.get("safety/crashes")}  # logged at least once
            if not scalars:
                continue
            last = max(max(step for step, _ in s["safety/crashes"]) for s in scalars.values())
            grid = np.linspace(0, last, 200)
            for axis, tag in zip(axes, TAGS):
                curves = [s[tag] for s in scalars.values() if s.get(tag)]
                if curves:
                    mean, low, high = band(curves, grid)
                    (line,) = axis.plot(grid, mean, label=f"{label} ({len(curves)} seeds)")
                    axis.fill_between(grid, low, high, color=line.get_color(), alpha=0.2)
            for seed, s in scalars.items():
                crashes, episodes = max(s["safety/crashes"]), max(s["safety/episodes"])
                table.setdefault(recipe.name, {}).setdefault(label, {})[seed] = {
                    "steps": crashes[0], "crashes": int(crashes[1]), "episodes": int(episodes[1]),
                    "crashes_per_1e5_steps": crashes[1] / crashes[0] * 1e5}
        for axis, (tag, name) in zip(axes, TAGS.items()):
            axis.set_xlabel("agent steps")
            axis.set_ylabel(name)
            axis.grid(alpha=0.3)
        axes[0].legend(fontsize=8)
        fig.suptitle(f"{recipe.name}: mean over seeds, band min-max")
        fig.tight_layout()
        fig.savefig(args.out / f"curves_{recipe.name}.png", dpi=110)
        plt.close(fig)
    (args.out / "training_collisions.json").write_text(json.dumps(table, indent=2) + "\n")
    for recipe, groups in table.items():
        for label, seeds in groups.items():
            per = [f"seed {seed}: {v['crashes']} in {v['steps']} steps ({v['crashes_per_1e5_steps']:.1f} per 10^5)"
                   for seed, v in sorted(seeds.items())]
            print(f"{recipe} | {label} | " + "; ".join(per))


if __name__ == "__main__":
    main()
