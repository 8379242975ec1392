"""Held-out corpus of dense-traffic MPC problems, every goal labelled by IPOPT.

Two phases per scenario, each resumable:

1. record (cheap): the scenario's multi-modal MPC (driver ``mpc``, eager) drives highway-env
   episodes on seeds nobody tunes on (default cruise 27000-27009, high_speed 27100-27109, 40 s).
   A control step is *dense* when the MPC's problem holds at least ``--min-obstacles`` present
   obstacle slots; every ``--every``-th dense step of each episode is kept. A kept state stores the
   MPC's :class:`mmpc.ProblemBatch` row (ego, goals, obstacle predictions at the optimizer's
   instants, mask), the obstacles' states, their predictions at the NLP's knots, the seed and step.
2. label (IPOPT): every goal of every state is solved by the batch-NLP baseline's goal NLP
   (:class:`mmpc.drivers.nlp.TrajectoryNLP` in goal mode, built as
   :class:`mmpc.drivers.batch_nlp.BatchNLPSolver` builds it, cold-started, default
   :class:`mmpc.drivers.nlp.NLPConfig`): IPOPT's status, ``feasible`` by the baseline's own rule
   (largest recomputed violation <= ``feasibility_tolerance``), that violation, iterations and
   solve time. Labels are written every ``--chunk`` states; a re-run labels only what is left.

Output: ``OUT/<scenario>.pt`` (``torch.save`` of a dict of tensors and lists; read it with
:func:`load_corpus`) and ``OUT/manifest.json`` (seeds, counts, commit, command line, IPOPT
settings and time). The obstacles of the NLP are the MPC's own slots (same vehicles, same order)
predicted at the NLP's knots by :meth:`mmpc.MPC.predict`, as the baseline predicts them.

    python scripts/build_problem_corpus.py --out benchmarks/problem_corpus
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from mmpc.cli.arguments import seed_list
from mmpc.config import ConfigError, require_int, to_dict
from mmpc.drivers.base import Decision, Observation
from mmpc.drivers.batch_nlp import BatchNLPSolver, goal_subset
from mmpc.drivers.mpc_driver import MPCDriver
from mmpc.drivers.nlp import SOLVED_STATUSES, NLPConfig, TrajectoryNLP
from mmpc.files import atomic_write, atomic_write_text
from mmpc.highway.runner import Observer, run_lockstep
from mmpc.mpc import MPC
from mmpc.scenario import ScenarioConfig, build_mpc, load_scenario

#: Format tag of a corpus file.
FORMAT = "mmpc-problem-corpus/1"
#: Held-out seeds per shipped scenario (nobody tunes on these).
DEFAULT_SEEDS = {"cruise": tuple(range(27000, 27010)), "high_speed": tuple(range(27100, 27110))}
#: Tensors every corpus file holds, with their dtype (S states, G goals, M slots, N instants, K+1 knots).
TENSORS = {
    "seed": torch.long,  # (S,)
    "step": torch.long,  # (S,) control step of the episode
    "ego": torch.float32,  # (S, 6)
    "goals": torch.float32,  # (S, G, 2)
    "obstacles": torch.float32,  # (S, M, N, 2) at the optimizer's instants
    "obstacle_mask": torch.bool,  # (S, M)
    "obstacle_states": torch.float32,  # (S, M, 4) x, y, vx, vy of the slots
    "goal_index": torch.long,  # (G,) position of each goal in the MPC's goal set
    "nlp_times": torch.float64,  # (K+1,)
    "nlp_obstacles": torch.float64,  # (S, M, K+1, 2) at the NLP's knots
    "labelled": torch.bool,  # (S,)
    "ipopt_status": torch.int16,  # (S, G) index into status_names; -1 unlabelled
    "ipopt_solved": torch.bool,  # (S, G) status in SOLVED_STATUSES
    "ipopt_feasible": torch.bool,  # (S, G) violation <= feasibility_tolerance
    "ipopt_violation": torch.float64,  # (S, G) largest constraint violation; NaN unlabelled
    "ipopt_solve_ms": torch.float64,  # (S, G) wall time of the IPOPT call; NaN unlabelled
    "ipopt_iterations": torch.int32,  # (S, G); -1 unlabelled
}
#: The settings a corpus was recorded with; a re-run must ask for the same.
RECORDING_KEYS = ("scenario", "seeds", "duration", "min_obstacles", "every", "goals")


class CorpusError(ValueError):
    """A corpus file is missing, unreadable or inconsistent, or the requested corpus is empty."""


@dataclass(frozen=True)
class CorpusSpec:
    """What to record and label.

    Attributes:
        scenarios: shipped scenario names (or YAML paths) to drive.
        seeds: seeds per scenario (held out: nobody tunes on them).
        duration: episode length [s].
        min_obstacles: a state is dense when its problem holds at least this many present slots.
        every: keep every ``every``-th dense step of each episode.
        goals: label an evenly spaced subset of this many goals per state (``None``: all).
        min_states: refuse a scenario that yields fewer kept states.
        chunk: states labelled between two writes of the file.
        label_limit: label at most this many states in this run (``None``: all).
        label_budget_s: stop labelling after the chunk that passes this many seconds (``None``: no limit).
        out: output folder.
        nlp: transcription and IPOPT settings (the baseline's defaults).
    """

    scenarios: tuple[str, ...] = ("cruise", "high_speed")
    seeds: dict = field(default_factory=lambda: dict(DEFAULT_SEEDS))
    duration: float = 40.0
    min_obstacles: int = 4
    every: int = 10
    goals: Optional[int] = None
    min_states: int = 250
    chunk: int = 10
    label_limit: Optional[int] = None
    label_budget_s: Optional[float] = None
    out: Path = Path("benchmarks/problem_corpus")
    nlp: NLPConfig = field(default_factory=NLPConfig)

    def __post_init__(self) -> None:
        if not self.scenarios or len(set(self.scenarios)) != len(self.scenarios):
            raise ValueError(f"`scenarios` must be distinct and at least one; got {self.scenarios}")
        for name in self.scenarios:
            if not self.seeds.get(name):
                raise ValueError(f"no seeds for scenario {name!r}: give --seeds {name}=FIRST-LAST")
        extra = sorted(set(self.seeds) - set(self.scenarios))
        if extra:
            raise ValueError(f"--seeds names scenarios not in --scenarios {list(self.scenarios)}: {extra}")
        if not (isinstance(self.duration, float) and math.isfinite(self.duration) and self.duration > 0):
            raise ValueError(f"`duration` must be a finite number of seconds > 0; got {self.duration!r}")
        require_int("", low=0, min_obstacles=self.min_obstacles)
        require_int("", low=1, every=self.every, min_states=self.min_states, chunk=self.chunk)
        if self.goals is not None and (not isinstance(self.goals, int) or self.goals < 1):
            raise ValueError(f"`goals` must be an int >= 1 or None (all); got {self.goals!r}")
        if self.label_limit is not None and (not isinstance(self.label_limit, int) or self.label_limit < 0):
            raise ValueError(f"`label_limit` must be an int >= 0 or None; got {self.label_limit!r}")
        if self.label_budget_s is not None and not self.label_budget_s > 0:
            raise ValueError(f"`label_budget_s` must be > 0 s or None; got {self.label_budget_s!r}")

    def recording(self, name: str) -> dict:
        """The recording settings of scenario ``name`` as stored in its file."""
        return {"scenario": name, "seeds": list(self.seeds[name]), "duration": self.duration,
                "min_obstacles": self.min_obstacles, "every": self.every, "goals": self.goals}


# ----------------------------------------------------------------------------------- files


def corpus_path(out: Path, name: str) -> Path:
    """The file of scenario ``name`` in ``out``."""
    return Path(out) / f"{Path(name).stem}.pt"


def save_corpus(path: Path, corpus: dict) -> None:
    """Write ``corpus`` to ``path`` atomically (a reader sees the old file or the new one)."""
    atomic_write(Path(path), lambda handle: torch.save(corpus, handle))


def load_corpus(path: Path) -> dict:
    """Read and check a corpus file.

    Returns:
        The dict written by this script: :data:`TENSORS`, ``status_names`` (list of str),
        ``recording`` (:data:`RECORDING_KEYS`), ``nlp_config``, ``scenario_config``, ``episodes``,
        timings and commits.

    Raises:
        CorpusError: no such file, a file torch cannot read (truncated, corrupt, not a corpus),
            a missing field, or shapes, dtypes or labels that do not agree.
    """
    path = Path(path)
    if not path.is_file():
        raise CorpusError(f"corpus file {path} does not exist; build it with scripts/build_problem_corpus.py")
    try:
        corpus = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # noqa: BLE001 - any unpickling failure means the same to the user
        raise CorpusError(f"corpus file {path} is not readable (truncated or corrupt?): {type(error).__name__}: "
                          f"{error}; delete it and build it again") from error
    if not isinstance(corpus, dict) or corpus.get("format") != FORMAT:
        found = corpus.get("format") if isinstance(corpus, dict) else type(corpus).__name__
        raise CorpusError(f"{path} is not a problem corpus (format {FORMAT!r}); found {found!r}")
    check_corpus(corpus, where=str(path))
    return corpus


def check_corpus(corpus: dict, where: str = "corpus") -> None:
    """Raise :class:`CorpusError` unless every field is present and the shapes and labels agree."""
    missing = sorted(set(TENSORS) - set(corpus)) + [k for k in ("status_names", "recording", "nlp_config") if k not in corpus]
    if missing:
        raise CorpusError(f"{where}: missing fields {missing}")
    for name, dtype in TENSORS.items():
        value = corpus[name]
        if not isinstance(value, torch.Tensor) or value.dtype != dtype:
            got = value.dtype if isinstance(value, torch.Tensor) else type(value).__name__
            raise CorpusError(f"{where}: `{name}` must be a {dtype} tensor; got {got}")
    states, goals = corpus["goals"].shape[:2] if corpus["goals"].ndim == 3 else (-1, -1)
    if states < 1:
        raise CorpusError(f"{where}: holds no state (goals of shape {tuple(corpus['goals'].shape)})")
    slots, instants = corpus["obstacles"].shape[1:3] if corpus["obstacles"].ndim == 4 else (-1, -1)
    knots = corpus["nlp_times"].numel()
    expected = {
        "seed": (states,), "step": (states,), "ego": (states, 6), "goals": (states, goals, 2),
        "obstacles": (states, slots, instants, 2), "obstacle_mask": (states, slots), "obstacle_states": (states, slots, 4),
        "goal_index": (goals,), "nlp_times": (knots,), "nlp_obstacles": (states, slots, knots, 2), "labelled": (states,),
        **{name: (states, goals) for name in TENSORS if name.startswith("ipopt_")},
    }
    for name, shape in expected.items():
        if tuple(corpus[name].shape) != shape:
            raise CorpusError(f"{where}: `{name}` must have shape {shape}; got {tuple(corpus[name].shape)}")
    if not torch.isfinite(corpus["ego"]).all() or not torch.isfinite(corpus["goals"]).all():
        raise CorpusError(f"{where}: `ego` and `goals` must be finite")
    names = corpus["status_names"]
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise CorpusError(f"{where}: `status_names` must be a list of str")
    labelled = corpus["labelled"]
    status = corpus["ipopt_status"]
    if (status[labelled] < 0).any() or (status >= len(names)).any() or (status[~labelled] != -1).any():
        raise CorpusError(f"{where}: `ipopt_status` must index `status_names` on labelled states and be -1 elsewhere")
    violation = corpus["ipopt_violation"][labelled]
    if torch.isnan(violation).any() or torch.isnan(corpus["ipopt_solve_ms"][labelled]).any():
        raise CorpusError(f"{where}: a labelled state has no violation or solve time")
    tolerance = corpus["nlp_config"].get("feasibility_tolerance")
    if tolerance is None or (corpus["ipopt_feasible"][labelled] != (violation <= tolerance)).any():
        raise CorpusError(f"{where}: `ipopt_feasible` disagrees with `ipopt_violation` <= feasibility_tolerance={tolerance}")
    if set(corpus["recording"]) != set(RECORDING_KEYS):
        raise CorpusError(f"{where}: `recording` must hold {list(RECORDING_KEYS)}; got {sorted(corpus['recording'])}")


# ----------------------------------------------------------------------------------- record


class DenseStateRecorder(Observer):
    """Keeps every ``every``-th dense step of each episode (an :class:`mmpc.highway.Observer`).

    Args:
        mpc: the driving MPC (its slots are re-derived to store the obstacles' states).
        seeds: the run's seeds, by environment index.
        min_obstacles: a step is dense when the problem holds at least this many present slots.
        every: keep every ``every``-th dense step of an episode (its first dense step included).
        goals: the positions of the stored goals in the MPC's goal set, (G,) long.
    """

    def __init__(self, mpc: MPC, seeds: Sequence[int], min_obstacles: int, every: int, goals: Optional[torch.Tensor]) -> None:
        self.mpc = mpc
        self.seeds = list(seeds)
        self.min_obstacles = min_obstacles
        self.every = every
        self.goals = goals
        self.steps = [0] * len(self.seeds)
        self.dense = [0] * len(self.seeds)
        self.kept = [0] * len(self.seeds)
        self.rows: dict[str, list[torch.Tensor]] = {name: [] for name in ("seed", "step", "ego", "goals", "obstacles",
                                                                          "obstacle_mask", "obstacle_states")}

    def decided(self, observation: Observation, decision: Decision, active: Sequence[int]) -> None:
        problem = decision.plan.problem
        dense = problem.obstacle_mask.sum(dim=1) >= self.min_obstacles  # (E,)
        keep = []
        for row, index in enumerate(active):
            if bool(dense[row]):
                if self.dense[index] % self.every == 0:
                    keep.append(row)
                self.dense[index] += 1
        if keep:
            rows = torch.tensor(keep, dtype=torch.long)
            states = self._slot_states(observation, problem)[rows]
            goals = problem.goals[rows] if self.goals is None else problem.goals[rows][:, self.goals]
            self.rows["seed"].append(torch.tensor([self.seeds[active[r]] for r in keep], dtype=torch.long))
            self.rows["step"].append(torch.tensor([self.steps[active[r]] for r in keep], dtype=torch.long))
            for name, value in (("ego", problem.ego[rows]), ("goals", goals), ("obstacles", problem.obstacles[rows]),
                                ("obstacle_mask", problem.obstacle_mask[rows]), ("obstacle_states", states)):
                self.rows[name].append(value.detach().clone())
            for r in keep:
                self.kept[active[r]] += 1
        for index in active:
            self.steps[index] += 1

    def _slot_states(self, observation: Observation, problem) -> torch.Tensor:
        """(E, M, 4) states of the MPC's obstacle slots (as :meth:`mmpc.MPC.build_problem` picks them),
        checked against the problem's predictions."""
        dtype = self.mpc.optimizer.dtype
        vehicles = observation.vehicles.to(dtype)
        if observation.vehicle_mask is not None:
            vehicles = torch.where(observation.vehicle_mask[..., None], vehicles, torch.zeros_like(vehicles))
        states, mask = self.mpc.nearest_obstacles(observation.ego.to(dtype), vehicles, observation.vehicle_mask)
        predicted = self.mpc.predict(states, self.mpc.optimizer.times)
        gap = torch.where(mask[..., None, None], (predicted - problem.obstacles).abs(), torch.zeros_like(predicted))
        if not torch.equal(mask, problem.obstacle_mask) or float(gap.max()) > 1e-4:
            raise RuntimeError("re-derived obstacle slots differ from the MPC's problem (mmpc.MPC.build_problem changed?)")
        return states

    def tensors(self) -> dict[str, torch.Tensor]:
        """The kept states, concatenated (empty dict when none was kept)."""
        if not self.rows["seed"]:
            return {}
        return {name: torch.cat(values) for name, values in self.rows.items()}


def record(name: str, scenario: ScenarioConfig, spec: CorpusSpec, nlp_times: np.ndarray) -> dict:
    """Drive ``scenario`` (``name`` in ``spec``) on its seeds and return the unlabelled corpus dict.

    Raises:
        CorpusError: no dense state, or fewer than ``spec.min_states``.
    """
    seeds = list(spec.seeds[name])
    scenario = scenario.replace(duration=spec.duration)
    mpc = build_mpc(scenario, compile=False)
    probe = mpc.build_problem(torch.zeros(1, 6, dtype=mpc.optimizer.dtype), torch.zeros(1, 0, 4, dtype=mpc.optimizer.dtype))
    num_goals = probe.goals.shape[1]
    subset = None if spec.goals is None else goal_subset(num_goals, spec.goals)
    recorder = DenseStateRecorder(mpc, seeds, spec.min_obstacles, spec.every, subset)
    start = time.perf_counter()
    results = run_lockstep(scenario, seeds, driver=MPCDriver(mpc, period=scenario.period), observers=[recorder])
    wall = time.perf_counter() - start
    rows = recorder.tensors()
    dense = sum(recorder.dense)
    if not rows:
        raise CorpusError(f"scenario {name}: no dense state (>= {spec.min_obstacles} present obstacle slots) in "
                          f"{sum(recorder.steps)} steps of seeds {seeds}: lower --min-obstacles or add seeds")
    count = rows["seed"].numel()
    if count < spec.min_states:
        enough = max(1, dense // spec.min_states)
        raise CorpusError(f"scenario {name}: {count} states kept (every {spec.every}th of {dense} dense steps), fewer "
                          f"than --min-states {spec.min_states}: use --every {enough} or more seeds")
    states, goals = rows["goals"].shape[:2]
    knot_times = torch.as_tensor(nlp_times, dtype=torch.float64)
    corpus = {
        "format": FORMAT,
        **rows,
        "goal_index": subset if subset is not None else torch.arange(num_goals),
        "nlp_times": knot_times,
        "nlp_obstacles": mpc.predict(rows["obstacle_states"].to(torch.float64), knot_times),
        "labelled": torch.zeros(states, dtype=torch.bool),
        "ipopt_status": torch.full((states, goals), -1, dtype=torch.int16),
        "ipopt_solved": torch.zeros(states, goals, dtype=torch.bool),
        "ipopt_feasible": torch.zeros(states, goals, dtype=torch.bool),
        "ipopt_violation": torch.full((states, goals), float("nan"), dtype=torch.float64),
        "ipopt_solve_ms": torch.full((states, goals), float("nan"), dtype=torch.float64),
        "ipopt_iterations": torch.full((states, goals), -1, dtype=torch.int32),
        "status_names": [],
        "recording": spec.recording(name),
        "nlp_config": dataclasses.asdict(spec.nlp),
        "scenario_config": to_dict(scenario, complete=True),
        "episodes": [{"seed": seed, "steps": recorder.steps[i], "dense_steps": recorder.dense[i], "kept": recorder.kept[i],
                      "collisions": int(result.metrics["collisions"])} for i, (seed, result) in enumerate(zip(seeds, results))],
        "record_wall_s": wall,
        "label_wall_s": 0.0,
        "recorded_at": git_state(),
    }
    check_corpus(corpus, where=f"scenario {name}")
    return corpus


# ----------------------------------------------------------------------------------- label


def make_nlp(scenario: ScenarioConfig, config: NLPConfig) -> TrajectoryNLP:
    """The batch-NLP baseline's goal NLP for ``scenario`` (built as :class:`BatchNLPSolver` builds it)."""
    return BatchNLPSolver(build_mpc(scenario, compile=False), workers=0, config=config).local


def label(path: Path, corpus: dict, nlp: TrajectoryNLP, spec: CorpusSpec) -> int:
    """Label the unlabelled states of ``corpus`` with IPOPT, writing ``path`` after every chunk.

    Returns:
        The number of states labelled in this call.
    """
    todo = (~corpus["labelled"]).nonzero().flatten().tolist()
    if spec.label_limit is not None:
        todo = todo[: spec.label_limit]
    names: list[str] = corpus["status_names"]
    start = time.perf_counter()
    done = 0
    for first in range(0, len(todo), spec.chunk):
        chunk_start = time.perf_counter()
        for s in todo[first:first + spec.chunk]:
            ego = corpus["ego"][s].to(torch.float64).numpy()
            obstacles = corpus["nlp_obstacles"][s].numpy()
            mask = corpus["obstacle_mask"][s].numpy()
            for g in range(corpus["goals"].shape[1]):
                solution = nlp.solve(ego, obstacles, mask, corpus["goals"][s, g].to(torch.float64).numpy())
                if solution.status not in names:
                    names.append(solution.status)
                corpus["ipopt_status"][s, g] = names.index(solution.status)
                corpus["ipopt_solved"][s, g] = solution.status in SOLVED_STATUSES
                corpus["ipopt_feasible"][s, g] = bool(solution.feasible)
                corpus["ipopt_violation"][s, g] = solution.violation
                corpus["ipopt_solve_ms"][s, g] = solution.solve_ms
                corpus["ipopt_iterations"][s, g] = solution.iterations
            corpus["labelled"][s] = True
            done += 1
        corpus["label_wall_s"] = float(corpus["label_wall_s"]) + time.perf_counter() - chunk_start
        corpus["labelled_at"] = git_state()
        save_corpus(path, corpus)
        labelled = int(corpus["labelled"].sum())
        print(f"  {path.name}: {labelled}/{corpus['labelled'].numel()} states labelled "
              f"({time.perf_counter() - start:.0f} s this run)", file=sys.stderr, flush=True)
        if spec.label_budget_s is not None and time.perf_counter() - start > spec.label_budget_s:
            print(f"  {path.name}: label budget of {spec.label_budget_s:.0f} s spent; run again to go on", file=sys.stderr)
            break
    return done


# ----------------------------------------------------------------------------------- manifest


def git_state() -> dict:
    """``{"commit": short HEAD, "dirty": modified tracked paths under mmpc/ and configs/}`` of this checkout."""
    root = Path(__file__).resolve().parents[1]
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True,
                                check=True).stdout.strip()
        status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", "mmpc", "configs"], cwd=root,
                                capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return {"commit": "unknown", "dirty": []}
    return {"commit": commit, "dirty": sorted(line[3:] for line in status.splitlines() if line.strip())}


def summary(path: Path, corpus: dict) -> dict:
    """The manifest entry of one corpus file."""
    labelled = corpus["labelled"]
    names = corpus["status_names"]
    codes = corpus["ipopt_status"][labelled]
    return {
        "file": path.name,
        "bytes": path.stat().st_size,
        "sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
        **corpus["recording"],
        "states": int(labelled.numel()),
        "goals_per_state": int(corpus["goals"].shape[1]),
        "obstacle_slots": int(corpus["obstacles"].shape[1]),
        "goals_total": int(corpus["goals"].shape[0] * corpus["goals"].shape[1]),
        "labelled_states": int(labelled.sum()),
        "labelled_goals": int(codes.numel()),
        "ipopt_feasible": int(corpus["ipopt_feasible"][labelled].sum()),
        "ipopt_solved": int(corpus["ipopt_solved"][labelled].sum()),
        "ipopt_status_counts": {names[c]: int((codes == c).sum()) for c in range(len(names))},
        "ipopt_total_s": float(corpus["ipopt_solve_ms"][labelled].sum()) / 1e3,
        "record_wall_s": round(float(corpus["record_wall_s"]), 1),
        "label_wall_s": round(float(corpus["label_wall_s"]), 1),
        "recorded_at": corpus.get("recorded_at"),
        "labelled_at": corpus.get("labelled_at"),
        "episodes": corpus["episodes"],
    }


def write_manifest(out: Path, spec: CorpusSpec, argv: Sequence[str]) -> dict:
    """Write ``out/manifest.json`` from the files of ``spec.scenarios`` (those present)."""
    entries = {}
    for name in spec.scenarios:
        path = corpus_path(out, name)
        if path.is_file():
            entries[Path(name).stem] = summary(path, load_corpus(path))
    manifest = {
        "format": FORMAT,
        "what": "dense-traffic states of the scenario MPC in highway-env (held-out seeds), every goal labelled by the "
                "batch-NLP baseline's IPOPT goal NLP; read with scripts/build_problem_corpus.py:load_corpus",
        "written_at": git_state(),  # this manifest; the data's commits are each scenario's recorded_at / labelled_at
        "command": "python scripts/build_problem_corpus.py " + " ".join(shlex.quote(a) for a in argv),
        "nlp_config": dataclasses.asdict(spec.nlp),
        "ipopt_options": {"max_iter": spec.nlp.max_iter, "tol": spec.nlp.tol, "max_cpu_time": spec.nlp.max_cpu_time,
                          "print_level": 0, "initial_guess": "cold: straight line to the goal (TrajectoryNLP.initial_guess)"},
        "solved_statuses": list(SOLVED_STATUSES),
        "scenarios": entries,
        "total_states": sum(e["states"] for e in entries.values()),
        "total_labelled_states": sum(e["labelled_states"] for e in entries.values()),
        "total_labelled_goals": sum(e["labelled_goals"] for e in entries.values()),
        "total_ipopt_s": round(sum(e["ipopt_total_s"] for e in entries.values()), 1),
    }
    atomic_write_text(Path(out) / "manifest.json", json.dumps(manifest, indent=1) + "\n")
    return manifest


# ----------------------------------------------------------------------------------- main


def build(spec: CorpusSpec, argv: Sequence[str]) -> dict:
    """Record what is missing, label what is unlabelled, write the manifest; returns it."""
    scenarios = [load_scenario(name) for name in spec.scenarios]  # unknown names fail before any work
    spec.out.mkdir(parents=True, exist_ok=True)
    for name, scenario in zip(spec.scenarios, scenarios):
        path = corpus_path(spec.out, name)
        nlp = None
        if path.is_file():
            corpus = load_corpus(path)
            wanted = spec.recording(name)
            if corpus["recording"] != wanted or corpus["nlp_config"] != dataclasses.asdict(spec.nlp):
                raise CorpusError(f"{path} was built with other settings ({corpus['recording']}, {corpus['nlp_config']}) "
                                  f"than asked for ({wanted}, {dataclasses.asdict(spec.nlp)}): use another --out or "
                                  f"delete the file")
            print(f"{name}: {path} holds {corpus['labelled'].numel()} states, {int(corpus['labelled'].sum())} labelled",
                  file=sys.stderr)
        else:
            nlp = make_nlp(scenario, spec.nlp)
            print(f"{name}: recording seeds {spec.seeds[name][0]}..{spec.seeds[name][-1]} "
                  f"({len(spec.seeds[name])} episodes of {spec.duration:g} s)", file=sys.stderr, flush=True)
            corpus = record(name, scenario, spec, nlp.times)
            save_corpus(path, corpus)
            print(f"{name}: {corpus['labelled'].numel()} states x {corpus['goals'].shape[1]} goals recorded in "
                  f"{corpus['record_wall_s']:.0f} s -> {path}", file=sys.stderr, flush=True)
        if not bool(corpus["labelled"].all()):
            nlp = nlp or make_nlp(scenario, spec.nlp)
            if not np.allclose(nlp.times, corpus["nlp_times"].numpy()):
                raise CorpusError(f"{path}: the NLP's knots differ from the stored ones (horizon or intervals changed)")
            label(path, corpus, nlp, spec)
    return write_manifest(spec.out, spec, argv)


def scenario_seeds(text: str) -> tuple[str, tuple[int, ...]]:
    """``"cruise=27000-27009"`` -> ("cruise", seeds)."""
    name, sep, seeds = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"expected SCENARIO=SEEDS such as cruise=27000-27009; got {text!r}")
    return name, seed_list(seeds)


def parse_args(argv: Sequence[str]) -> CorpusSpec:
    defaults = CorpusSpec()
    parser = argparse.ArgumentParser(prog="build_problem_corpus.py", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenarios", default=",".join(defaults.scenarios),
                        help="comma-separated shipped scenarios (default: %(default)s)")
    parser.add_argument("--seeds", type=scenario_seeds, action="append", default=[], metavar="SCENARIO=SEEDS",
                        help="held-out seeds of a scenario, e.g. cruise=27000-27009 (repeatable; default: "
                             + ", ".join(f"{k}={v[0]}-{v[-1]}" for k, v in DEFAULT_SEEDS.items()) + ")")
    parser.add_argument("--duration", type=float, default=defaults.duration, help="episode length [s] (default: %(default)s)")
    parser.add_argument("--min-obstacles", type=int, default=defaults.min_obstacles,
                        help="a state is dense with at least this many present obstacle slots (default: %(default)s)")
    parser.add_argument("--every", type=int, default=defaults.every,
                        help="keep every N-th dense step of each episode (default: %(default)s)")
    parser.add_argument("--goals", type=int, default=None,
                        help="label an evenly spaced subset of this many goals per state (default: all)")
    parser.add_argument("--min-states", type=int, default=defaults.min_states,
                        help="refuse a scenario with fewer kept states (default: %(default)s)")
    parser.add_argument("--chunk", type=int, default=defaults.chunk, help="states labelled per write (default: %(default)s)")
    parser.add_argument("--label-limit", type=int, default=None, help="label at most this many states in this run")
    parser.add_argument("--label-budget-s", type=float, default=None, help="stop labelling after this many seconds")
    parser.add_argument("--nlp-max-iter", type=int, default=defaults.nlp.max_iter, help="IPOPT iteration limit (default: %(default)s)")
    parser.add_argument("--out", type=Path, default=defaults.out, help="output folder (default: %(default)s)")
    args = parser.parse_args(argv)
    scenarios = tuple(s for s in args.scenarios.split(",") if s)
    given = dict(args.seeds)
    seeds = {name: given.get(name, DEFAULT_SEEDS.get(Path(name).stem)) for name in scenarios}
    seeds.update(given)
    return CorpusSpec(
        scenarios=scenarios, seeds={k: v for k, v in seeds.items() if v}, duration=args.duration,
        min_obstacles=args.min_obstacles, every=args.every, goals=args.goals, min_states=args.min_states,
        chunk=args.chunk, label_limit=args.label_limit, label_budget_s=args.label_budget_s, out=args.out,
        nlp=dataclasses.replace(defaults.nlp, max_iter=args.nlp_max_iter),
    )


def main(argv: Optional[Sequence[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    torch.set_num_threads(1)
    try:
        spec = parse_args(argv)
        start = time.perf_counter()
        manifest = build(spec, argv)
    except (CorpusError, ConfigError, FileNotFoundError, ValueError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    for name, entry in manifest["scenarios"].items():
        print(f"{name}: {entry['states']} states x {entry['goals_per_state']} goals, {entry['labelled_states']} labelled; "
              f"IPOPT feasible {entry['ipopt_feasible']} / {entry['labelled_goals']}, IPOPT time {entry['ipopt_total_s']:.0f} s")
    print(f"wrote {spec.out / 'manifest.json'} ({time.perf_counter() - start:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
