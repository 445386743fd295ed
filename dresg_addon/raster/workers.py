"""Independent pieces of a view (row bands, chunks of Gaussians) run side by side on CPU threads."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import torch


def cpu_workers(device: torch.device, items: int) -> int:
    """How many threads to spread ``items`` pieces over: torch's thread count on CPU, 1 on a GPU."""
    return max(1, min(torch.get_num_threads() if device.type == "cpu" else 1, items))


_PREFIX = "dresg-raster"
_pools: dict[int, ThreadPoolExecutor] = {}
_pool_lock = threading.Lock()


def _pool(workers: int) -> ThreadPoolExecutor:
    """One lasting pool per size: its threads keep their malloc arenas warm from view to view."""
    with _pool_lock:
        if workers not in _pools:
            _pools[workers] = _start_pool(workers)
        return _pools[workers]


def _in_new_thread(function):
    result = []
    thread = threading.Thread(target=lambda: result.append(function()), name=f"{_PREFIX}-setup")
    thread.start()
    thread.join()
    return result[0]


def _start_pool(workers: int) -> ThreadPoolExecutor:
    """A pool of ``workers`` threads, started now, each running torch with one thread.

    torch hands every thread started later the count last set on any thread: left at the pool's 1, a
    host's next thread (a Blender job's worker) would run torch on one thread. So the count new threads
    got before is set back, from a throwaway thread so that the caller's own count is not touched.
    """
    for_new_threads = _in_new_thread(torch.get_num_threads)
    pool = ThreadPoolExecutor(workers, _PREFIX, initializer=torch.set_num_threads, initargs=(1,))
    started = threading.Barrier(workers, timeout=60)
    list(pool.map(lambda _: started.wait(), range(workers)))  # every thread has run its initializer
    _in_new_thread(lambda: torch.set_num_threads(for_new_threads))
    return pool


def in_workers(work, items, workers: int) -> list:
    """[work(worker, item) for item in items], spread over ``workers`` threads with one torch thread each.

    Torch releases the GIL inside each op, so whole pieces run side by side; on a small CPU that beats
    splitting every small op over threads. The pool's threads run torch with one thread each (set for
    those threads only: the caller's setting is left alone). Worker j takes items j, j + workers, ...:
    a fixed split, so per-worker partial sums (and so the results) do not depend on timing.
    """
    if workers <= 1 or len(items) <= 1 or threading.current_thread().name.startswith(_PREFIX):
        # (from inside a pool thread, waiting on the same pool could deadlock: run in this thread)
        return [work(0, item) for item in items]
    results = [None] * len(items)

    def run(worker):
        for i in range(worker, len(items), workers):
            results[i] = work(worker, items[i])

    for future in [_pool(workers).submit(run, w) for w in range(workers)]:
        future.result()
    return results
