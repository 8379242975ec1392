"""Warm start, offline (issue 41's measurement before a warm start is built into the optimizer):
does a solve started from the previous step's 100-iteration solution, shifted one control step,
reach that step's cold 100-iteration answer in the last k iterations of the penalty schedule?

    python scripts/warm_start_offline.py high_speed 70000,70001,70002,70003,70004,70005,70006,70007 5.0 runs/warm.json

Drives the seeds in lockstep on the batched simulator with the eager expert, then re-solves every
recorded step: cold with k iterations, and warm (the shifted coefficients; multipliers zeroed or
kept) with the last k. Per variant: the share of the reference's feasible goals found (recall),
feasibility agreement, the same goal chosen (meta cost, ``select_best``) and the reference cost
given up by the variant's choice. It reaches into :mod:`mmpc.optimizer`'s private functions on
purpose: the state it warms is not public yet.
"""
import json
import sys

import torch
from mmpc.basis import _bernstein
from mmpc.drivers import MPCDriver
from mmpc.highway.runner import Observer, run_lockstep
from mmpc.optimizer import _atan2, _closed_form_steps, _iterate, _start, _summarise, _validate
from mmpc.ranking import select_best
from mmpc.result import SolveResult, Trajectories
from mmpc.scenario import build_mpc, load_scenario

def main(argv: list[str]) -> dict:
    """Run the study: ``argv`` = scenario, comma-separated seeds, duration [s], JSON path; returns the rows."""
    torch.set_num_threads(1)
    name, seeds, duration, out_path = argv[0], [int(s) for s in argv[1].split(",")], float(argv[2]), argv[3]
    scenario = load_scenario(name, {"sim": "batched"}).replace(duration=duration)
    mpc = build_mpc(scenario, compile=False)
    opt = mpc.optimizer
    cfg = opt.config
    dt = 1.0 / scenario.frequency

    class Problems(Observer):
        def __init__(self):
            self.problems = []
        def decided(self, observation, decision, active):
            self.problems.append(decision.plan.problem if len(active) == len(seeds) else None)

    recorder = Problems()
    run_lockstep(scenario, seeds, driver=MPCDriver(mpc), observers=[recorder])

    tau = torch.linspace(0.0, 1.0, cfg.num_steps, dtype=torch.float64)
    P = _bernstein(cfg.order, tau)
    P_shift = _bernstein(cfg.order, (tau + dt / cfg.horizon))  # extrapolates the last 0.1 s
    SHIFT = (torch.linalg.pinv(P) @ P_shift).to(opt.dtype)  # (K, K): c' = SHIFT c


    def solve(problem, state=None, first=0, last=None):
        """The eager iterations first..last-1 from ``state`` (None: the cold start); the result and the final state."""
        last = cfg.iterations if last is None else last
        ego, goals, obstacles, mask, axes = _validate(problem, cfg, opt.dtype, opt.device)
        prepared = opt._prepare(ego, goals, obstacles, mask, axes, False)
        limits = opt._eager_limits
        gather_index = max(first - 1, 0)
        if state is None:
            state = _start(prepared.b_position, prepared.obstacles, prepared.axes, opt.position_init, opt.samples,
                           opt.gather[gather_index], limits)
        else:  # the residual of the warm c, scaled as the position QP of iteration `first` expects
            c = state.c
            n = opt.samples.shape[0] // 3
            samples = (opt.samples @ c).view(3 * n, 2, prepared.obstacles.shape[3], -1)
            psi = _atan2(samples[2 * n:, 1], samples[2 * n:, 0], limits)
            residuals = _closed_form_steps(samples, psi, prepared.obstacles, prepared.axes, limits)
            state = state._replace(scaled_residual=opt.gather[gather_index] @ residuals.stacked.view(3 * n, -1))
        for start in range(first, last, opt.chunk):
            stop = min(start + opt.chunk, last)
            position = opt.position[start:stop, prepared.uniform_count] if prepared.uniform_count is not None else \
                opt.position[start:stop].index_select(1, prepared.counts)
            state, step = _iterate(state, prepared.b_position, prepared.b_heading, prepared.obstacles, prepared.axes, position,
                                   opt.gather[start:stop], opt.heading[start:stop], opt.heading_gather[start:stop], opt.samples,
                                   opt.heading_basis, limits, False)
        fields, coefficients, norms, scalars, status = _summarise(
            state.c, step, prepared.obstacles, prepared.axes, prepared.mask, prepared.origin, prepared.goal_ahead,
            prepared.num_goals, opt.heading_basis, opt.heading_rate_basis, cfg, limits)
        result = SolveResult(Trajectories(opt.times, *fields), coefficients, norms[..., 0], norms[..., 1], norms[..., 2],
                             *scalars, status=status, feasible=status == 0, history=None)
        return result, state, prepared


    def warm_state(state, prepared_prev, prepared_now, multipliers):
        """The previous final state shifted one control step and moved to the new start."""
        E = prepared_now.origin.shape[0]
        K, B2 = state.c.shape
        G = B2 // (2 * E)
        delta = (prepared_now.origin - prepared_prev.origin)  # (E, 2)
        offset = delta.T[:, :, None].expand(2, E, G).reshape(1, -1)  # columns (axis, e, g)
        c = SHIFT @ state.c - offset
        lam = state.multipliers if multipliers == "keep" else torch.zeros_like(state.multipliers)
        lam_psi = state.multipliers_psi if multipliers == "keep" else torch.zeros_like(state.multipliers_psi)
        return state._replace(c=c, multipliers=lam, multipliers_psi=lam_psi)


    def choice(result, problem):
        cost = mpc.meta_cost(result.trajectories, mpc.road)
        best = select_best(result, cost, cfg)
        return best.index, best.feasible, cost


    rows = {}
    previous = None
    for t, problem in enumerate(recorder.problems):
        if problem is None:
            previous = None
            continue
        with torch.no_grad():
            cold, cold_state, prepared = solve(problem)
        ref_index, ref_ok, ref_cost = choice(cold, problem)
        variants = {}
        for k in (10, 20, 30, 50):
            variants[f"cold{k}"] = lambda k=k: solve(problem, None, 0, k)[0]
            same_shapes = previous is not None and previous[0].c.shape == cold_state.c.shape
            if k < 50 and same_shapes and previous[2].origin.shape == prepared.origin.shape:
                for lam in ("zero", "keep"):
                    variants[f"warm{k}_{lam}_tail"] = lambda k=k, lam=lam: solve(
                        problem, warm_state(previous[0], previous[2], prepared, lam), cfg.iterations - k)[0]
        for key, run in variants.items():
            with torch.no_grad():
                result = run()
            index, ok, _ = choice(result, problem)
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
        previous = (cold_state, None, prepared)
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
