"""Learning curve of the mode proposer: held-out agreement with the expert and closed-loop meta
cost vs the number of labelled states.

Reads the labels of an ``mmpc imitate proposer`` run (all rounds, in round order), and for every
size N trains a proposer from scratch on the first episodes that hold N states (the run's own
training config), then measures on data no training saw:

- ``coverage``: the share of held-out states (expert-driven episodes on separate seeds) whose expert
  goal is among the goals the driver solves: the proposer's best ``keep`` and the ego lane's
  stop goal; ``top_k``: among the best ``keep`` alone;
- closed loop on the run's world: the proposer's driver alone on ``--check-episodes`` seeds,
  collisions, mean meta cost and the share of escalated steps, beside the expert on the same seeds.

Prints a table, writes ``OUT/learning_curve.json`` and ``OUT/learning_curve.png`` (the held-out
labels go to ``RUN/held_out``, reused by a later call).

    python scripts/proposer_learning_curve.py --run runs/proposer/high_speed --sizes 10000,30000,100000 --out docs/imitation/proposer_high_speed
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from mmpc.config import from_dict, to_dict
from mmpc.drivers import MPCDriver
from mmpc.imitation.features import scene_geometry
from mmpc.imitation.labels import label_episodes, read_labels
from mmpc.imitation.listwise import RankingLabels, top_k_agreement, train_proposer
from mmpc.imitation.proposer_dagger import REPORT, ProposerDaggerConfig, check_drive
from mmpc.imitation.proposer_driver import ProposerDriver, ego_lane_stop_goal
from mmpc.scenario import ScenarioConfig, build_mpc


def first_states(labels: RankingLabels, count: int) -> RankingLabels:
    """The first whole episodes of ``labels`` that hold at least ``count`` states (all if fewer)."""
    ends = np.flatnonzero(np.diff(labels.episodes, append=labels.episodes[-1] + 1)) + 1
    stop = ends[np.searchsorted(ends, min(count, labels.num_states))]
    return labels.take(np.arange(stop))


def coverage(proposer, mpc, labels: RankingLabels, keep: int) -> tuple[float, float]:
    """(coverage, top-k agreement) of ``proposer`` on ``labels`` (see the module docstring)."""
    features = torch.as_tensor(proposer.features(labels.ego, labels.neighbours))
    with torch.no_grad():
        scores, _ = proposer(features)
    expert = torch.as_tensor(labels.expert)
    stop = ego_lane_stop_goal(mpc, torch.as_tensor(labels.ego), labels.num_goals)
    top = scores.topk(keep, dim=1).indices
    covered = (top == expert[:, None]).any(dim=1) | (stop == expert if stop is not None else False)
    return float(covered.float().mean()), top_k_agreement(scores, expert, keep)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", required=True, help="an `mmpc imitate proposer --out` folder")
    parser.add_argument("--sizes", default="10000,30000,100000", help="labelled states per point, comma-separated")
    parser.add_argument("--held-out-episodes", type=int, default=16, help="expert-driven episodes labelled for the agreement")
    parser.add_argument("--held-out-seed-start", type=int, default=48000)
    parser.add_argument("--check-episodes", type=int, default=32, help="closed-loop episodes per point (0: none)")
    parser.add_argument("--check-seed-start", type=int, default=49000)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    run, out = Path(args.run), Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    identity = json.loads((run / REPORT).read_text())["identity"]
    scenario = from_dict(ScenarioConfig, identity["scenario"], where=f"{run / REPORT}: scenario")
    config = from_dict(ProposerDaggerConfig, {**identity["config"], "rounds": 0}, where=f"{run / REPORT}: config")
    rounds = sorted((run / "labels").glob("round_*"), key=lambda p: int(p.name.removeprefix("round_")))
    labels = read_labels(rounds)
    held_out_seeds = list(range(args.held_out_seed_start, args.held_out_seed_start + args.held_out_episodes))
    name = "".join(c if c.isalnum() else "_" for c in scenario.name)
    label_episodes(scenario, held_out_seeds, run / "held_out", lockstep=config.lockstep,  # beside the run's labels
                   dataset_id=f"mmpc/{name}-rankings-heldout-v0")
    held_out = read_labels([run / "held_out"])
    mpc = build_mpc(scenario)
    check_seeds = list(range(args.check_seed_start, args.check_seed_start + args.check_episodes))
    expert = check_drive(scenario, MPCDriver(mpc, period=scenario.period), check_seeds, config.lockstep) if check_seeds else None
    keep = config.train.keep
    rows = []
    print(f"{scenario.name}: {labels.num_states} labelled states in {len(rounds)} rounds; held out: "
          f"{held_out.num_states} states of {len(held_out_seeds)} expert episodes")
    if expert is not None:
        print(f"expert alone on {len(check_seeds)} episodes: collisions {expert['collisions']}, "
              f"meta cost {expert['meta_cost_mean']:.2f}")
    print(f"{'states':>9} {'coverage':>9} {'top-' + str(keep):>7} {'collisions':>10} {'meta cost':>10} {'escalated':>9} {'train s':>8}")
    for size in sorted(int(s) for s in args.sizes.split(",")):
        subset = first_states(labels, size)
        start = time.perf_counter()
        proposer, _ = train_proposer(subset, scenario.road, config.train, scene=scene_geometry(scenario))
        seconds = time.perf_counter() - start
        covered, top_k = coverage(proposer, mpc, held_out, keep)
        row = {"states": subset.num_states, "coverage": covered, "top_k": top_k, "train_s": seconds}
        if check_seeds:
            driver = ProposerDriver(mpc, proposer, keep=keep)
            row.update({f"check_{k}": v for k, v in check_drive(scenario, driver, check_seeds, config.lockstep).items()})
            row["escalated_share"] = driver.escalated_rows / max(driver.decided_rows, 1)
        rows.append(row)
        check = (f"{row['check_collisions']:>10} {row['check_meta_cost_mean']:>10.2f} {row['escalated_share']:>9.1%}"
                 if check_seeds else "")
        print(f"{row['states']:>9} {covered:>9.3f} {top_k:>7.3f} {check} {seconds:>8.0f}")
        if subset.num_states == labels.num_states:
            break
    result = {"scenario": scenario.name, "run": str(run), "keep": keep, "held_out_seeds": held_out_seeds,
              "check_seeds": check_seeds, "expert_check": expert, "train": to_dict(config.train), "rows": rows}
    (out / "learning_curve.json").write_text(json.dumps(result, indent=2) + "\n")
    plot(result, out / "learning_curve.png")
    print(f"wrote {out / 'learning_curve.json'} and {out / 'learning_curve.png'}")


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["rows"]
    states = [row["states"] for row in rows]
    figure, (left, right) = plt.subplots(1, 2, figsize=(9, 3.4))
    left.plot(states, [row["coverage"] for row in rows], "o-", label=f"expert goal solved (top {result['keep']} + stop)")
    left.plot(states, [row["top_k"] for row in rows], "s--", label=f"expert goal in top {result['keep']}")
    left.set(xscale="log", xlabel="labelled states", ylabel="held-out share", ylim=(0, 1.02),
             title=f"{result['scenario']}: agreement with the expert")
    left.legend(loc="lower right", fontsize=8)
    if result["expert_check"] is not None:
        right.plot(states, [row["check_meta_cost_mean"] for row in rows], "o-", label="proposer + optimizer")
        expert = result["expert_check"]["meta_cost_mean"]
        right.axhline(expert, color="k", ls=":", label="MPC expert (all goals)")
        right.set_ylim(0.0, 1.1 * max([expert] + [row["check_meta_cost_mean"] for row in rows]))
        right.set(xscale="log", xlabel="labelled states", ylabel="mean meta cost (lower is better)",
                  title=f"closed loop, {len(result['check_seeds'])} held-out episodes")
        right.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=120)


if __name__ == "__main__":
    main()
