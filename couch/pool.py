"""Process pools for the stages that spread independent work over the cores.

Workers are *spawned*, not forked: torch's and open3d's thread pools do not survive a fork. Each
worker sets the thread count of torch, open3d (TBB), OpenCV and numpy's BLAS once (one thread by
default, so that N workers on N cores do not fight over them) and may import modules as it
starts (``preload``: a worker's first import of torch and open3d takes seconds); a worker ends
itself within a second of the process that made the pool being killed.
:func:`finished` walks the futures as they complete and cancels those not yet started when the
caller stops early (a failed task or Ctrl-C), so an error does not wait for the rest of the
queue. :func:`pool_map` is the stages' way to run independent tasks on a pool if they are given
one (:data:`Pool`), in their own process if not, with the same results.
"""

from __future__ import annotations

import contextlib
import importlib
import multiprocessing
import os
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Executor, Future, ProcessPoolExecutor, as_completed
from typing import Any, TypeVar

__all__ = ["Pool", "finished", "limited_threads", "pool_map", "spawn_pool"]

T = TypeVar("T")

Pool = Executor | None
"""Where a stage's independent tasks run: an executor (e.g. :func:`spawn_pool`), or None: one
after another in this process."""


def _exit_with(parent: int, poll_s: float = 1.0) -> None:
    """In a worker: end the process once ``parent`` is gone. A pool's workers wait on a queue
    whose write end they hold themselves, so when the process that made the pool is killed
    (SIGTERM, SIGKILL, a job scheduler's limit) nothing tells them: they would draw the tasks
    already queued and then wait for ever, holding their memory."""
    while os.getppid() == parent:
        time.sleep(poll_s)
    os._exit(1)


def _set_library_threads(threads: int | tuple[int, int, int]) -> tuple[int, int, int]:
    """Set torch's, open3d's and OpenCV's thread counts (one for all, or one each in that
    order); returns the counts they had."""
    import cv2
    import open3d
    import torch

    torch_n, open3d_n, cv2_n = (threads,) * 3 if isinstance(threads, int) else threads
    before = (torch.get_num_threads(), open3d.utility.get_max_threads(), cv2.getNumThreads())
    torch.set_num_threads(torch_n)
    open3d.utility.set_max_threads(open3d_n)  # its TBB pool (OMP_NUM_THREADS is not read)
    cv2.setNumThreads(cv2_n)
    return before


def _set_threads(threads: int | None, preload: tuple[str, ...] = (),
                 parent: int | None = None) -> None:
    if parent is not None:
        threading.Thread(target=_exit_with, args=(parent,), daemon=True,
                         name="couch-pool-parent-watch").start()
    if threads is not None:
        from threadpoolctl import threadpool_limits

        _set_library_threads(threads)
        threadpool_limits(threads)  # numpy's OpenBLAS: its threads start with a large product
    for name in preload:
        importlib.import_module(name)


@contextlib.contextmanager
def limited_threads(threads: int = 1) -> Iterator[None]:
    """Run the body on ``threads`` threads of torch, open3d, OpenCV and numpy's BLAS, as a
    :func:`spawn_pool` worker runs its tasks, and restore the counts after. What a task
    computes can change in the last bits with the thread count (reductions split differently)
    and a marginal decision with them, so a stage that runs its tasks here when it has no pool
    gives the files its pool gives."""
    from threadpoolctl import threadpool_limits

    before = _set_library_threads(threads)
    try:
        with threadpool_limits(threads):
            yield
    finally:
        _set_library_threads(before)


def spawn_pool(workers: int, *, threads: int | None = 1, preload: Sequence[str] = (),
               start: bool = False) -> ProcessPoolExecutor:
    """A pool of ``workers`` spawned processes, each running torch, open3d, OpenCV and numpy's
    BLAS on ``threads`` threads (None: leave their defaults, e.g. when each task sets its own),
    each importing the modules ``preload`` as it starts. ``start``: start every worker now
    (else each starts with the task that needs it), so that their imports run while the caller
    works."""
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    pool = ProcessPoolExecutor(max_workers=workers,
                               mp_context=multiprocessing.get_context("spawn"),
                               initializer=_set_threads,
                               initargs=(threads, tuple(preload), os.getpid()))
    if start:
        for _ in range(workers):  # a spawned pool starts a process per task it is given
            pool.submit(int)
    return pool


def finished(futures: Iterable[Future[T]]) -> Iterator[Future[T]]:
    """The futures in the order they finish (``as_completed``); when the loop over them ends
    early (an exception in its body or in ``result()``, Ctrl-C, ``break``), the ones that have
    not started are cancelled."""
    futures = list(futures)
    try:
        yield from as_completed(futures)
    finally:
        for fut in futures:
            fut.cancel()  # a no-op for the finished and the running ones


def pool_map(pool: Pool, fn: Callable[..., T],
             tasks: Iterable[tuple[Any, ...] | dict[str, Any]], *,
             desc: str | None = None, unit: str = "task") -> list[T]:
    """``[fn(*args) for args in tasks]`` (``fn(**args)`` for a dict), on ``pool`` when one is
    given (``fn`` and the arguments must then pickle: a module-level function, plain data), in
    this process otherwise. Results come in the order of ``tasks``; the first task to fail
    raises its exception and the tasks not yet started are cancelled. ``desc``: a progress bar
    over the tasks as they finish."""
    from tqdm import tqdm

    tasks = list(tasks)
    with tqdm(total=len(tasks), desc=desc, unit=unit, disable=desc is None) as bar:
        if pool is None or len(tasks) < 2:
            out = []
            for args in tasks:
                out.append(fn(**args) if isinstance(args, dict) else fn(*args))
                bar.update()
            return out
        futures = [pool.submit(fn, **args) if isinstance(args, dict) else pool.submit(fn, *args)
                   for args in tasks]
        for fut in finished(futures):
            fut.result()  # the first failure raises here, as it comes
            bar.update()
        return [fut.result() for fut in futures]
