"""What a benchmark ran on: every reported figure names its machine (these machines are shared)."""

from __future__ import annotations

import os
import platform
import resource


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            return next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        return platform.processor() or "unknown CPU"


def usable_cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def machine_description(*extra: str) -> str:
    """CPU model, usable cores, torch and its threads, load average, plus ``extra`` facts."""
    import torch

    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    parts = [cpu_model(), f"{usable_cores()} usable cores", f"torch {torch.__version__} with {torch.get_num_threads()} threads"]
    parts += list(extra) + [f"load average {load} (shared machine)"]
    return ", ".join(parts)


def peak_rss_bytes() -> int:
    """Peak resident memory of this process so far: Linux's VmHWM, which a spawned process starts
    afresh (``ru_maxrss`` keeps the parent's resident memory at the fork across the exec), else
    ``ru_maxrss`` (KiB on Linux)."""
    try:
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith("VmHWM:")) * 1024
    except (OSError, StopIteration, ValueError):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def current_rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
