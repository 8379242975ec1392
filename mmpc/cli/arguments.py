"""Argument types and groups shared by every ``mmpc`` verb (``mmpc.rl`` and ``mmpc.imitation``
included), so that seeds, configs, overrides, compiling and output folders read the same everywhere."""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path
from typing import Any, Optional

import yaml

from mmpc.device import DEVICE_ENV, resolve_device
from mmpc.files import TEMPORARY_PREFIX
from mmpc.solver.execution import COMPILE_ENV

#: ``--compile`` choices -> the value of :data:`mmpc.solver.execution.COMPILE_ENV` they set (``None``: leave it).
COMPILE_CHOICES = {"auto": None, "on": "1", "off": "0"}


def int_list(text: str) -> tuple[int, ...]:
    try:
        values = tuple(int(v) for v in text.split(",") if v)
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers; got {text!r}") from error
    if not values or min(values) < 0:
        raise argparse.ArgumentTypeError(f"expected non-negative integers; got {text!r}")
    return values


#: The most seeds :func:`seed_list` reads (repeats counted): a million episodes is more than any
#: evaluation runs, and ``0-999999999`` would otherwise build a 36 GB list while parsing.
MAX_SEEDS = 1_000_000


def seed_list(text: str) -> tuple[int, ...]:
    """``"0-19"``, ``"0,3,7"`` or a mix (``"0-4,9"``) -> seeds, repeats dropped; at most
    :data:`MAX_SEEDS`, counted from the ranges before any is built."""
    ranges: list[range] = []
    try:
        for part in (p for p in text.split(",") if p):
            low, _, high = part.partition("-")
            ranges.append(range(int(low), int(high or low) + 1))
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"expected seeds like 0-19 or 0,3,7; got {text!r}") from error
    if not ranges or any(len(r) == 0 or r.start < 0 for r in ranges):
        raise argparse.ArgumentTypeError(f"expected non-negative seeds like 0-19 or 0,3,7 (ranges low-high with low <= high); "
                                         f"got {text!r}")
    count = sum(len(r) for r in ranges)
    if count > MAX_SEEDS:
        raise argparse.ArgumentTypeError(f"{text!r} names {count:,} seeds; at most {MAX_SEEDS:,} are allowed")
    return tuple(dict.fromkeys(seed for r in ranges for seed in r))


def override(text: str) -> tuple[str, object]:
    """``"traffic.lane_changes=true"`` -> ("traffic.lane_changes", True) (the value is YAML)."""
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE such as traffic.lane_changes=true; got {text!r}")
    return key, yaml.safe_load(value)


def add_config(parser: argparse.ArgumentParser, what: str, default: Optional[str] = None) -> None:
    """``--config NAME_OR_PATH`` and ``--set KEY=VALUE`` (repeatable) for the verb's config
    (:func:`mmpc.config.load_config`; ``args.config``, ``args.set``)."""
    parser.add_argument("--config", default=default, metavar="NAME_OR_PATH",
                        help=f"{what}: a shipped name or a YAML path (default: "
                             f"{default or 'the defaults, see `mmpc config show`'})")
    add_set(parser, what)


def add_set(parser: argparse.ArgumentParser, what: str, example: str = "") -> None:
    """``--set KEY=VALUE`` (dotted key, YAML value, repeatable) into ``args.set``."""
    parser.add_argument("--set", type=override, action="append", default=[], metavar="KEY=VALUE",
                        help=f"override a value of the {what} (dotted key, YAML value; repeatable){example}")


def add_sim(parser: argparse.ArgumentParser) -> None:
    """``--sim highway-env|batched``: the world the scenarios run in (``args.sim``, see :func:`scenario_overrides`)."""
    from mmpc.scenario import SIMULATORS

    parser.add_argument("--sim", choices=SIMULATORS, default=None,
                        help="the world: highway-env (the reference, with video) or batched (mmpc.sim: all episodes "
                             "stepped at once in torch, IDM traffic only); default: the scenario's (highway-env)")


def scenario_overrides(args: argparse.Namespace, pairs: Optional[list[tuple[str, Any]]] = None) -> dict[str, Any]:
    """The scenario overrides of a verb: its ``--set`` pairs (or ``pairs``), then ``--sim``."""
    overrides = dict(args.set if pairs is None else pairs)
    if getattr(args, "sim", None) is not None:
        overrides["sim"] = args.sim
    return overrides


def add_compile(parser: argparse.ArgumentParser) -> None:
    """``--compile auto|on|off`` for verbs that build an MPC (:func:`apply_compile`)."""
    parser.add_argument("--compile", choices=tuple(COMPILE_CHOICES), default="auto",
                        help=f"compile the batch optimizer: auto (default, where a kernel compiler is found: each call "
                             f"layout after ~20 s of eager solves of it, unless {COMPILE_ENV} is set), on (at once), off (eager)")


