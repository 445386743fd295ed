"""Independent pieces of a view (row bands, chunks of Gaussians) run side by side on CPU threads."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import torch


def cpu_workers(device: torch.device, items: int) -> int:
    """How many threads to spread ``items`` pieces over: torch's thread count on CPU, 1 on a GPU."""
    return max(1, min(torch.get_num_threads() if device.type == "cpu" else 1, items))


_PREFIX = "dresg-raster"


def _in_new_thread(function):
    result = []
    thread = threading.Thread(target=lambda: result.append(function()), name=f"{_PREFIX}-setup")
    thread.start()
    thread.join()
    return result[0]


def _one_torch_thread() -> None:
    # torch sets a thread up on its first call there, from the count last set on any thread: done first, so
    # that no later setting elsewhere (as _start's own below) overrides this thread's count of 1.
    torch.get_num_threads()
    torch.set_num_threads(1)


class WorkerPool:
    """Lasting threads, one torch thread each, started on first use; :meth:`shutdown` ends them (a later
    :meth:`map` starts them again). One pool per size: its threads keep their malloc arenas warm from view
    to view."""

    def __init__(self) -> None:
        self._executors: dict[int, ThreadPoolExecutor] = {}
        self._lock = threading.Lock()

    @property
    def threads(self) -> int:
        """How many threads the pool holds now."""
        with self._lock:
            return sum(self._executors)

    def map(self, work, items, workers: int) -> list:
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

        with self._lock:  # submitted under the lock: a shutdown on another thread waits for these, not fails them
            if workers not in self._executors:
                self._executors[workers] = self._start(workers)
            futures = [self._executors[workers].submit(run, w) for w in range(workers)]
        for future in futures:
            future.result()
        return results

    def shutdown(self) -> None:
        """End the threads once the work already given to them is done."""
        with self._lock:
            executors, self._executors = list(self._executors.values()), {}
        for executor in executors:
            executor.shutdown(wait=True)

    @staticmethod
    def _start(workers: int) -> ThreadPoolExecutor:
        """``workers`` threads, started now, each running torch with one thread.

        torch hands every thread started later the count last set on any thread: left at the pool's 1, a
        host's next thread (a Blender job's worker) would run torch on one thread. So the count new threads
        got before is set back, from a throwaway thread so that the caller's own count is not touched.
        """
        for_new_threads = _in_new_thread(torch.get_num_threads)
        executor = ThreadPoolExecutor(workers, _PREFIX, initializer=_one_torch_thread)
        started = threading.Barrier(workers, timeout=60)
        list(executor.map(lambda _: started.wait(), range(workers)))  # every thread has run its initializer
        _in_new_thread(lambda: torch.set_num_threads(for_new_threads))
        return executor


POOL = WorkerPool()  # the rasterizer's; the Blender add-on shuts it down when it is disabled


def in_workers(work, items, workers: int) -> list:
    """:meth:`WorkerPool.map` on :data:`POOL`."""
    return POOL.map(work, items, workers)


def shutdown() -> None:
    """End :data:`POOL`'s threads (the next render starts them again)."""
    POOL.shutdown()
