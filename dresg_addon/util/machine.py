"""The machine a measurement ran on, for benchmark and report headers (no torch import)."""

from __future__ import annotations

import os
import platform


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo, else what ``platform`` knows."""
    try:
        with open("/proc/cpuinfo") as info:
            for line in info:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def usable_cores() -> int:
    """Cores this process may run on (its affinity where the OS has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def load_average(digits: int = 2) -> str:
    """'1-min, 5-min, 15-min' load averages, or 'n/a' where the OS has none."""
    return ", ".join(f"{v:.{digits}f}" for v in os.getloadavg()) if hasattr(os, "getloadavg") else "n/a"


def available_memory_bytes() -> int | None:
    """Memory the kernel says new allocations can get without swapping (MemAvailable), or None when unknown."""
    try:
        with open("/proc/meminfo", encoding="ascii") as handle:
            for line in handle:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None
