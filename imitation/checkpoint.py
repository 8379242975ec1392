"""Checkpoint files of the imitation models (the cloned policy, the mode proposer): a torch file
holding a dict of tensors and plain data, tagged with a format name and a version, written atomically."""

from __future__ import annotations

from pathlib import Path

import torch

from mmpc.files import atomic_write


def write_checkpoint(path: Path, form: str, version: int, content: dict) -> Path:
    """Write ``content`` with its ``format`` and ``version`` tags to ``path`` (folders created)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    checkpoint = {"format": form, "version": version, **content}
    atomic_write(path, lambda handle: torch.save(checkpoint, handle))
    return path


def read_checkpoint(path: Path, form: str, version: int, *, what: str, hint: str) -> dict:
    """The dict of a checkpoint written by :func:`write_checkpoint` with these tags.

    Args:
        path: the file.
        form, version: the tags it must carry.
        what: what the file should be, for errors (e.g. "policy").
        hint: how to get one, for errors (e.g. "train one with `mmpc imitate bc`").

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a torch file, another format, or another version.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} checkpoint {path} does not exist ({hint})")
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises several types for a file that is not a checkpoint
        raise ValueError(f"{path} is not a readable torch checkpoint ({type(error).__name__}: {error})") from error
    if not isinstance(checkpoint, dict) or checkpoint.get("format") != form:
        raise ValueError(f"{path} is not an mmpc {what} checkpoint (format {form!r} expected)")
    if checkpoint.get("version") != version:
        raise ValueError(f"{path}: checkpoint version {checkpoint.get('version')!r}; this mmpc reads {version} "
                         f"({hint})")
    return checkpoint