def add_device(parser: argparse.ArgumentParser) -> None:
    """``--device auto|cpu|cuda|cuda:N`` for verbs that build an MPC or the batched simulator
    (:func:`apply_device`, called by :func:`mmpc.cli.main.main`)."""
    parser.add_argument("--device", default=None, metavar="auto|cpu|cuda|cuda:N",
                        help=f"where the batched simulator and the MPC compute: cpu (default), cuda, cuda:N, or auto "
                             f"(the GPU when there is one); sets {DEVICE_ENV}, which worker processes inherit")


def apply_device(choice: Optional[str]) -> None:
    """Set :data:`mmpc.device.DEVICE_ENV` for ``--device`` (``None`` leaves it) and check that the
    run's setting, given or inherited from the environment, names a device this machine has
    (``ValueError`` saying what came), before any work: a worker would otherwise fail on it."""
    if choice is None:
        resolve_device(os.environ.get(DEVICE_ENV, ""))
    else:
        resolve_device(choice)  # before it is set: a refused value leaves the process's setting as it was
        os.environ[DEVICE_ENV] = choice


#: ``--threads`` at most this many per CPU the process may use: more only oversubscribes the
#: cores (and OpenMP far above fails: 1,000 threads hung a 2-core machine, 20,000 broke libgomp).
THREADS_PER_CPU = 4


def max_threads() -> int:
    """The largest ``--threads`` accepted: :data:`THREADS_PER_CPU` x the CPUs this process may run on."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return THREADS_PER_CPU * cpus


def apply_compile(choice: str) -> None:
    """Set :data:`mmpc.solver.execution.COMPILE_ENV` for ``--compile on|off`` (``auto`` leaves it), so
    that every MPC this process and its workers build (:func:`mmpc.scenario.build_mpc`) follows it."""
    value = COMPILE_CHOICES[choice]
    if value is not None:
        os.environ[COMPILE_ENV] = value


def compile_at_once() -> None:
    """For benchmarks: every call layout compiled at its first call (:data:`COMPILE_ENV` = 1 where
    a kernel compiler is found, else 0) unless the environment already says, so that no timing
    includes the eager solves ``compile="auto"`` runs before it compiles a layout."""
    from mmpc.solver.execution import kernel_compiler_found

    if not os.environ.get(COMPILE_ENV, "").strip():
        os.environ[COMPILE_ENV] = "1" if kernel_compiler_found(on_cpu=True) else "0"


def split_overrides(pairs: list[tuple[str, Any]], section: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """``--set`` pairs -> (those for the verb's config, those under ``section.`` with the prefix
    removed), e.g. DAgger's ``--set train.epochs=5 --set scenario.lanes=4``."""
    prefix = f"{section}."
    own = {key: value for key, value in pairs if not key.startswith(prefix)}
    routed = {key.removeprefix(prefix): value for key, value in pairs if key.startswith(prefix)}
    return own, routed


def unwritable(out: Path) -> Optional[str]:
    """Why ``out`` cannot take outputs (created, then a probe file written and removed); ``None`` if it can."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=out, prefix=TEMPORARY_PREFIX):
            pass
    except OSError as error:
        return f"{type(error).__name__}: {error}"
    return None



#: What each of mmpc's own drivers takes after ``NAME:`` in a spec (``[...]``: optional), for
#: :func:`driver_help`; a driver registered by another package is listed by its name alone.
DRIVER_ARGUMENTS = {
    "batch-nlp": "[:B] (B goals, default 11)",
    "bc": ":RUN/policy.pt",
    "proposer": ":RUN/proposer.pt or :NAME (shipped)",
    "sb3": ":RUN/model.zip or :NAME (shipped)",
    "safe-random": "[:RL_CONFIG] (random goals behind the safety layer)",
    "safe-expert": "[:RL_CONFIG] (the expert behind the safety layer)",
    "verified": ":DRIVER (any other spec behind the legal-safety check, e.g. verified:mpc)",
}


def driver_help() -> str:
    """Every driver spec form, from the registry's names (:func:`mmpc.drivers.registry.driver_names`:
    the entry points and the drivers registered in this process) and :data:`DRIVER_ARGUMENTS`."""
    from mmpc.drivers.registry import driver_names

    return ", ".join(f"{name}{DRIVER_ARGUMENTS.get(name, '')}" for name in driver_names())


def driver_specs(values: list[str]) -> tuple[str, ...]:
    """``--driver mpc,frenet --driver bc:run/policy.pt`` -> distinct specs in order."""
    return tuple(dict.fromkeys(spec.strip() for value in values for spec in value.split(",") if spec.strip()))
