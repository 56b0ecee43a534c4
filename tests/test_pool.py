"""couch.pool: spawned workers with one thread per library, and early stops that cancel the
queue."""

from __future__ import annotations

import math
import textwrap
import time

import pytest
import torch

from couch.pool import finished, pool_map, spawn_pool


def _threads() -> tuple[int, int, int, list[int]]:
    import cv2
    import open3d
    from threadpoolctl import threadpool_info

    blas = [p["num_threads"] for p in threadpool_info() if p["internal_api"] == "openblas"]
    return (torch.get_num_threads(), open3d.utility.get_max_threads(), cv2.getNumThreads(),
            blas)


def test_workers_run_one_thread_of_each_library():
    """Two workers on two cores: torch, open3d's TBB, OpenCV and numpy's OpenBLAS each on one
    thread in each (their defaults start one per core in every worker)."""
    with spawn_pool(2) as pool:
        seen = [pool.submit(_threads).result() for _ in range(4)]
    for torch_n, open3d_n, cv2_n, blas in seen:
        assert (torch_n, open3d_n, cv2_n) == (1, 1, 1)
        assert blas and set(blas) == {1}, blas  # found (numpy's at least), each on one thread


def test_a_failed_task_cancels_the_tasks_not_started():
    with spawn_pool(1, threads=None) as pool:
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


def test_pool_map_keeps_the_order_and_takes_keywords():
    tasks = [(9.0,), (4.0,), (1.0,)]
    with spawn_pool(2, threads=None) as pool:
        assert pool_map(pool, math.sqrt, tasks) == [3.0, 2.0, 1.0]
        assert pool_map(pool, textwrap.shorten, [dict(text="a bb ccc dddd", width=9),
                                                 dict(text="a bb", width=9)]) == ["a [...]",
                                                                                  "a bb"]
        with pytest.raises(ValueError, match="math domain error"):
            pool_map(pool, math.sqrt, [(1.0,), (-1.0,)])
    # without a pool: the same, here
    assert pool_map(None, math.sqrt, tasks) == [3.0, 2.0, 1.0]
    assert pool_map(None, textwrap.shorten, [dict(text="a bb", width=9)]) == ["a bb"]


def test_preloaded_workers_have_the_modules_when_started():
    loaded = "'{}' in __import__('sys').modules"
    with spawn_pool(1, preload=("xml.dom.minidom",), start=True) as pool:
        assert pool.submit(eval, loaded.format("xml.dom.minidom")).result()
        assert not pool.submit(eval, loaded.format("xml.sax")).result()
