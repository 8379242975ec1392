"""Crash-safe file writes (readers see the old file or the complete new one, never a part) and
the lock that keeps one writer per output folder."""

from __future__ import annotations

import contextlib
import fcntl
import os
import tempfile
from pathlib import Path
from typing import IO, Callable, Iterator

#: Prefix of the temporary files :func:`atomic_write` leaves behind if the process is killed
#: mid-write (a writer may sweep ``.tmp-*`` in its folder).
TEMPORARY_PREFIX = ".tmp-"


class OutputFolderError(RuntimeError):
    """An output folder a command will not write to: another process holds its lock, or it holds
    what the command would overwrite. The command line prints it without a traceback."""


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


@contextlib.contextmanager
def exclusive(
    out: Path, lock: str, holder: str, error: type[Exception] = OutputFolderError,
) -> Iterator[None]:
    """Hold the lock file ``out / lock`` while the block runs (released by the OS if this process
    dies); when another process holds it, raise ``error`` naming ``holder``, the folder and the lock."""
    with open(out / lock, "w") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError as busy:
            raise error(f"{holder} is writing to {out} (it holds the lock {out / lock}); wait for it or use another "
                        "output folder") from busy
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def file_slug(text: str) -> str:
    """``text`` as a file name: characters other than letters, digits and ``.-_`` become ``_``."""
    return "".join(c if c.isalnum() or c in ".-_" else "_" for c in text)
