"""When the check runs compiled: one policy for its compiled parts (the fail-safe rollout and the
occupancy sets), whose eager time counts together."""

from __future__ import annotations

import logging
import time
from typing import Callable, Optional, TypeVar

import torch

from mmpc.solver import execution

logger = logging.getLogger(__name__)

#: ``compile="auto"``: seconds of eager checking after which the check's parts are compiled: about
#: what compiling them costs (~90 s on one core the first time, ~10 s from inductor's on-disk
#: cache), so a short run never pays much more than it saves.
CHECK_COMPILE_AFTER_S = 20.0

Result = TypeVar("Result")


class CheckCompiling:
    """Whether the check's parts run compiled (``torch.compile`` with dynamic shapes: one compile
    serves every batch).

    Args:
        compile: ``"auto"``: compiled where a C++ compiler is found, once the eager parts have taken
            :data:`CHECK_COMPILE_AFTER_S` (``MMPC_COMPILE=0``: never, ``1``: at the first call, as the
            solver's ``--compile off|on``); ``True``: at the first call; ``False``: eager.
    """

    def __init__(self, compile: bool | str = "auto") -> None:
        compile_after = 0.0
        if compile == "auto":
            setting = execution.compile_setting()
            compile = execution.kernel_compiler_found(on_cpu=True) if setting is None else setting
            compile_after = CHECK_COMPILE_AFTER_S if setting is None else 0.0
        if not isinstance(compile, bool):
            raise ValueError(f"`compile` must be True, False or 'auto'; got {compile!r}")
        self.compile, self.compile_after = compile, compile_after
        self.eager_seconds = 0.0  # spent in the eager parts so far [s]

    @property
    def compiled(self) -> bool:
        """Whether the parts run compiled now."""
        return self.compile and self.eager_seconds >= self.compile_after

    def eager(self, function: Callable[..., Result], *args, **kwargs) -> Result:
        """``function(*args, **kwargs)``, its time counted towards compiling."""
        started = time.perf_counter()
        try:
            return function(*args, **kwargs)
        finally:
            self.eager_seconds += time.perf_counter() - started

    def attempt(self, compiled_call: Callable[[], Result]) -> Optional[Result]:
        """``compiled_call()`` within the process's recompile limit; past it ``None`` (warned once,
        compiling off from then on), and the caller runs its eager path."""
        try:
            with torch._dynamo.config.patch(recompile_limit=execution.RECOMPILE_LIMIT):
                return compiled_call()
        except torch._dynamo.exc.FailOnRecompileLimitHit:
            logger.warning("the check: %d compiled layouts in this process (the limit); checking eagerly from now on",
                           execution.RECOMPILE_LIMIT)
            self.compile = False
            return None
