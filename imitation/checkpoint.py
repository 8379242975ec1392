"""Checkpoint files of the imitation models (the cloned policy, the mode proposer), one format
for both: a torch file holding a dict of tensors and plain data, written atomically::

    {"format": <kind tag>, "version": <int>, "config": <the architecture, a dict>,
     <the kind's own entries, e.g. "num_goals">, "road": {"num_lanes", "lane_width"},
     "scene": {"vehicle_length", "ellipse"}, "state_dict": <weights and statistics>,
     "scenario": <name or None>, "info": <JSON-able dict>}

A :class:`CheckpointKind` names one kind; :func:`save_model` writes a model of it,
:func:`read_model` reads and checks a file of it, :func:`load_model` rebuilds the model.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Optional

import torch
from torch import nn

from mmpc.config import from_dict, to_dict
from mmpc.files import atomic_write
from mmpc.imitation.features import SceneGeometry
from mmpc.road import Road


@dataclass(frozen=True)
class CheckpointKind:
    """One kind of checkpoint.

    Attributes:
        form: the ``format`` tag (e.g. ``"mmpc-policy"``).
        version: the ``version`` this mmpc writes and reads.
        what: the model, for errors (e.g. ``"policy"``).
        hint: how to get one, for errors (e.g. ``"train one with `mmpc imitate bc`"``).
        config_type: the dataclass of the ``config`` entry.
        extra: the kind's own entries, written after ``config``.
        legacy_scene: the scene of a file without a ``scene`` entry (written before the features
            read the scenario); ``None``: the entry is required.
    """

    form: str
    version: int
    what: str
    hint: str
    config_type: type
    extra: tuple[str, ...] = ()
    legacy_scene: Optional[SceneGeometry] = None


def road_of(values: Mapping[str, Any]) -> Road:
    """A :class:`Road` from its checkpoint form ``{"num_lanes": ..., "lane_width": ...}``."""
    return from_dict(Road, values, where="road")


def road_dict(road: Road) -> dict:
    """The checkpoint form of a :class:`Road` (see :func:`road_of`)."""
    return {"num_lanes": road.num_lanes, "lane_width": float(road.lane_width)}


def save_model(path: Path, kind: CheckpointKind, model: nn.Module, *, scenario: Optional[str] = None,
               info: Optional[dict] = None, **extra: Any) -> Path:
    """Write ``model`` (its ``config``, ``road``, ``scene`` and ``state_dict``) as a checkpoint of
    ``kind`` to ``path`` (folders created), with the kind's own entries ``extra`` and the
    scenario's name and JSON-able ``info``. Returns ``path``."""
    if set(extra) != set(kind.extra):
        raise ValueError(f"a {kind.what} checkpoint holds the entries {list(kind.extra)}; got {sorted(extra)}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    checkpoint = {
        "format": kind.form, "version": kind.version, "config": to_dict(model.config),
        **{name: extra[name] for name in kind.extra},
        "road": road_dict(model.road), "scene": to_dict(model.scene), "state_dict": model.state_dict(),
        "scenario": scenario, "info": info or {},
    }
    atomic_write(path, lambda handle: torch.save(checkpoint, handle))
    return path


def read_model(path: Path, kind: CheckpointKind) -> dict:
    """The dict of a checkpoint of ``kind`` written by :func:`save_model` (tensors and plain data only).

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a torch file, another format or version, or an entry missing.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{kind.what} checkpoint {path} does not exist ({kind.hint})")
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises several types for a file that is not a checkpoint
        raise ValueError(f"{path} is not a readable torch checkpoint ({type(error).__name__}: {error})") from error
    if not isinstance(checkpoint, dict) or checkpoint.get("format") != kind.form:
        raise ValueError(f"{path} is not an mmpc {kind.what} checkpoint (format {kind.form!r} expected)")
    if checkpoint.get("version") != kind.version:
        raise ValueError(f"{path}: checkpoint version {checkpoint.get('version')!r}; this mmpc reads {kind.version} "
                         f"({kind.hint})")
    required = ("config", *kind.extra, "road", "state_dict") + (("scene",) if kind.legacy_scene is None else ())
    missing = [name for name in required if name not in checkpoint]
    if missing:
        raise ValueError(f"{path}: the {kind.what} checkpoint lacks {', '.join(map(repr, missing))} (damaged?)")
    return checkpoint


def load_model(checkpoint: dict, kind: CheckpointKind, build: Callable[..., nn.Module]) -> nn.Module:
    """The model of a checkpoint read by :func:`read_model`, in eval mode: ``build(road, config,
    scene=scene, **entries)`` (``entries``: the kind's own) with the stored weights and statistics."""
    config = from_dict(kind.config_type, checkpoint["config"], where=f"{kind.what} checkpoint: config")
    scene = (from_dict(SceneGeometry, checkpoint["scene"], where=f"{kind.what} checkpoint: scene")
             if "scene" in checkpoint else kind.legacy_scene)
    model = build(road_of(checkpoint["road"]), config, scene=scene, **{name: checkpoint[name] for name in kind.extra})
    model.load_state_dict(checkpoint["state_dict"])
    return model.eval()
