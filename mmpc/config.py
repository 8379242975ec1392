"""Configuration: the one mechanism every config uses (the batch optimizer's settings are
:class:`mmpc.solver.config.OptimizerConfig`).

Every config is a frozen dataclass with units on its fields, validated in ``__post_init__``.
Three functions serve them all, reading the field types:

- :func:`from_dict` builds any config from a mapping (parsed YAML): nested configs from
  sections, ``tuple[...]`` fields from lists, ``Optional`` fields from ``null``, a union of
  configs (a scenario's ``objective``, ``traffic``) by its ``type`` key. A key that is not a
  field is an error that names the section and lists the allowed keys, so that a misspelled
  YAML key is refused instead of silently ignored; so is a value not of its field's type
  (:func:`fits_type`: ``v_max: true``, ``horizon: abc``), by its dotted key, and so is a NaN or
  infinite number where a float is wanted (``ego.speed: .inf``). A section may
  start from another file: ``{from: NAME_OR_PATH, ...}`` (or just ``NAME_OR_PATH``) loads that
  config and changes the keys given (sections merge key by key).
- :func:`to_dict` writes the YAML-ready inverse (tuples as lists, ``type`` for variants), so
  ``from_dict(type(c), to_dict(c)) == c``.
- :func:`load_config` reads a shipped config by name (``mmpc.configs``, the class's
  ``config_folder``) or a YAML file by path, and applies dotted overrides
  (``{"mpc.stop_gap": 3.0}``, what ``--set`` passes).

A config built directly (not from a mapping) checks its field types with
:func:`require_field_types` in its ``__post_init__``.

A config class may define ``upgrade(values, where) -> values``, a classmethod that rewrites a
mapping written by an earlier mmpc (retired keys) before it is read; it warns or refuses.
"""

from __future__ import annotations

import collections.abc
import dataclasses
import functools
import math
import types
import typing
from pathlib import Path
from typing import Any, Mapping, Optional, TypeVar, Union

import yaml

from mmpc.configs import shipped_config_dir

T = TypeVar("T")

#: The key of a section that starts from another config (a shipped name or a YAML path).
BASE_KEY = "from"
#: The key that names the variant of a union of configs (the class's ``kind``).
TYPE_KEY = "type"


class ConfigError(ValueError):
    """A config (file, mapping, override or dataclass field) is invalid; the message says which
    value came and what was expected. The command line prints it without a traceback."""


def from_dict(cls: type[T], values: Any, *, where: str = "") -> T:
    """Build the config dataclass ``cls`` from ``values`` (parsed YAML), by its field types.

    Args:
        cls: a dataclass (nested configs, tuples, ``Optional``, unions of configs selected by
            their ``kind``, plain scalars and mappings as fields).
        values: a mapping of field name -> value; ``None`` (an empty YAML section) means the
            defaults; a string is a shipped name or a YAML path (:func:`load_config`). A
            mapping may carry ``from: NAME_OR_PATH``: that config, with the other keys changed.
        where: what ``values`` is, for messages (e.g. ``"scenario configs/scenarios/cruise.yaml"``);
            default: the class name.

    Returns:
        ``cls(**fields)``; its ``__post_init__`` validates the values.

    Raises:
        ValueError: a key that is not a field (the message names ``where`` and lists the
            allowed keys), a value not of its field's type (:func:`fits_type`; the message
            names its dotted key, e.g. ``optimizer.horizon``), a section that is not a mapping,
            a variant without a known ``type``, or a value its ``__post_init__`` refuses.
    """
    return _build(cls, values, where or cls.__name__, (), "")


