"""``mmpc config show KIND [NAME_OR_PATH] [--set KEY=VALUE]``: a config as YAML, every setting
written out: the defaults, a shipped config, a file, with overrides (what a verb would run with)."""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import Optional

import yaml

from mmpc.cli.arguments import add_set

#: Config kinds -> (module, class).
KINDS = {
    "scenario": ("mmpc.scenario", "ScenarioConfig"),
    "optimizer": ("mmpc.solver.config", "OptimizerConfig"),
    "mpc": ("mmpc.mpc", "MPCConfig"),
    "rl": ("mmpc.rl.config", "RLConfig"),
    "bc": ("mmpc.imitation.bc", "TrainConfig"),
    "dagger": ("mmpc.imitation.dagger", "DaggerConfig"),
    "proposer": ("mmpc.imitation.proposer_dagger", "ProposerDaggerConfig"),
}


def config_class(kind: str) -> type:
    """The config class of a :data:`KINDS` name."""
    module, name = KINDS[kind]
    return getattr(importlib.import_module(module), name)


def run(args: argparse.Namespace) -> int:
    from mmpc.config import load_config, shipped_names, to_dict

    cls = config_class(args.kind)
    try:
        config = load_config(cls, args.name, dict(args.set))
    except (FileNotFoundError, ValueError) as error:
        print(f"mmpc config show: error: {error}", file=sys.stderr)
        return 2
    source = args.name or "defaults"
    shipped = shipped_names(cls)
    needs = {name: missing_data(load_config(cls, name)) for name in shipped} if hasattr(cls, "missing_data") else {}
    listed = [name + (" (needs data)" if needs.get(name) else "") for name in shipped]
    print(f"# {cls.__module__}.{cls.__name__}: {source}" + (f"; shipped: {', '.join(listed)}" if listed else ""))
    needs[source] = missing_data(config)  # the config shown, with its --set
    for name, reason in needs.items():
        if reason:
            print(f"# {name} needs data: {reason}")
    print(yaml.safe_dump(to_dict(config, complete=True), sort_keys=False), end="")
    return 0


def missing_data(config: object) -> Optional[str]:
    """What ``config`` reads that this machine lacks (its ``missing_data()``, as
    :meth:`mmpc.scenario.ScenarioConfig.missing_data`; ``None``: nothing, or a kind that reads no data)."""
    method = getattr(config, "missing_data", None)
    return method() if callable(method) else None


def add_subcommand(sub: argparse._SubParsersAction) -> None:
    """Add ``mmpc config show``."""
    config = sub.add_parser("config", help="show a config as YAML (the defaults, a shipped one or a file, with --set)")
    commands = config.add_subparsers(dest="config_command", required=True)
    show = commands.add_parser("show", help="print a config with every setting written out")
    show.add_argument("kind", choices=sorted(KINDS), help="which config")
    show.add_argument("name", nargs="?", default=None, metavar="NAME_OR_PATH",
                      help="a shipped config's name or a YAML path (default: the defaults)")
    add_set(show, "config")
    show.set_defaults(func=run)
