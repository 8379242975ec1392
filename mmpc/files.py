"""Crash-safe file writes (readers see the old file or the complete new one, never a part) and
the lock that keeps one writer per output folder."""

from __future__ import annotations

import contextlib
import fcntl
import os
import stat
import uuid
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
    flush it to disk, then rename it onto ``path``; the temporary file is removed on an error.

    The file gets the mode ``open(path, "w")`` would give it: an existing file's, else 0o666
    less the umask (a temporary file of :mod:`tempfile` would leave it 0o600)."""
    path = Path(path)
    temporary = path.with_name(f"{TEMPORARY_PREFIX}{uuid.uuid4().hex}{path.suffix}")
    handle = os.fdopen(os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666), "wb")
    try:
        with handle:
            with contextlib.suppress(FileNotFoundError):
                os.fchmod(handle.fileno(), stat.S_IMODE(os.stat(path).st_mode))
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(temporary)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    """:func:`atomic_write` of UTF-8 text."""
    atomic_write(path, lambda handle: handle.write(text.encode("utf-8")))


@contextlib.contextmanager
def exclusive(
    out: Path, lock: str, holder: str, error: type[Exception] = OutputFolderError, *, remove: bool = False,
) -> Iterator[None]:
    """Hold the lock file ``out / lock`` while the block runs (released by the OS if this process
    dies); when another process holds it, raise ``error`` naming ``holder``, the folder and the lock.

    With ``remove`` the lock file is deleted when the block ends, normally or by an exception,
    while it is still held. A process that opened the file before it was deleted finds, once it
    holds that file's lock, that ``out / lock`` is another file or none, and takes the lock anew:
    a deleted lock file never lets two writers in.
    """
    path = out / lock
    while True:
        handle = open(path, "w")
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError as busy:
            handle.close()
            raise error(f"{holder} is writing to {out} (it holds the lock {path}); wait for it or use another "
                        "output folder") from busy
        if _names(path, handle):
            break
        handle.close()  # the lock of a file deleted since it was opened: open the one there now
    try:
        yield
    finally:
        if remove:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)
        fcntl.flock(handle, fcntl.LOCK_UN)
        handle.close()


def _names(path: Path, handle: IO) -> bool:
    """``path`` is the file open in ``handle`` (not deleted or replaced since)."""
    try:
        named = os.stat(path)
    except FileNotFoundError:
        return False
    opened = os.fstat(handle.fileno())
    return (named.st_dev, named.st_ino) == (opened.st_dev, opened.st_ino)


def file_slug(text: str) -> str:
    """``text`` as a file name: characters other than letters, digits and ``.-_`` become ``_``."""
    return "".join(c if c.isalnum() or c in ".-_" else "_" for c in text)