def to_dict(config: Any, *, complete: bool = False) -> dict:
    """The YAML-ready form of a config dataclass, read back by :func:`from_dict`.

    Tuples become lists, nested configs mappings, a config with a ``kind`` gets its ``type``
    key. An optional setting left at its ``None`` default is left out (unless ``complete``), so
    that one added later leaves the records of earlier runs (dataset identities,
    fingerprints) unchanged.

    Args:
        config: a dataclass instance.
        complete: also write the optional settings left at ``None`` (to show every setting).

    Returns:
        Plain data (dicts, lists, str, numbers, bools, None).
    """
    if not dataclasses.is_dataclass(config) or isinstance(config, type):
        raise TypeError(f"`config` must be a dataclass instance; got {type(config).__name__}")
    values: dict = {}
    kind = getattr(type(config), "kind", None)
    if isinstance(kind, str):
        values[TYPE_KEY] = kind
    for field in dataclasses.fields(config):
        if not field.init:
            continue
        value = getattr(config, field.name)
        if value is None and not complete and field.default is None:
            continue
        values[field.name] = _plain(value, complete)
    return values


def load_config(cls: type[T], name_or_path: Optional[str | Path] = None,
                overrides: Optional[Mapping[str, Any]] = None) -> T:
    """Load a config of class ``cls``: a shipped one by name, a YAML file, or the defaults.

    Args:
        cls: the config class (e.g. :class:`mmpc.scenario.ScenarioConfig`); its
            ``config_folder`` names its folder of shipped files in :mod:`mmpc.configs`.
        name_or_path: a shipped file's stem (``"cruise"``) or a path to a YAML file (with a
            suffix); ``None``: the dataclass defaults.
        overrides: dotted keys -> values (``{"mpc.stop_gap": 3.0, "name": "gap3"}``) replacing
            values of the file (or of the defaults) before validation. A section the file
            leaves out is first filled with the field's default, so that an override changes
            one value of what would have been loaded. An unknown key is an error, as in a file.

    Returns:
        The validated config.

    Raises:
        FileNotFoundError: no such file; the message lists the shipped names.
        ValueError: an empty file or one that does not hold a mapping, an unknown key or an
            invalid value.
    """
    if name_or_path is None:
        return with_overrides(cls(), overrides or {})
    path, values = read_config_yaml(cls, name_or_path)
    where = f"{cls.__name__} {path}"
    for dotted, value in (overrides or {}).items():
        _override(cls, values, dotted, value, where)
    return from_dict(cls, values, where=where)


def with_overrides(config: T, overrides: Mapping[str, Any]) -> T:
    """A copy of ``config`` with dotted keys changed (as :func:`load_config`'s ``overrides``),
    validated again; ``config`` itself when there are none."""
    if not overrides:
        return config
    values, where = to_dict(config, complete=True), f"{type(config).__name__} with overrides"
    for dotted, value in overrides.items():
        _override(type(config), values, dotted, value, where)
    return from_dict(type(config), values, where=where)


def shipped_names(cls: type) -> list[str]:
    """The names of the shipped configs of class ``cls`` (``[]`` when it ships none)."""
    folder = getattr(cls, "config_folder", None)
    directory = shipped_config_dir(folder) if folder else None
    return sorted(p.stem for p in directory.glob("*.yaml")) if directory and directory.is_dir() else []


def read_config_yaml(cls: type, name_or_path: str | Path) -> tuple[Path, dict]:
    """Read the YAML of a config of class ``cls``, given by path or by a shipped file's stem.

    Returns:
        The resolved path and the parsed mapping.

    Raises:
        FileNotFoundError: no such file; the message lists the shipped names.
        ValueError: the file is empty (or only comments) or does not hold a mapping: an empty
            file is a mistake, not a request for the defaults.
    """
    path = Path(name_or_path)
    folder = getattr(cls, "config_folder", None)
    if not path.suffix and folder:
        path = shipped_config_dir(folder) / f"{name_or_path}.yaml"
    if not path.is_file():
        shipped = shipped_names(cls)
        hint = f"shipped {folder}: {shipped}" if shipped else f"{cls.__name__} ships no named configs; give a YAML path"
        raise FileNotFoundError(f"{cls.__name__} {str(name_or_path)!r}: no file {path}; {hint}")
    with open(path, encoding="utf-8") as handle:
        values = yaml.safe_load(handle)
    if values is None:
        raise ConfigError(f"{cls.__name__} file {path} is empty; expected a mapping of settings (key: value lines)")
    if not isinstance(values, dict):
        raise ConfigError(f"{cls.__name__} file {path} must hold a mapping of settings (key: value lines); "
                         f"got a {type(values).__name__}")
    return path, values


