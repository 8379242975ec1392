"""Where tasks run: in this process, in a pool of spawned worker processes, or as Ray tasks.

The one worker pool of mmpc: the evaluation, the expert demonstrations and DAgger's rollouts
all hand their tasks to :func:`run_tasks`. A task is any picklable object with a ``label``
(text for messages); ``run(task)`` (a module-level function, so that a worker can import it)
returns the task's result. Results come back to the calling process in completion order, so
that only it writes files that collect them.

A task fails as ``failed(task, error)``, whose return value stands for the result (or which
raises to stop the run): ``error`` is the exception ``run`` raised, or a message when the task's
worker process died ``retries + 1`` times or Ray could not run it.
"""

from __future__ import annotations

import ctypes
import logging
import multiprocessing
import os
import signal
import socket
import sys
from collections import deque
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Callable, Iterator, Optional, Sequence, TypeVar

import torch

from mmpc.config import require_int
from mmpc.solver.execution import COMPILE_ENV

logger = logging.getLogger(__name__)

Task = TypeVar("Task")
Result = TypeVar("Result")


@dataclass(frozen=True)
class Backend:
    """Where and how tasks run.

    Attributes:
        workers: tasks in flight at once: 1 runs them one after the other in this process, more
            in a pool of that many spawned worker processes; with ``ray``: ``None`` takes the
            cluster's CPU count.
        threads: torch threads while a task runs.
        ray: ``None`` (this machine), ``"local"`` (start a local Ray with ``workers`` CPUs),
            ``"auto"`` or a cluster address (``"host:6379"``, ``"ray://host:10001"``). A Ray
            already initialised in this process is used as it is.
        retries: how many more times a task in flight when its worker died is run (alone)
            before it fails.
    """

    workers: Optional[int] = 1
    threads: int = 1
    ray: Optional[str] = None
    retries: int = 1

    def __post_init__(self) -> None:
        if self.workers is None and self.ray is None:
            raise ValueError("`workers` may be None (the cluster's CPUs) only with `ray`; got workers=None, ray=None")
        require_int("", low=1, **{name: value for name, value in (("workers", self.workers), ("threads", self.threads))
                                   if value is not None})
        require_int("", low=0, retries=self.retries)
        if self.ray is not None and (not isinstance(self.ray, str) or not self.ray):
            raise ValueError(f"`ray` must be None, 'local', 'auto' or a cluster address; got {self.ray!r}")

    @property
    def name(self) -> str:
        """``ray``, ``processes`` or ``in-process``."""
        return "ray" if self.ray is not None else "processes" if self.workers != 1 else "in-process"


def worker_name() -> str:
    """``host:pid`` of the running process."""
    return f"{socket.gethostname()}:{os.getpid()}"


def error_text(error: BaseException) -> str:
    """An exception as one line of at most 500 characters (type and message)."""
    text = f"{type(error).__name__}: {error}".replace("\n", " ").replace("\r", " ")
    return text[:500]


def _label(task: object) -> str:
    return str(getattr(task, "label", task))


#: ``prctl`` option: the signal the kernel sends this process when its parent dies (linux/prctl.h).
PR_SET_PDEATHSIG = 1


