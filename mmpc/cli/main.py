"""The ``mmpc`` command: ``solve``, ``drive``, ``evaluate``, ``config show``, ``rl ...`` and ``imitate ...``.

Each verb's module adds its subcommand and keeps its heavy imports (CasADi, Ray,
stable-baselines3, Minari) inside the command function. A verb whose interrupted run a re-run
resumes says what it keeps with ``set_defaults(kept="... {out} ...")`` (formatted with its
arguments): an interrupt (Ctrl-C) prints that and the resume hint, without a traceback.
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


def interrupted(args: argparse.Namespace) -> str:
    """The line telling that the command of ``args`` was interrupted, with what it kept (its
    ``kept`` default) and how to resume."""
    sub = getattr(args, f"{args.command}_command", None)
    verb = args.command if sub is None else f"{args.command} {sub}"
    kept = getattr(args, "kept", None)
    if kept is None:
        return f"mmpc {verb}: interrupted"
    return f"mmpc {verb}: interrupted; {kept.format(**vars(args))}; re-run the same command to resume"


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
    if getattr(args, "goals", 1) < 1:
        print("mmpc: error: --goals must be >= 1", file=sys.stderr)
        return 2
    for name in ("workers", "threads"):
        if getattr(args, name, None) is not None and getattr(args, name) < 1:
            print(f"mmpc: error: --{name} must be >= 1", file=sys.stderr)
            return 2
    if getattr(args, "duration", None) is not None and not args.duration > 0:
        print("mmpc: error: --duration must be > 0 s", file=sys.stderr)
        return 2
    from mmpc.cli.arguments import apply_device
    from mmpc.config import ConfigError

    try:
        apply_device(getattr(args, "device", None))
    except ValueError as error:
        print(f"mmpc: error: --device: {error}", file=sys.stderr)
        return 2
    try:
        return int(args.func(args))
    except ConfigError as error:  # a bad config, --set or --sim: the message says what came and what was expected
        print(f"mmpc {args.command}: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(interrupted(args), file=sys.stderr)
        return INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
