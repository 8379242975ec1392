"""The output folder of a training run, held while the run writes it (``mmpc rl train``,
``mmpc imitate {bc, dagger, proposer}``): created when missing, its lock file keeping a second
writer out (:func:`mmpc.files.exclusive`), and for a run that does not resume, refused when it
holds anything (the run would replace or mix with it)."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Callable, Iterator, Optional

from mmpc.files import OutputFolderError, exclusive


@contextlib.contextmanager
def run_folder(
    out: Path,
    lock: str,
    holder: str,
    *,
    fresh: Optional[str] = None,
    describe: Callable[[Path], str] = lambda out: "files",
) -> Iterator[None]:
    """Hold the run folder ``out`` (created when missing) while the block writes it; the lock file
    goes when the block ends.

    Args:
        out: the folder.
        lock: its lock file's name; another process holding it refuses this one.
        holder: who holds the lock, as the refusal names it (e.g. "another `mmpc rl train` run").
        fresh: for a run that does not resume, why it refuses a folder holding anything but the
            lock, e.g. "a training run neither resumes nor overwrites one"; ``None``: the run
            resumes what the folder holds (it reads it itself).
        describe: ``describe(out)``: what an occupied folder holds, as words (e.g. "a finished
            run (dqn on safe, seed 0)"; default "files").

    Raises:
        mmpc.files.OutputFolderError: ``out`` cannot be created or written (the message names it
            and the system's reason), another process holds its lock, or (``fresh``) it holds files.
    """
    out = Path(out)
    with contextlib.ExitStack() as stack:
        try:
            out.mkdir(parents=True, exist_ok=True)
            if fresh is not None and not (out / lock).exists():
                _require_empty(out, lock, fresh, describe)  # before the lock file goes in: a refused folder is left as it was
            stack.enter_context(exclusive(out, lock, holder, OutputFolderError, remove=True))
        except OSError as error:
            raise OutputFolderError(f"`out` {out} must be a folder this process can create and write to; got "
                                    f"{type(error).__name__}: {error}") from error
        if fresh is not None:
            _require_empty(out, lock, fresh, describe)
        yield


def _require_empty(out: Path, lock: str, fresh: str, describe: Callable[[Path], str]) -> None:
    names = sorted(p.name for p in out.iterdir() if p.name != lock)
    if names:
        raise OutputFolderError(f"`out` {out} already holds {describe(out)}: {', '.join(names)}; {fresh}: choose another "
                                "--out (or remove that folder)")
