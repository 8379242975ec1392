"""Crash-safe file writes: readers see the old file or the complete new one, never a part."""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import IO, Callable

#: Prefix of the temporary files :func:`atomic_write` leaves behind if the process is killed
#: mid-write (a writer may sweep ``.tmp-*`` in its folder).
TEMPORARY_PREFIX = ".tmp-"


def atomic_write(path: Path, write: Callable[[IO[bytes]], object]) -> None:
    """Write through ``write(handle)`` (a binary file) to a temporary file in ``path``'s folder,
    flush it to disk, then rename it onto ``path``; the temporary file is removed on an error."""
    path = Path(path)
    handle = tempfile.NamedTemporaryFile("wb", dir=path.parent, prefix=TEMPORARY_PREFIX, suffix=path.suffix, delete=False)
    try:
        with handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(handle.name, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(handle.name)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    """:func:`atomic_write` of UTF-8 text."""
    atomic_write(path, lambda handle: handle.write(text.encode("utf-8")))