def _build(cls: type[T], values: Any, where: str, chain: tuple[str, ...], key: str) -> T:
    """:func:`from_dict` with the chain of ``from`` files being read (to refuse a cycle) and the
    dotted key of the section (``""`` at the top, ``"optimizer"``, ``"traffic.vehicles[1]"``)."""
    if values is None:
        values = {}
    if isinstance(values, (str, Path)):
        values = {BASE_KEY: values}
    if not isinstance(values, Mapping):
        raise ConfigError(f"{where} must be a mapping (key: value lines) or the name or path of a "
                         f"{cls.__name__}; got {values!r}")
    values = dict(values)
    if BASE_KEY in values:
        base = values.pop(BASE_KEY)
        if not isinstance(base, (str, Path)):
            raise ConfigError(f"{where}: `{BASE_KEY}` must name a shipped {cls.__name__} or a YAML path; got {base!r}")
        if str(base) in chain:
            raise ConfigError(f"{where}: `{BASE_KEY}: {base}` reads itself (through {list(chain)})")
        path, loaded = read_config_yaml(cls, base)
        resolved = to_dict(_build(cls, loaded, f"{cls.__name__} {path}", chain + (str(base),), key), complete=True)
        values = _merge(resolved, values)
    kind = getattr(cls, "kind", None)
    if isinstance(kind, str) and TYPE_KEY in values:
        given = values.pop(TYPE_KEY)
        if given != kind:
            raise ConfigError(f"{where}: `{TYPE_KEY}` is {given!r}; expected {kind!r}")
    upgrade = getattr(cls, "upgrade", None)
    if upgrade is not None:
        values = upgrade(values, where)
    fields = {field.name: field for field in dataclasses.fields(cls) if field.init}  # type: ignore[arg-type]
    unknown = sorted(set(values) - set(fields), key=str)
    if unknown:
        raise ConfigError(f"unknown key(s) {unknown} in {where}; allowed keys: {sorted(fields)}")
    hints = _field_hints(cls)
    built = {}
    for name, value in values.items():
        dotted = f"{key}.{name}" if key else name
        built[name] = _convert(hints[name], value, f"{where}: {name}", chain, dotted)
        require(fits_type(hints[name], built[name]), _type_message(hints[name], value, dotted, where))
        _require_finite(hints[name], built[name], dotted, where)
    return cls(**built)


def _convert(hint: Any, value: Any, where: str, chain: tuple[str, ...], key: str) -> Any:
    """``value`` as the field type ``hint`` wants it (lists as tuples, sections as configs);
    a value of another type passes unchanged, for :func:`_build` to refuse."""
    origin = typing.get_origin(hint)
    if origin in (Union, types.UnionType):
        members = [member for member in typing.get_args(hint) if member is not type(None)]
        if value is None and len(members) < len(typing.get_args(hint)):
            return None
        configs = [member for member in members if dataclasses.is_dataclass(member)]
        if configs and (isinstance(value, Mapping) or len(members) == len(configs)):
            return _variant(configs, value, where, chain, key)
        for member in members:
            if member not in configs:
                converted = _convert(member, value, where, chain, key)
                if fits_type(member, converted):
                    return converted
        return value
    if dataclasses.is_dataclass(hint):
        return _build(hint, value, where, chain, key)
    if origin is tuple and isinstance(value, (list, tuple)):
        args = typing.get_args(hint)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], item, f"{where}[{i}]", chain, f"{key}[{i}]") for i, item in enumerate(value))
        if len(args) == len(value):
            return tuple(_convert(arg, item, f"{where}[{i}]", chain, f"{key}[{i}]")
                         for i, (arg, item) in enumerate(zip(args, value)))
        return tuple(value)
    if origin in (dict, Mapping, typing.get_origin(Mapping[str, Any])) and isinstance(value, Mapping):
        value_hint = typing.get_args(hint)[1] if typing.get_args(hint) else Any
        return {name: _convert(value_hint, item, f"{where}.{name}", chain, f"{key}.{name}") for name, item in value.items()}
    return value


