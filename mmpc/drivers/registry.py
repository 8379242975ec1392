"""Drivers by name: a spec string (``mpc``, ``frenet``, ``bc:RUN/policy.pt``, ...) builds one.

Drivers register themselves; this module names none. A package declares its drivers as entry
points of the group :data:`ENTRY_POINT_GROUP` (``name = "module:factory"``; mmpc's own, and
those of :mod:`mmpc.rl` and :mod:`mmpc.imitation`, are in ``pyproject.toml``), loaded on first
use, so optional dependencies (CasADi, stable-baselines3) load only with the drivers that need
them and worker processes (process pool, Ray) see the same drivers. A driver defined in a script
registers with :func:`register_driver` (in-process backends only: a spawned worker does not run
the script).

A factory is ``factory(scenario, argument) -> Driver``, ``argument`` being the text after ``:``
in the spec or ``None``. A factory whose driver reads files that a name stands for (a shipped
model, a run's config beside its model) says which with an attribute ``files(argument) ->
tuple[Path, ...]`` (:func:`driver_files`); without one, an argument naming a file is that file.
"""

from __future__ import annotations

from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Optional

from mmpc.drivers.base import Driver

if TYPE_CHECKING:
    from mmpc.scenario import ScenarioConfig

#: The entry-point group that names driver factories.
ENTRY_POINT_GROUP = "mmpc.drivers"

DriverFactory = Callable[["ScenarioConfig", Optional[str]], Driver]

_registered: dict[str, DriverFactory] = {}


def _declared() -> dict[str, metadata.EntryPoint]:
    return {point.name: point for point in metadata.entry_points(group=ENTRY_POINT_GROUP)}


def register_driver(name: str, factory: DriverFactory) -> None:
    """Make ``name`` a driver spec built by ``factory(scenario, argument)``.

    Raises:
        ValueError: ``name`` is empty, holds ``:`` or ``,``, or is taken (declared or registered).
    """
    if not isinstance(name, str) or not name or ":" in name or "," in name:
        raise ValueError(f"a driver name must be a non-empty string without ':' or ','; got {name!r}")
    if name in _registered or name in _declared():
        raise ValueError(f"driver {name!r} exists already; choose another name")
    if not callable(factory):
        raise TypeError(f"driver factory for {name!r} must be callable; got {type(factory).__name__}")
    _registered[name] = factory


def driver_names() -> list[str]:
    """Every driver name that a spec may start with, sorted."""
    return sorted({*_declared(), *_registered})


def make_driver(spec: str, scenario: "ScenarioConfig") -> Driver:
    """Build the driver named by ``spec`` for ``scenario``.

    Args:
        spec: ``NAME`` or ``NAME:ARGUMENT`` with NAME one of :func:`driver_names`
            (e.g. ``frenet``, ``bc:runs/bc/policy.pt``).
        scenario: the scenario it will drive (objective, road, optimizer settings).

    Raises:
        ValueError: an empty or unknown spec (the message lists the known names).
    """
    name, sep, argument = check_spec(spec)
    factory = _registered.get(name) or _declared()[name].load()
    return factory(scenario, argument if sep else None)


def driver_files(spec: str) -> tuple[Path, ...]:
    """The files the driver of ``spec`` reads (a checkpoint; a model and its run's config): its
    factory's ``files(argument)``, else the argument where it names a file, else none; an
    evaluation fingerprints them (:mod:`mmpc.evaluate.store`).

    Raises:
        ValueError: an empty or unknown spec (:func:`check_spec`).
    """
    name, sep, argument = check_spec(spec)
    factory = _registered.get(name) or _declared()[name].load()
    files = getattr(factory, "files", None)
    if files is not None:
        return tuple(files(argument if sep else None))
    return (Path(argument),) if argument and Path(argument).is_file() else ()


def check_spec(spec: str) -> tuple[str, str, str]:
    """``spec.partition(":")`` of a spec whose name is a known driver; ``ValueError`` otherwise."""
    if not isinstance(spec, str) or not spec:
        raise ValueError(f"driver spec must be a non-empty string such as 'mpc'; got {spec!r}")
    name, sep, argument = spec.partition(":")
    if name not in _registered and name not in _declared():
        known = driver_names()
        hint = "" if known else " (no driver is declared: is mmpc installed, e.g. pip install -e .?)"
        raise ValueError(f"unknown driver {name!r} in {spec!r}; expected one of {known}{hint}")
    return name, sep, argument
