"""Process pools for the stages that spread independent work over the cores.

Workers are *spawned*, not forked: torch's and open3d's thread pools do not survive a fork. Each
worker sets its torch thread count once (one thread by default, so that N workers on N cores do
not fight over them). :func:`finished` walks the futures as they complete and cancels those not
yet started when the caller stops early (a failed task or Ctrl-C), so an error does not wait for
the rest of the queue.
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Iterable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from typing import TypeVar

__all__ = ["finished", "spawn_pool"]

T = TypeVar("T")


def _set_threads(threads: int) -> None:
    import torch

    torch.set_num_threads(threads)


def spawn_pool(workers: int, *, torch_threads: int | None = 1) -> ProcessPoolExecutor:
    """A pool of ``workers`` spawned processes, each with ``torch_threads`` torch threads
    (None: leave torch's default, e.g. when each task sets its own)."""
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    keep = torch_threads is None
    return ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=None if keep else _set_threads,
                               initargs=() if keep else (torch_threads,))


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
