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
            _pools[workers] = ThreadPoolExecutor(workers, _PREFIX, initializer=torch.set_num_threads, initargs=(1,))
        return _pools[workers]


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
