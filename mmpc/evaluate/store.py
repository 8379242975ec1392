"""The evaluation's files: ``episodes.csv`` (one row per episode, :data:`COLUMNS`) and
``scenarios.json`` (:class:`FolderInputs`: the settings and their hash of every scenario whose
episodes the folder holds, and the hash of the files of every driver spec that names files).

``episodes.csv`` is written by the coordinating process only: rewritten atomically at the start
of a run, then appended to and fsync'ed as each group finishes, so a killed run loses no
finished episode. A last line without its newline (a write cut short) is dropped on reading;
any other damage is refused with the file and the line.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import logging
import os
from pathlib import Path
from typing import NamedTuple, Optional, Sequence

from mmpc.collisions import CRASH_COLUMNS
from mmpc.config import from_dict, to_dict
from mmpc.drivers.registry import driver_files
from mmpc.files import atomic_write_text
from mmpc.scenario import ScenarioConfig

logger = logging.getLogger(__name__)

#: An episode's identity.
KEY_COLUMNS = ("driver", "scenario", "seed")
#: How it ran: ``status`` ok/error, ``error`` the exception, ``group`` (= seed // lockstep) and
#: ``group_size`` (episodes driven together), ``worker`` (host:pid), ``wall_s`` (the group's
#: wall time [s]).
RUN_COLUMNS = ("status", "error", "group", "group_size", "worker", "wall_s")
#: The episode metrics (:func:`mmpc.metrics.episode_metrics`; empty where a scenario has none),
#: what a collision struck and whose fault it was (:class:`mmpc.highway.runner.EpisodeResult`),
#: ``solve_ms_per_episode_mean``: each decision's time divided by the episodes it served, the
#: crash's scene (:data:`mmpc.collisions.CRASH_COLUMNS`; empty without a collision), and what the
#: assumption monitor saw (:class:`mmpc.verify.AssumptionMonitor`: cars that left their sets; whether the collider had).
METRIC_COLUMNS = (
    "steps", "duration", "collisions", "collision_part", "ego_fault_collisions", "offroad", "mean_speed", "meta_cost_mean", "meta_cost_max", "plan_cost_mean",
    "task_return", "speed_residual_mean", "right_lane_distance_mean", "lin_acc_mean", "ang_acc_mean", "solve_ms_mean",
    "solve_ms_max", "solve_ms_per_episode_mean", "iterations_mean", "lane_changes", "fallback_steps", "verified_share",
    "first_verified_step", "failsafe_steps", "min_clearance", "off_centre_share", "lane_change_s_mean", "min_ttc", "short_ttc_steps",
    "near_lane_change_steps", "assumption_violations", *CRASH_COLUMNS, "crash_collider_outside",
)
COLUMNS = KEY_COLUMNS + RUN_COLUMNS + METRIC_COLUMNS
_INT_COLUMNS = frozenset({"seed", "group", "group_size", "steps", "collisions", "ego_fault_collisions", "offroad",
                          "lane_changes", "fallback_steps", "first_verified_step", "failsafe_steps", "short_ttc_steps", "near_lane_change_steps",
                          "crash_fallback_steps",
                          "assumption_violations", "crash_collider_outside"})
_TEXT_COLUMNS = frozenset({"driver", "scenario", "status", "error", "worker", "collision_part"})
#: The metrics that are numbers (all but the part a collision struck).
NUMBER_COLUMNS = tuple(column for column in METRIC_COLUMNS if column not in _TEXT_COLUMNS)
_NULLABLE_TEXT_COLUMNS = frozenset({"collision_part"})  # an empty cell reads back as None

Key = tuple[str, str, int]


def new_row(**values: object) -> dict:
    """A row with every one of :data:`COLUMNS`, in order (``None`` where not given)."""
    return {column: values.get(column) for column in COLUMNS}


def row_key(row: dict) -> Key:
    """``(driver, scenario, seed)`` of a row."""
    return row["driver"], row["scenario"], row["seed"]


class EvaluationFolderError(ValueError):
    """An evaluation folder whose ``episodes.csv`` or ``scenarios.json`` cannot be resumed from
    (another format, a damaged line, episodes of another scenario of the same name)."""


#: What to do about a damaged line of ``episodes.csv``.
_DAMAGED_LINE = "fix or delete the line (a deleted episode is run again) or use another `out`"


def _parse(column: str, text: str, where: str) -> object:
    if column in _TEXT_COLUMNS:
        return None if text == "" and column in _NULLABLE_TEXT_COLUMNS else text
    if text == "":
        return None
    try:
        return int(text) if column in _INT_COLUMNS else float(text)
    except ValueError:
        expected = "an integer" if column in _INT_COLUMNS else "a number"
        raise EvaluationFolderError(f"{where}: `{column}` is {text!r}, expected {expected}; {_DAMAGED_LINE}") from None


def read_episodes(path: Path) -> list[dict]:
    """The rows of an ``episodes.csv``, typed (ints, floats, ``None`` for empty cells).

    A last line without its newline (a write cut short by a killed process) is dropped.

    Raises:
        EvaluationFolderError: the header lacks a key column, or a line has another number of
            fields than the header, an empty key, a status other than ok/error or a value that
            does not parse; the message names the file and the line.
    """
    path = Path(path)
    if not path.exists():
        return []
    data = path.read_bytes()
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as error:
        line = data[:error.start].count(b"\n") + 1
        raise EvaluationFolderError(f"{path}, line {line}: not UTF-8 text ({error}); {_DAMAGED_LINE}") from error
    if text and not text.endswith("\n"):
        logger.warning("%s: dropping an incomplete last line (an interrupted write)", path)
        text = text[: text.rfind("\n") + 1]
    reader = csv.reader(io.StringIO(text))
    rows = []
    try:
        header = next(reader, [])
        missing = [c for c in KEY_COLUMNS + ("status",) if c not in header]
        if text and missing:
            raise EvaluationFolderError(f"{path} is not an evaluation's episodes.csv: columns {missing} missing; "
                                        "use another `out`")
        for fields in reader:
            if not fields:  # a blank line
                continue
            where = f"{path}, line {reader.line_num}"
            if len(fields) != len(header):
                raise EvaluationFolderError(f"{where}: {len(fields)} fields, expected {len(header)} (the header's); "
                                            f"{_DAMAGED_LINE}")
            values = dict(zip(header, fields))
            row = {column: _parse(column, values.get(column, ""), where) for column in COLUMNS}
            if not row["driver"] or not row["scenario"] or row["seed"] is None or row["status"] not in ("ok", "error"):
                raise EvaluationFolderError(
                    f"{where}: expected a driver, a scenario, a seed and status ok or error; got "
                    f"driver={row['driver']!r}, scenario={row['scenario']!r}, seed={row['seed']!r}, "
                    f"status={row['status']!r}; {_DAMAGED_LINE}")
            rows.append(row)
    except csv.Error as error:  # e.g. a NUL byte, as a crash can leave
        raise EvaluationFolderError(f"{path}, line {reader.line_num}: {error}; {_DAMAGED_LINE}") from error
    return rows


def _csv_lines(rows: Sequence[dict]) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=COLUMNS, extrasaction="ignore", lineterminator="\n")
    for row in rows:
        writer.writerow({column: "" if row.get(column) is None else row[column] for column in COLUMNS})
    return buffer.getvalue()


class EpisodeFile:
    """``episodes.csv``, written by the coordinating process only: rewritten atomically at the
    start of a run, then appended to (one write + fsync per finished group)."""

    def __init__(self, path: Path, rows: Sequence[dict]) -> None:
        self.path = path
        atomic_write_text(path, ",".join(COLUMNS) + "\n" + _csv_lines(rows))
        self._handle = open(path, "a", encoding="utf-8", newline="")

    def append(self, rows: Sequence[dict]) -> None:
        self._handle.write(_csv_lines(rows))
        self._handle.flush()
        os.fsync(self._handle.fileno())

    def close(self) -> None:
        self._handle.close()


#: What to do about a damaged ``scenarios.json``.
_CORRUPT_SCENARIOS = ("delete it only if the episodes in this folder were run with the scenarios and driver files as "
                      "they are now; otherwise use another `out`")


def scenario_settings(scenario: ScenarioConfig) -> dict:
    """Every setting of a scenario (:func:`mmpc.config.to_dict`), what :func:`scenario_fingerprint`
    hashes; ``sim`` only when it is not highway-env, so that folders written before the batched
    simulator resume."""
    settings = to_dict(scenario)
    if settings.get("sim") == "highway-env":
        del settings["sim"]
    return settings


def scenario_fingerprint(scenario: ScenarioConfig) -> str:
    """A short hash of :func:`scenario_settings`."""
    return hashlib.sha256(json.dumps(scenario_settings(scenario), sort_keys=True).encode()).hexdigest()[:16]


def driver_fingerprint(spec: str) -> Optional[str]:
    """A short hash of the names and contents of the files the driver reads
    (:func:`mmpc.drivers.driver_files`; ``None``: it reads none)."""
    files = driver_files(spec)
    if not files:
        return None
    digest = hashlib.sha256()
    for path in files:
        digest.update(path.name.encode() + b"\0" + hashlib.sha256(path.read_bytes()).digest())
    return digest.hexdigest()[:16]


#: ``format`` of ``scenarios.json``; files without it come from mmpc before 2026-11-23, whose
#: hashes covered ``mpc.compile`` and ``mpc.wheelbase`` (no longer settings of a scenario).
SCENARIOS_FORMAT = 2


class FolderInputs(NamedTuple):
    """What an evaluation folder's ``scenarios.json`` records of the inputs its episodes were run with.

    Fields:
        scenarios: scenario name -> :func:`scenario_fingerprint`.
        settings: scenario name -> :func:`scenario_settings` (none in folders of an earlier mmpc).
        drivers: driver spec -> :func:`driver_fingerprint`, for the specs that name files
            (none in folders of an earlier mmpc).
        legacy: written by mmpc before 2026-11-23, whose scenario hashes covered other settings.
    """

    scenarios: dict[str, str]
    settings: dict[str, dict]
    drivers: dict[str, str]
    legacy: bool


def read_inputs(out: Path) -> FolderInputs:
    """The ``scenarios.json`` of the evaluation folder ``out`` (all empty where there is none).

    Raises:
        EvaluationFolderError: the file is not such a record (the message names it).
    """
    path = Path(out) / "scenarios.json"
    if not path.exists():
        return FolderInputs({}, {}, {}, False)
    try:
        stored = json.loads(path.read_text(encoding="utf-8"))
    except ValueError as error:  # JSONDecodeError names the line and column; UnicodeDecodeError the byte
        raise EvaluationFolderError(f"{path} is corrupt ({error}); expected the JSON object of scenario name -> "
                                    f"settings hash this folder's episodes were run with; {_CORRUPT_SCENARIOS}") from error
    legacy = isinstance(stored, dict) and "format" not in stored
    record = {"scenarios": stored} if legacy else stored if isinstance(stored, dict) else {}
    inputs = FolderInputs(record.get("scenarios"), record.get("settings", {}), record.get("drivers", {}), legacy)
    if not all(isinstance(section, dict) and all(isinstance(v, kind) for v in section.values())
               for section, kind in ((inputs.scenarios, str), (inputs.settings, dict), (inputs.drivers, str))):
        raise EvaluationFolderError(f"{path} is corrupt: expected a JSON object of scenario name -> settings hash (and "
                                    f"of scenario name -> settings, driver spec -> files hash); got {str(stored)[:100]}; "
                                    f"{_CORRUPT_SCENARIOS}")
    return inputs


def _flat(settings: dict, prefix: str = "") -> dict:
    """Nested settings as ``{"dotted.key": value}``."""
    flat = {}
    for key, value in settings.items():
        flat.update(_flat(value, f"{prefix}{key}.") if isinstance(value, dict) else {f"{prefix}{key}": value})
    return flat


def scenario_differences(folder: Path, scenario: str, other_folder: Path, other_scenario: str,
                         ignore: Sequence[str] = ("name",)) -> list[str]:
    """How scenario ``other_scenario``'s episodes in ``other_folder`` were run differently from
    ``scenario``'s in ``folder``, read from the folders' ``scenarios.json``: ``"key: value vs
    other value"`` per setting but those in ``ignore``; empty where they agree; one line saying so
    where a folder does not record its scenario's settings.

    Raises:
        EvaluationFolderError: a ``scenarios.json`` is corrupt.
    """
    recorded = []
    for where, name in ((Path(folder), scenario), (Path(other_folder), other_scenario)):
        inputs = read_inputs(where)
        if name not in inputs.scenarios:
            return [f"{where / 'scenarios.json'} does not record scenario {name!r}, so its settings cannot be compared"]
        recorded.append((inputs.scenarios[name], inputs.settings.get(name)))
    (first_hash, first_settings), (other_hash, other_settings) = recorded
    if first_hash == other_hash:
        return []
    if first_settings is None or other_settings is None:
        return [f"settings hash {first_hash} vs {other_hash} (the settings are not recorded: a folder of an earlier mmpc)"]
    # read as today's loader reads them: a setting added since (at its default) or retired (off) is no difference
    first_settings, other_settings = (scenario_settings(scenario) if (scenario := _reread(settings, "")) is not None
                                      else settings for settings in (first_settings, other_settings))
    ours, theirs = _flat(first_settings), _flat(other_settings)
    return [f"{key}: {ours.get(key, '-')} vs {theirs.get(key, '-')}" for key in sorted(ours.keys() | theirs.keys())
            if key.split(".")[0] not in ignore and ours.get(key, "-") != theirs.get(key, "-")]


def _reread(settings: Optional[dict], where: str) -> Optional[ScenarioConfig]:
    """The scenario recorded as ``settings`` read as today's loader reads a file (retired keys
    dropped, :meth:`ScenarioConfig.upgrade`); ``None`` where none is recorded or it no longer loads."""
    if settings is None:
        return None
    try:
        return from_dict(ScenarioConfig, {"sim": "highway-env", **settings}, where=where)
    except ValueError:
        return None


def _changes(recorded: Optional[ScenarioConfig], scenario: ScenarioConfig) -> str:
    """What differs between the scenario the episodes were run with and ``scenario``, in words."""
    if recorded is None:
        return "its settings changed, e.g. --duration or --set; the folder does not record them readably"
    ours, theirs = _flat(scenario_settings(recorded)), _flat(scenario_settings(scenario))
    lines = [f"{key}: {ours.get(key, '-')} then, {theirs.get(key, '-')} now" for key in sorted(ours.keys() | theirs.keys())
             if ours.get(key, "-") != theirs.get(key, "-")]
    return "settings changed: " + "; ".join(lines)


def check_inputs(out: Path, scenarios: Sequence[ScenarioConfig], drivers: Sequence[str]) -> None:
    """Refuse to mix in ``out`` episodes of two different scenarios under one name, or of a driver
    spec whose files (:func:`mmpc.drivers.driver_files`) changed; record those of this run in ``scenarios.json``.

    Raises:
        EvaluationFolderError: a scenario's settings or a driver's files differ from those
            ``out``'s episodes were run with, or ``scenarios.json`` is damaged.
    """
    path = out / "scenarios.json"
    known = read_inputs(out)
    for scenario in scenarios:
        fingerprint = scenario_fingerprint(scenario)
        if known.scenarios.setdefault(scenario.name, fingerprint) != fingerprint:
            if known.legacy:
                raise EvaluationFolderError(
                    f"{out} was written by an earlier mmpc whose scenario hashes included settings that are no longer "
                    f"part of a scenario (mpc.compile, mpc.wheelbase), so its episodes of {scenario.name!r} cannot be "
                    f"matched to today's scenario; use another `out`, or delete {path} if the scenarios are unchanged "
                    "apart from those two settings")
            recorded = _reread(known.settings.get(scenario.name), f"{path}: scenario {scenario.name!r}")
            if recorded is None or scenario_fingerprint(recorded) != fingerprint:
                raise EvaluationFolderError(
                    f"{out} holds episodes of another scenario named {scenario.name!r} ({_changes(recorded, scenario)}); "
                    "use another `out` or rename the scenario (--set name=...)")
            # recorded with keys this mmpc reads away (retired options that were off): the same scenario
            known.scenarios[scenario.name], known.settings[scenario.name] = fingerprint, scenario_settings(scenario)
        known.settings.setdefault(scenario.name, scenario_settings(scenario))
    for spec in drivers:
        fingerprint = driver_fingerprint(spec)
        if fingerprint is not None and known.drivers.setdefault(spec, fingerprint) != fingerprint:
            files = ", ".join(str(p) for p in driver_files(spec))
            raise EvaluationFolderError(
                f"{out} holds episodes of driver {spec!r} run with other contents of its file(s) {files} (files hash "
                f"{known.drivers[spec]}, now {fingerprint}); use another `out`, or give the new file another path "
                "(another spec)")
    record = {"format": SCENARIOS_FORMAT, "scenarios": known.scenarios, "settings": known.settings, "drivers": known.drivers}
    atomic_write_text(path, json.dumps(record, indent=2) + "\n")
