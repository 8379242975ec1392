"""Argument types and groups shared by every ``mmpc`` verb (``mmpc.rl`` and ``mmpc.imitation``
included), so that seeds, overrides and output folders read the same everywhere."""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path
from typing import Optional

import yaml

from mmpc.files import TEMPORARY_PREFIX


def int_list(text: str) -> tuple[int, ...]:
    try:
        values = tuple(int(v) for v in text.split(",") if v)
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers; got {text!r}") from error
    if not values or min(values) < 0:
        raise argparse.ArgumentTypeError(f"expected non-negative integers; got {text!r}")
    return values


def seed_list(text: str) -> tuple[int, ...]:
    """``"0-19"``, ``"0,3,7"`` or a mix (``"0-4,9"``) -> seeds."""
    seeds: list[int] = []
    try:
        for part in (p for p in text.split(",") if p):
            low, _, high = part.partition("-")
            seeds.extend(range(int(low), int(high) + 1) if high else [int(low)])
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"expected seeds like 0-19 or 0,3,7; got {text!r}") from error
    if not seeds or min(seeds) < 0:
        raise argparse.ArgumentTypeError(f"expected non-negative seeds like 0-19 or 0,3,7; got {text!r}")
    return tuple(dict.fromkeys(seeds))


def override(text: str) -> tuple[str, object]:
    """``"traffic.lane_changes=true"`` -> ("traffic.lane_changes", True) (the value is YAML)."""
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE such as traffic.lane_changes=true; got {text!r}")
    return key, yaml.safe_load(value)


def unwritable(out: Path) -> Optional[str]:
    """Why ``out`` cannot take outputs (created, then a probe file written and removed); ``None`` if it can."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=out, prefix=TEMPORARY_PREFIX):
            pass
    except OSError as error:
        return f"{type(error).__name__}: {error}"
    return None



def driver_specs(values: list[str]) -> tuple[str, ...]:
    """``--driver mpc,frenet --driver bc:run/policy.pt`` -> distinct specs in order."""
    return tuple(dict.fromkeys(spec.strip() for value in values for spec in value.split(",") if spec.strip()))
