"""How torch's CPU threads wait and how many run: a policy for the code that owns the process or thread.

The CLI's ``main`` and the benchmark workers own their process and call :func:`apply_thread_policy`
before torch loads; they and the Blender job's worker thread adapt their own thread's count with a
:class:`ThreadAdapter`. Importing the engine or rendering changes neither: in Blender the process is
Blender's (no torch import here).

torch's CPU build runs its ops on an OpenMP (libgomp) pool whose threads spin after each op before
they sleep (300,000 spins by default). On a quiet machine that saves a wake-up per op; on a busy one
the spinning threads take the cores the work needs. Measured on 2 cores, rendering 17 bonsai views at
448x320 through the CLI: 4.5 s quiet; next to another torch process doing small ops (whose threads
spin too) 106 s by default, 9.5 s with a spin count of 2,000 and 6.9 s with passive waiting; next to
a pure-Python busy loop 8.7 s by default and 8.8 s with 2,000 spins. Passive waiting costs ~15% on a
quiet machine, 2,000 spins nothing measurable, so the policy sets 2,000 (docs/decisions/014-thread-policy.md).

What the user set in the environment wins, and nothing changes once torch is loaded (libgomp reads
these variables once). The load average cannot tell another job's load from this process's own recent
work, so the policy does not depend on it.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable

SPIN_COUNT = "2000"
USER_SETTINGS = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")


def apply_thread_policy(environ=os.environ) -> str:
    """Set a short OpenMP spin in ``environ`` unless torch is loaded or the user chose one; says what."""
    if "torch" in sys.modules:
        return "torch already loaded: its thread policy is left as is"
    if any(name in environ for name in USER_SETTINGS):
        return "thread policy from the environment"
    environ["GOMP_SPINCOUNT"] = SPIN_COUNT
    return f"GOMP_SPINCOUNT={SPIN_COUNT}"


ADAPT_VARIABLE = "DRESG_ADAPTIVE_THREADS"  # "0" keeps torch's thread count fixed (bit-exact comparisons)
ADAPT_INTERVAL_S = 2.0  # shortest window the other processes' load is measured over
BUSY_CORE = 0.75  # another process using this much of a core over the window counts as taking it


class CoreMonitor:
    """How many of this process's usable cores other processes kept busy (Linux /proc/stat; else none).

    Busy time of the usable cores (their ``cpuN`` lines) minus this process's own CPU time, over the
    time since the last look.
    """

    def __init__(self) -> None:
        self._cores = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
        self.cores = len(self._cores)
        self._tick = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
        self._last = self._sample()

    def _sample(self) -> tuple[float, float, float] | None:  # (monotonic s, busy core-s, own CPU s)
        try:
            with open("/proc/stat", encoding="ascii") as handle:
                lines = handle.read().splitlines()
        except OSError:
            return None
        wanted = {f"cpu{core}" for core in self._cores}
        busy = 0.0
        for line in lines:
            fields = line.split()
            if fields and fields[0] in wanted:
                values = [float(v) for v in fields[1:]]
                busy += sum(values) - values[3] - (values[4] if len(values) > 4 else 0.0)  # minus idle, iowait
        own = os.times()
        return time.monotonic(), busy / self._tick, own.user + own.system

    def others_busy(self, min_interval_s: float = ADAPT_INTERVAL_S) -> float | None:
        """Cores other processes used on average since the last call, or None (too soon, or unknown)."""
        if self._last is None or time.monotonic() - self._last[0] < min_interval_s:
            return None  # checked before reading /proc: this runs before every render and colour step
        now = self._sample()
        if now is None:
            return None
        (t0, busy0, own0), (t1, busy1, own1) = self._last, now
        self._last = now
        return max(0.0, ((busy1 - busy0) - (own1 - own0)) / (t1 - t0))


def threads_for_load(others_busy: float, cores: int, preferred: int) -> int:
    """Torch threads for the cores other processes leave free (at least 1, at most ``preferred``)."""
    taken = int(others_busy / BUSY_CORE) if others_busy > 0 else 0
    return max(1, min(preferred, cores - min(taken, cores)))


class ThreadAdapter:
    """Matches torch's CPU threads on one thread to the cores other processes leave free.

    Owned by whoever owns the thread that runs torch (the CLI's ``main``, a benchmark worker, the Blender
    job's worker thread) and called by it between steps (:meth:`wrap` a progress callback): never by the
    engine, which runs in processes it does not own (Blender). torch's count is per thread, so call it on
    the thread that renders. Measures at most every 2 s. Threads that spin or wait on a core another
    process holds make every op wait for them (5-24x slower on 2 cores); one thread per free core keeps the
    slowdown near the share of cores taken. A count the owner sets with ``torch.set_num_threads`` becomes
    the new ceiling; ``DRESG_ADAPTIVE_THREADS=0`` in the environment turns this off.
    """

    def __init__(self, environ=os.environ) -> None:
        self.enabled = environ.get(ADAPT_VARIABLE, "1") != "0"
        self._monitor: CoreMonitor | None = None
        self._preferred: int | None = None  # the count without load: the thread's own, or its owner's latest choice
        self._last_set: int | None = None  # the count as this adapter last left it

    def adapt(self) -> int | None:
        """Set the calling thread's torch threads for the current load; the new count when it changed."""
        if not self.enabled:
            return None
        import torch

        current = torch.get_num_threads()
        if self._monitor is None or current != self._last_set:  # first call, or the owner chose a count since
            if self._monitor is None:
                self._monitor = CoreMonitor()
            self._preferred = self._last_set = current
            return None
        others = self._monitor.others_busy()
        if others is None:
            return None
        wanted = threads_for_load(others, max(self._monitor.cores, 1), self._preferred)
        if wanted == current:
            return None
        torch.set_num_threads(wanted)
        self._last_set = wanted
        return wanted

    def restore(self) -> None:
        """Put back the count the thread had before any change (torch hands the last count set to new threads)."""
        if self._preferred is not None and self._last_set != self._preferred:
            import torch

            torch.set_num_threads(self._preferred)
            self._last_set = self._preferred

    def wrap(self, callback: Callable | None) -> Callable:
        """``callback`` (may be None) that adapts first: a progress callback the engine calls between its steps."""

        def adapting(*args, **kwargs):
            self.adapt()
            return None if callback is None else callback(*args, **kwargs)

        return adapting
