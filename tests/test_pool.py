"""couch.pool: spawned workers with one thread per library, and early stops that cancel the
queue."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest
import torch

from couch.pool import finished, limited_threads, pool_map, spawn_pool


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


def _gone(pid: int) -> bool:
    """True once ``pid`` has exited (a zombie nobody reaps counts: it has ended)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] in ("Z", "X")
    except FileNotFoundError:
        return True


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_workers_end_when_the_process_that_made_the_pool_is_killed(tmp_path):
    # Killed without a chance to clean up (SIGKILL; a scheduler's SIGTERM is the same to the
    # workers), the pool's owner leaves its worker in a 60 s task with more queued: the worker
    # ends itself instead of running the queue and then waiting for ever.
    script = textwrap.dedent("""
        import os, signal, time
        from couch.pool import spawn_pool
        pool = spawn_pool(1, threads=None)
        print(pool.submit(os.getpid).result(), flush=True)
        for _ in range(3):
            pool.submit(time.sleep, 60)
        time.sleep(0.5)
        os.kill(os.getpid(), signal.SIGKILL)
    """)
    # a file, not a pipe: the worker inherits it, and a pipe would stay open while it lives
    with open(tmp_path / "out", "w") as out:
        run = subprocess.run([sys.executable, "-c", script], stdout=out, stderr=out, timeout=60)
    said = (tmp_path / "out").read_text()
    assert run.returncode == -signal.SIGKILL, said
    worker = int(said.split()[0])
    deadline = time.monotonic() + 15
    while not _gone(worker) and time.monotonic() < deadline:
        time.sleep(0.2)
    if not _gone(worker):
        os.kill(worker, signal.SIGKILL)  # not left behind by a failing run
        pytest.fail(f"worker {worker} still running 15 s after its parent was killed")


def test_limited_threads_runs_here_as_a_worker_and_restores():
    outside = _threads()
    with limited_threads(2):  # counts to come back to, whatever pytest's worker runs on
        two = _threads()
        assert two[:3] == (2, 2, 2)
        with limited_threads(1):
            torch_n, open3d_n, cv2_n, blas = _threads()
            assert (torch_n, open3d_n, cv2_n) == (1, 1, 1) and set(blas) == {1}
        assert _threads() == two
    assert _threads() == outside
