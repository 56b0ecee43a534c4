"""couch.pool: spawned workers with one torch thread, and early stops that cancel the queue."""

from __future__ import annotations

import math
import time

import pytest
import torch

from couch.pool import finished, spawn_pool


def test_workers_run_one_torch_thread_each():
    with spawn_pool(2) as pool:
        threads = {pool.submit(torch.get_num_threads).result() for _ in range(4)}
    assert threads == {1}


def test_a_failed_task_cancels_the_tasks_not_started():
    with spawn_pool(1, torch_threads=None) as pool:
        # the first task fails while the slow ones wait in the queue
        futures = [pool.submit(math.sqrt, -1.0)] + [pool.submit(time.sleep, 1.0)
                                                    for _ in range(10)]
        with pytest.raises(ValueError, match="math domain error"):
            for fut in finished(futures):
                fut.result()
    # one worker runs one sleep and holds two more in its queue, which cannot be cancelled; two
    # more of slack for a loaded machine
    assert sum(f.cancelled() for f in futures) >= 5


def test_no_workers_is_an_error():
    with pytest.raises(ValueError, match="workers must be >= 1"):
        spawn_pool(0)