def _variant(configs: list[type], value: Any, where: str, chain: tuple[str, ...], key: str) -> Any:
    """Build the member of a union of configs: the only one, or the one whose ``kind`` is ``value['type']``."""
    if len(configs) == 1 and not isinstance(getattr(configs[0], "kind", None), str):
        return _build(configs[0], value, where, chain, key)
    registry = {cls.kind: cls for cls in configs}  # type: ignore[attr-defined]
    if not isinstance(value, Mapping) or TYPE_KEY not in value:
        raise ConfigError(f"{where} must be a mapping with a `{TYPE_KEY}` key, one of {sorted(registry)}; got {value!r}")
    kind = value[TYPE_KEY]
    if kind not in registry:
        raise ConfigError(f"{where}: unknown type {kind!r}; expected one of {sorted(registry)}")
    return _build(registry[kind], value, f"{where} {kind}", chain, key)


def _plain(value: Any, complete: bool) -> Any:
    """Configs -> mappings, tuples -> lists, recursively."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return to_dict(value, complete=complete)
    if isinstance(value, Mapping):
        return {key: _plain(item, complete) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(item, complete) for item in value]
    return value


def _merge(base: dict, changes: Mapping) -> dict:
    """``base`` with ``changes`` applied key by key; sections merge, except a variant whose
    ``type`` changes (replaced) and a section with its own ``from``."""
    merged = dict(base)
    for key, value in changes.items():
        earlier = merged.get(key)
        if (isinstance(value, Mapping) and isinstance(earlier, Mapping) and BASE_KEY not in value
                and value.get(TYPE_KEY, earlier.get(TYPE_KEY)) == earlier.get(TYPE_KEY)):
            merged[key] = _merge(dict(earlier), value)
        else:
            merged[key] = value
    return merged


def _override(cls: Any, values: dict, dotted: str, value: Any, where: str) -> None:
    """Set ``values[a][b]...[z] = value`` for ``dotted = "a.b...z"``. A section that is missing
    (or given as a name) is first filled with what it would have been: the field's default (or
    the named config), written out; inside a section with ``from`` a missing one stays empty
    (the merge supplies the rest)."""
    *sections, key = dotted.split(".")
    target, merging = values, BASE_KEY in values
    for depth, section in enumerate(sections):
        field = _field(cls, section)
        current = target.get(section)
        merging = merging or (isinstance(current, Mapping) and BASE_KEY in current)
        if isinstance(current, (str, Path)) and field is not None and dataclasses.is_dataclass(_field_hints(cls)[section]):
            current = {BASE_KEY: current}
            merging = True
        elif current is None and not merging and field is not None and _has_default(field):
            default = _default(field)
            current = to_dict(default, complete=True) if dataclasses.is_dataclass(default) else {}
        elif current is None:
            current = {}
        if not isinstance(current, Mapping):
            raise ConfigError(f"override {dotted!r}: {'.'.join(sections[:depth + 1])!r} is not a section of {where} "
                             f"(it holds {current!r})")
        current = dict(current)
        target[section] = current
        target = current
        cls = _section_class(field, current)
    target[key] = value


def _field(cls: Any, name: str) -> Optional[dataclasses.Field]:
    if cls is None or not dataclasses.is_dataclass(cls):
        return None
    return next((field for field in dataclasses.fields(cls) if field.name == name and field.init), None)


def _has_default(field: dataclasses.Field) -> bool:
    return field.default is not dataclasses.MISSING or field.default_factory is not dataclasses.MISSING


def _default(field: dataclasses.Field) -> Any:
    return field.default if field.default is not dataclasses.MISSING else field.default_factory()  # type: ignore[misc]


def _section_class(field: Optional[dataclasses.Field], section: Mapping) -> Any:
    """The config class a section of ``field`` holds (a union's by its ``type``), else ``None``."""
    if field is None:
        return None
    default = _default(field) if _has_default(field) else None
    if dataclasses.is_dataclass(default) and section.get(TYPE_KEY, getattr(default, "kind", None)) == getattr(default, "kind", None):
        return type(default)
    return None


@functools.cache
def _field_hints(cls: type) -> dict[str, Any]:
    """The field types of the dataclass ``cls``, string annotations resolved."""
    return typing.get_type_hints(cls)


def fits_type(hint: Any, value: Any) -> bool:
    """Whether ``value`` is of the config field type ``hint``, as a config reads types.

    A bool is no number (``v_max: true`` is refused), an int is a float (YAML's ``v_max: 24``),
    a string is no number; ``tuple[...]`` holds a tuple of such items (:func:`from_dict` turns
    YAML lists into tuples first), ``Mapping[K, V]`` a mapping of such keys and values,
    ``Optional`` / a union any member's; ``Any`` and what it cannot check (a ``Callable``) pass.
    """
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is Any:
        return True
    if hint is type(None):
        return value is None
    if origin in (Union, types.UnionType):
        return any(fits_type(member, value) for member in args)
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if origin is tuple:
        if not isinstance(value, tuple):
            return False
        items = (args[0],) * len(value) if len(args) == 2 and args[1] is Ellipsis else args
        return len(items) == len(value) and all(map(fits_type, items, value))
    if origin in (dict, collections.abc.Mapping) and args:
        return isinstance(value, collections.abc.Mapping) and all(
            fits_type(args[0], name) and fits_type(args[1], item) for name, item in value.items())
    expected = origin or hint
    return isinstance(value, expected) if isinstance(expected, type) else True


def describe_type(hint: Any) -> str:
    """``hint`` in words, for messages: ``"a number"``, ``"an int or null"``, ``"a list (tuple) [a number, a number]"``."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (Union, types.UnionType):
        return " or ".join(describe_type(member) for member in args)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list (tuple), each item {describe_type(args[0])}"
        return f"a list (tuple) [{', '.join(describe_type(arg) for arg in args)}]"
    if origin in (dict, collections.abc.Mapping):
        return "a mapping" + (f", each value {describe_type(args[1])}" if args and args[1] is not Any else "")
    words = {type(None): "null", bool: "true or false", int: "an int", float: "a number", str: "a string", Any: "anything"}
    if hint in words:
        return words[hint]
    name = getattr(hint, "__name__", str(hint))
    return f"{'an' if name[:1].lower() in 'aeiou' else 'a'} {name}"


def non_finite(hint: Any, value: Any, key: str) -> Optional[tuple[str, float]]:
    """The first NaN or infinity that ``value`` holds where the field type ``hint`` wants a float
    (the field itself, the items of a ``tuple[float, ...]``, the values of a ``Mapping[str,
    float]``, a member of ``Optional`` / a union), as ``(key, value)`` with the key of the item
    (``traffic.target_speeds[1]``); ``None`` when every such float is finite. A field typed
    ``Any`` is not looked into."""
    if hint is float:
        return (key, value) if isinstance(value, float) and not math.isfinite(value) else None
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (Union, types.UnionType):
        member = next((member for member in args if fits_type(member, value)), None)
        return None if member is None else non_finite(member, value, key)
    if origin is tuple and isinstance(value, tuple):
        items = (args[0],) * len(value) if len(args) == 2 and args[1] is Ellipsis else args
        found = (non_finite(item, part, f"{key}[{i}]") for i, (item, part) in enumerate(zip(items, value)))
        return next((hit for hit in found if hit is not None), None)
    if origin in (dict, collections.abc.Mapping) and len(args) == 2 and isinstance(value, collections.abc.Mapping):
        found = (non_finite(args[1], item, f"{key}.{name}") for name, item in value.items())
        return next((hit for hit in found if hit is not None), None)
    return None


def _require_finite(hint: Any, value: Any, key: str, where: str) -> None:
    """Refuse a NaN or infinite float in a float field (:func:`non_finite`): no float setting of
    mmpc takes inf for "unbounded", and a NaN slips through range checks written as comparisons.
    The message names the key: ``"{where}: `ego.speed` must be finite; got inf"``."""
    found = non_finite(hint, value, key)
    if found is not None:
        raise ConfigError(f"{where}: `{found[0]}` must be finite; got {found[1]!r}")


def _type_message(hint: Any, value: Any, key: str, where: str) -> str:
    """``"{where}: `key` must be a number; got 'abc'"``: a value not of its field type."""
    return f"{where}: `{key}` must be {describe_type(hint)}; got {value!r}"


def require_field_types(config: Any) -> None:
    """Check every field of the config dataclass ``config`` against its type (:func:`fits_type`),
    for a config built directly, not by :func:`from_dict` (which checks as it builds); the
    message names the class and the field: ``"OptimizerConfig: `a_max` must be a number; got '4'"``.
    A float field (or float item) that is NaN or infinite is refused as :func:`from_dict` refuses it."""
    hints = _field_hints(type(config))
    for field in dataclasses.fields(config):
        if field.init:
            value = getattr(config, field.name)
            require(fits_type(hints[field.name], value), _type_message(hints[field.name], value, field.name, type(config).__name__))
            _require_finite(hints[field.name], value, field.name, type(config).__name__)


def require(condition: bool, message: str) -> None:
    """Raise :class:`ConfigError` ``(message)`` unless ``condition``: the check every config validator uses."""
    if not condition:
        raise ConfigError(message)


def is_finite_number(value: Any) -> bool:
    """A real int or float (not a bool) that is neither NaN nor infinite."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def require_positive(where: str, **values: Any) -> None:
    """Check that every keyword value is a finite number > 0.

    The message names the field and the value that came: ``"{where}: `name` must be a finite
    number > 0; got value"`` (without the ``where`` prefix when it is empty).
    """
    prefix = f"{where}: " if where else ""
    for name, value in values.items():
        require(is_finite_number(value) and value > 0, f"{prefix}`{name}` must be a finite number > 0; got {value!r}")


def require_int(where: str, low: Optional[int] = None, high: Optional[int] = None, **values: Any) -> None:
    """Check that every keyword value is an int (not a bool) in ``[low, high]`` (``None``: open).

    Messages as :func:`require_positive`: ``"`name` must be an int >= low; got value"`` (``in
    [low, high]`` with both bounds, ``<= high`` with the upper one alone).
    """
    prefix = f"{where}: " if where else ""
    expected = ("" if low is None and high is None else f" >= {low}" if high is None else f" <= {high}" if low is None
                else f" in [{low}, {high}]")
    for name, value in values.items():
        require(isinstance(value, int) and not isinstance(value, bool) and (low is None or value >= low)
                and (high is None or value <= high), f"{prefix}`{name}` must be an int{expected}; got {value!r}")


def require_non_negative(where: str, **values: Any) -> None:
    """Check that every keyword value is a finite number >= 0 (messages as :func:`require_positive`)."""
    prefix = f"{where}: " if where else ""
    for name, value in values.items():
        require(is_finite_number(value) and value >= 0, f"{prefix}`{name}` must be a finite number >= 0; got {value!r}")