def _init_worker(parent: int) -> None:
    """A worker process leaves Ctrl-C to the coordinating process ``parent``, which terminates
    it, and ends when ``parent`` dies, even by SIGKILL (no time to terminate it): on Linux the
    kernel kills it (``PR_SET_PDEATHSIG``, chosen over a thread polling ``os.getppid()`` because it
    needs no interpreter, so a worker busy in a solve goes at once), and one whose parent died
    before that exits here. (The kernel reacts to the end of the thread that started the worker:
    the one iterating :func:`run_tasks`.) Elsewhere workers outlive a killed parent."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:
        os._exit(1)


def _run_with_threads(run: Callable[[Task], Result], threads: int, task: Task) -> Result:
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        return run(task)
    finally:
        torch.set_num_threads(previous)


def run_tasks(
    tasks: Sequence[Task],
    run: Callable[[Task], Result],
    failed: Callable[[Task, BaseException | str], Result],
    backend: Backend = Backend(),
) -> Iterator[tuple[Task, Result]]:
    """Run every task on ``backend``; yield ``(task, result)`` as each one finishes.

    Args:
        tasks: picklable tasks (their ``label`` names them in messages).
        run: ``run(task) -> result``, a module-level function.
        failed: ``failed(task, error) -> result`` for a task that raised or could not be run.
        backend: where they run.
    """
    if backend.ray is not None:
        return _ray(tasks, run, failed, backend)
    if backend.workers == 1:
        return _in_process(tasks, run, failed, backend.threads)
    return _process_pool(tasks, run, failed, backend)


def _in_process(tasks, run, failed, threads: int) -> Iterator[tuple]:
    for task in tasks:
        try:
            result = _run_with_threads(run, threads, task)
        except Exception as error:  # noqa: BLE001 - failed() decides what a failure becomes
            result = failed(task, error)
        yield task, result


def _process_pool(tasks, run, failed, backend: Backend) -> Iterator[tuple]:
    """Tasks in a pool of spawned processes, at most ``backend.workers`` in flight.

    When a worker dies the pool breaks and every task in flight fails with it; the pool is
    recreated and those tasks (suspects) are run one at a time, alone, so a death then blames
    exactly one task: it is run again up to ``retries`` times, then it fails.
    """
    normal = deque(tasks)
    suspects: deque = deque()
    deaths: dict[int, int] = {}  # id(task) -> deaths of its worker while it ran alone
    context = multiprocessing.get_context("spawn")
    while normal or suspects:
        pool = ProcessPoolExecutor(backend.workers, mp_context=context, initializer=_init_worker,
                                   initargs=(os.getpid(),))
        running: dict[Future, object] = {}
        isolated = False  # the one task in flight is a suspect running alone
        try:
            while normal or suspects or running:
                if suspects:
                    if not running:
                        task = suspects.popleft()
                        running[pool.submit(_run_with_threads, run, backend.threads, task)] = task
                        isolated = True
                else:
                    isolated = False
                    while normal and len(running) < backend.workers:
                        task = normal.popleft()
                        running[pool.submit(_run_with_threads, run, backend.threads, task)] = task
                done, _ = wait(running, return_when=FIRST_COMPLETED)
                broken = False
                for future in done:  # tasks that finished before a break keep their results
                    error = future.exception()
                    if isinstance(error, BrokenProcessPool):
                        broken = True
                        continue
                    task = running.pop(future)
                    yield task, failed(task, error) if error is not None else future.result()
                if broken:
                    raise BrokenProcessPool("a worker process died")
        except BrokenProcessPool:
            pool.shutdown(wait=True, cancel_futures=True)
            for task in running.values():
                if isolated:
                    deaths[id(task)] = deaths.get(id(task), 0) + 1
                    if deaths[id(task)] > backend.retries:
                        logger.error("%s: its worker died %d times", _label(task), deaths[id(task)])
                        yield task, failed(task, f"worker process died {deaths[id(task)]} times running this task")
                        continue
                logger.warning("%s: a worker process died; running the task again, alone", _label(task))
                suspects.append(task)
        except BaseException:  # interrupted (Ctrl-C, SIGTERM as KeyboardInterrupt): do not wait for the tasks
            for process in list(getattr(pool, "_processes", {}).values()):
                process.terminate()
            pool.shutdown(wait=False, cancel_futures=True)
            raise
        else:
            pool.shutdown(wait=True)


def _ray(tasks, run, failed, backend: Backend) -> Iterator[tuple]:
    """Ray tasks (1 CPU each), at most ``workers`` in flight; a task whose worker died is retried
    by Ray ``retries`` times, then it fails."""
    try:
        import ray
    except ImportError as error:
        raise ImportError("the `ray` backend needs Ray: pip install 'mmpc[ray]'") from error
    started = False
    if not ray.is_initialized():
        if backend.ray == "local":
            ray.init(num_cpus=backend.workers, include_dashboard=False, log_to_driver=False)
        else:
            ray.init(address=backend.ray, log_to_driver=False)
        started = True
    try:
        workers = backend.workers or max(1, int(ray.cluster_resources().get("CPU", 1)))
        # the compile setting (--compile, MMPC_COMPILE) travels with the tasks to every node
        env_vars = {COMPILE_ENV: os.environ[COMPILE_ENV]} if COMPILE_ENV in os.environ else {}
        remote = ray.remote(num_cpus=1, max_retries=backend.retries, runtime_env={"env_vars": env_vars})(_run_with_threads)
        pending = deque(tasks)
        running: dict = {}
        while pending or running:
            while pending and len(running) < workers:
                task = pending.popleft()
                running[remote.remote(run, backend.threads, task)] = task
            done, _ = ray.wait(list(running), num_returns=1)
            for ref in done:
                task = running.pop(ref)
                try:
                    result = ray.get(ref)
                except ray.exceptions.RayTaskError as error:  # run() raised: its own exception
                    result = failed(task, error.as_instanceof_cause())
                except ray.exceptions.RayError as error:
                    logger.error("%s failed on Ray: %s", _label(task), error_text(error))
                    result = failed(task, error)
                yield task, result
    finally:
        if started:
            ray.shutdown()
