"""The ``mmpc`` command: ``solve``, ``drive``, ``evaluate``, ``config show``, ``rl ...`` and ``imitate ...``.

Each verb's module adds its subcommand and keeps its heavy imports (CasADi, Ray,
stable-baselines3, Minari) inside the command function. A verb whose interrupted run a re-run
resumes says what it keeps with ``set_defaults(kept="... {out} ...")`` (formatted with its
arguments): an interrupt (Ctrl-C) prints that and the resume hint, without a traceback.

Refusals are one line on stderr and exit status 2, in one place (:func:`main`): the arguments
every verb shares are checked before any work (:func:`refused`, the run's device), and an error
that refuses what the user gave (:func:`user_errors`: a config, a path, an output folder that
cannot be written or is in use) ends the command with its message. Any other exception is a bug
and keeps its traceback.
"""

from __future__ import annotations

import argparse
import logging
import sys
from typing import Optional, Sequence

from mmpc.cli import config, drive, evaluate, solve
from mmpc.imitation import cli as imitation_cli
from mmpc.rl import cli as rl_cli


#: The exit status of an interrupted command: 128 + SIGINT, what a shell reports for Ctrl-C.
INTERRUPTED = 130


def verb(args: argparse.Namespace) -> str:
    """The command of ``args`` as typed: ``drive``, ``rl train``."""
    sub = getattr(args, f"{args.command}_command", None)
    return args.command if sub is None else f"{args.command} {sub}"


def interrupted(args: argparse.Namespace) -> str:
    """The line telling that the command of ``args`` was interrupted, with what it kept (its
    ``kept`` default) and how to resume."""
    kept = getattr(args, "kept", None)
    if kept is None:
        return f"mmpc {verb(args)}: interrupted"
    return f"mmpc {verb(args)}: interrupted; {kept.format(**vars(args))}; re-run the same command to resume"


def user_errors() -> tuple[type[Exception], ...]:
    """The exceptions that refuse what the user gave, which :func:`main` prints as one line: a bad
    config, ``--set`` or ``--sim`` (:class:`mmpc.config.ConfigError`), an output folder another
    run holds or an earlier run's damaged files (:class:`mmpc.files.OutputFolderError`,
    :class:`mmpc.evaluate.EvaluationFolderError`, :class:`mmpc.imitation.dataset.DemonstrationsError`),
    and the operating system's refusals (``OSError``: an ``--out`` that cannot be created or
    written, a missing input file such as a config name that is not shipped, whose
    ``FileNotFoundError`` names it and lists the shipped ones)."""
    from mmpc.config import ConfigError
    from mmpc.evaluate.store import EvaluationFolderError
    from mmpc.files import OutputFolderError
    from mmpc.imitation.dataset import DemonstrationsError

    return ConfigError, EvaluationFolderError, OutputFolderError, DemonstrationsError, OSError


def one_line(error: BaseException) -> str:
    """``error``'s message on one line (an ``OSError`` with its kind: ``PermissionError: ...``); of a
    message of several lines (torch's) the first."""
    lines = str(error).strip().splitlines() or [type(error).__name__]
    return f"{type(error).__name__}: {lines[0]}" if isinstance(error, OSError) else lines[0]


def refused(args: argparse.Namespace) -> Optional[str]:
    """Why the arguments every verb shares cannot run (``None``: they can), before any work."""
    from mmpc.cli.arguments import THREADS_PER_CPU, max_threads

    if getattr(args, "goals", 1) < 1:
        return "--goals must be >= 1"
    if getattr(args, "workers", None) is not None and args.workers < 1:
        return "--workers must be >= 1"
    if getattr(args, "threads", None) is not None and not 1 <= args.threads <= max_threads():
        return f"--threads must be in [1, {max_threads()}] ({THREADS_PER_CPU} per CPU this process may use); got {args.threads}"
    if getattr(args, "duration", None) is not None and not args.duration > 0:
        return "--duration must be > 0 s"
    for name in ("scenario", "scenarios"):
        names = [n for n in str(getattr(args, name, None) or "").split(",") if n]
        repeated = sorted({n for n in names if names.count(n) > 1})
        if repeated:
            return f"--{name} names {', '.join(repeated)} more than once; each scenario runs once (its name keys the results)"
    return None


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mmpc", description="Multi-modal MPC by batch non-holonomic trajectory optimization.")
    parser.add_argument("--log-level", default="WARNING", help="logging level of the library (default WARNING)")
    sub = parser.add_subparsers(dest="command", required=True)
    solve.add_subcommand(sub)
    drive.add_subcommand(sub)
    evaluate.add_subcommand(sub)
    config.add_subcommand(sub)
    rl_cli.add_subcommands(sub)
    imitation_cli.add_subcommands(sub)
    return parser


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(levelname)s %(name)s: %(message)s")
    problem = refused(args)
    if problem is not None:
        print(f"mmpc: error: {problem}", file=sys.stderr)
        return 2
    from mmpc.cli.arguments import apply_device
    from mmpc.device import DEVICE_ENV

    if hasattr(args, "device"):  # the verbs that compute on it: --device, or MMPC_DEVICE inherited
        try:
            apply_device(args.device)
        except ValueError as error:
            print(f"mmpc: error: {'--device' if args.device is not None else DEVICE_ENV}: {one_line(error)}", file=sys.stderr)
            return 2
    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        print(interrupted(args), file=sys.stderr)
        return INTERRUPTED
    except Exception as error:
        if not isinstance(error, user_errors()):
            raise  # a bug: its traceback
        print(f"mmpc {verb(args)}: error: {one_line(error)}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
