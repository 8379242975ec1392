"""Where a verified proposer's decision time goes, and why its rows solve cold: `mmpc evaluate`
in this process with the driver's parts timed (the check, the proposal, the solves) and
WarmStarts.start wrapped to tally, per solve of a subset of the goals, the first reason that makes
each cold row cold.

    python docs/experiments/2026-11-29-proposer-warm/why_cold.py DRIVER SCENARIO SEEDS DURATION OUT
"""

import collections
import json
import sys
import time

import torch

import mmpc.drivers.verified as verified
from mmpc.cli.main import main
from mmpc.drivers.mpc_driver import MPCDriver
from mmpc.imitation.proposer_driver import ProposerDriver
from mmpc.mpc import MPC
from mmpc.warm import WarmStarts

TALLY = collections.Counter()
SECONDS = collections.Counter()
original_start = WarmStarts.start


def timed(owner, name, key):
    function = getattr(owner, name)

    def wrapper(*args, **kwargs):
        start = time.perf_counter()
        try:
            return function(*args, **kwargs)
        finally:
            SECONDS[key] += time.perf_counter() - start
    setattr(owner, name, wrapper)


def tallied_start(self, ids, ego, slots=None):
    round = original_start(self, ids, ego, slots)
    TALLY["solves"] += 1
    TALLY["rows"] += ids.shape[0]
    TALLY["warm rows"] += int((round.steps > 0).sum())
    kept = self._kept
    if kept is None or slots is None or not self.enabled:
        return round
    config = self.mpc.config
    match = ids[:, None] == kept.ids[None, :]
    rows = match.int().argmax(dim=1)
    steps = kept.steps[rows] + 1
    same = slots[:, :, None] == kept.slots[rows][:, None, :]
    new_goal = ~same.any(dim=2)
    reasons = [
        ("cold: new environment", ~match.any(dim=1)),
        ("cold: after a fallback", kept.fell_back[rows]),
        ("cold: feasible set decayed", kept.feasible_goals[rows] < config.warm_keep_share * kept.cold_feasible_goals[rows]),
        ("cold: every n-th", steps >= config.warm_cold_every),
        ("cold: a goal not solved last step", new_goal.any(dim=1)),
    ]
    left = torch.ones(ids.shape[0], dtype=torch.bool)
    for name, flag in reasons:
        TALLY[name] += int((flag & left).sum())
        left &= ~flag
    TALLY["goals new since the last step"] += int(new_goal.sum())
    TALLY["goals"] += int(new_goal.numel())
    return round


WarmStarts.start = tallied_start
timed(verified, "guarded_command", "check (guarded command)")
timed(ProposerDriver, "propose", "proposal (features, network)")
timed(ProposerDriver, "decide", "proposer decide")
timed(MPCDriver, "decide", "mpc decide")
timed(MPC, "build_problem", "build problem")
timed(MPC, "score", "solve (MPC.score)")
score = MPC.score


def counted_score(self, problem, *args, **kwargs):
    scored = score(self, problem, *args, **kwargs)
    SECONDS["of which compiling"] += scored.compile_ms / 1e3
    TALLY["goal-iterations"] += int(scored.result.iterations.sum())
    return scored


MPC.score = counted_score
driver, scenario, seeds, duration, out = sys.argv[1:6]
start = time.perf_counter()
code = main(["evaluate", "--driver", driver, "--scenarios", scenario, "--seeds", seeds, "--sim", "batched",
             "--duration", duration, "--lockstep", "64", "--out", out, "--threads", "1", "--compile", "on"])
report = {"wall_s": time.perf_counter() - start, "tally": dict(TALLY), "seconds": dict(SECONDS)}
print(json.dumps(report, indent=1))
(__import__("pathlib").Path(out) / "why_cold.json").write_text(json.dumps(report, indent=1))
sys.exit(code)
