"""Warm start, offline (issue 41): does a solve started from the previous step's 100-iteration
solution, shifted one control step, reach that step's cold 100-iteration answer in the last k
iterations of the penalty schedule?

    python scripts/warm_start_offline.py high_speed 70000,70001,70002,70003,70004,70005,70006,70007 5.0 runs/warm.json

Drives the seeds in lockstep on the batched simulator with the eager expert, then re-solves every
recorded step: cold with k iterations (the schedule's first k), and warm from the previous step's
reference iterates (:meth:`mmpc.BatchOptimizer.shifted` coefficients; multipliers zeroed or kept
unshifted) with the last k. Per variant: the share of the reference's feasible goals found
(recall), feasibility agreement, the same goal chosen (meta cost, ``select_best``) and the
reference cost given up by the variant's choice.
"""
import dataclasses
import json
import sys

import torch

from mmpc.drivers import MPCDriver
from mmpc.highway.runner import Observer, run_lockstep
from mmpc.ranking import select_best
from mmpc.scenario import PAPER_SCHEDULE, build_mpc, load_scenario
from mmpc.solver.optimizer import BatchOptimizer

COLD_ITERATIONS = (10, 20, 30, 50)
WARM_ITERATIONS = (10, 20, 30)


def main(argv: list[str]) -> dict:
    """Run the study: ``argv`` = scenario, comma-separated seeds, duration [s], JSON path; returns the rows."""
    torch.set_num_threads(1)
    name, seeds, duration, out_path = argv[0], [int(s) for s in argv[1].split(",")], float(argv[2]), argv[3]
    scenario = load_scenario(name, {"sim": "batched", **PAPER_SCHEDULE}).replace(duration=duration)  # cold references
    mpc = build_mpc(scenario, compile=False)
    opt = mpc.optimizer
    cfg = opt.config
    dt = 1.0 / scenario.frequency
    short = {k: BatchOptimizer(dataclasses.replace(cfg, iterations=k)) for k in COLD_ITERATIONS}  # the schedule's head

    class Problems(Observer):
        def __init__(self):
            self.problems = []

        def decided(self, observation, decision, active):
            self.problems.append(decision.plan.problem if len(active) == len(seeds) else None)

    recorder = Problems()
    run_lockstep(scenario, seeds, driver=MPCDriver(mpc), observers=[recorder])

    def warm_start(previous, previous_problem, problem, multipliers):
        """The previous reference's iterates shifted one control step to this problem's start."""
        shifted = opt.shifted(previous.warm, dt, problem.ego[:, :2] - previous_problem.ego[:, :2])
        if multipliers == "keep":
            return shifted._replace(multipliers=previous.warm.multipliers, heading_multipliers=previous.warm.heading_multipliers)
        return shifted._replace(multipliers=torch.zeros_like(shifted.multipliers),
                                heading_multipliers=torch.zeros_like(shifted.heading_multipliers))

    def choice(result):
        cost = mpc.meta_cost(result.trajectories, mpc.road)
        best = select_best(result, cost, cfg)
        return best.index, best.feasible, cost

    rows = {}
    previous = None  # (reference result, problem) of the step before
    for problem in recorder.problems:
        if problem is None:
            previous = None
            continue
        with torch.no_grad():
            cold = opt(problem)
        ref_index, ref_ok, ref_cost = choice(cold)
        variants = {f"cold{k}": lambda k=k: short[k](problem) for k in COLD_ITERATIONS}
        if previous is not None and previous[0].warm.position.shape[:2] == problem.goals.shape[:2]:
            for k in WARM_ITERATIONS:
                for lam in ("zero", "keep"):
                    variants[f"warm{k}_{lam}_tail"] = lambda k=k, lam=lam: opt(
                        problem, warm=warm_start(*previous, problem, lam), warm_iterations=k)
        for key, run in variants.items():
            with torch.no_grad():
                result = run()
            index, ok, _ = choice(result)
            row = rows.setdefault(key, {"steps": 0, "elements": 0, "same_feasible": 0, "cold_feasible": 0, "found": 0,
                                        "extra": 0, "same_choice": 0, "choice_steps": 0, "regret": 0.0, "ref_cost": 0.0})
            both = ok & ref_ok
            rows_e = torch.arange(index.shape[0])
            # the reference cost of what the variant chose, above the reference's own choice
            regret = (ref_cost[rows_e, index] - ref_cost[rows_e, ref_index]).clamp_min(0)
            row["regret"] += float(regret[both].sum())
            row["ref_cost"] += float(ref_cost[rows_e, ref_index][both].sum())
            row["steps"] += 1
            row["elements"] += cold.feasible.numel()
            row["same_feasible"] += int((result.feasible == cold.feasible).sum())
            row["cold_feasible"] += int(cold.feasible.sum())
            row["found"] += int((result.feasible & cold.feasible).sum())
            row["extra"] += int((result.feasible & ~cold.feasible).sum())
            row["same_choice"] += int(((index == ref_index) & ok & ref_ok).sum())
            row["choice_steps"] += int(ref_ok.sum())
        previous = (cold, problem)
    out = {k: {**v, "recall": v["found"] / max(v["cold_feasible"], 1), "agreement": v["same_feasible"] / max(v["elements"], 1),
               "same_choice_share": v["same_choice"] / max(v["choice_steps"], 1),
               "relative_regret": v["regret"] / max(v["ref_cost"], 1e-9)} for k, v in rows.items()}
    for k, v in sorted(out.items()):
        print(f"{k:>20}: steps {v['steps']:4d} feasible recall {v['recall']:.3f}, extra {v['extra']:5d}, agreement "
              f"{v['agreement']:.3f}, same choice {v['same_choice_share']:.3f}, cost regret {100 * v['relative_regret']:.2f} %")
    with open(out_path, "w") as handle:
        json.dump(out, handle, indent=1)
    return out


if __name__ == "__main__":
    main(sys.argv[1:])
