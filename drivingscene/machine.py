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


MEMORY_LIMIT_ENV = "DRIVINGSCENE_MEMORY_LIMIT"
_UNITS = {"": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}


def available_memory_bytes() -> int:
    """Bytes this process may still allocate: ``DRIVINGSCENE_MEMORY_LIMIT`` (bytes, or with a K, M,
    G or T suffix, binary) where set, else the kernel's MemAvailable, capped by the room left under a
    cgroup (container) memory limit, which is what the OOM killer enforces, and under the process's
    address-space limit (``ulimit -v``)."""
    text = os.environ.get(MEMORY_LIMIT_ENV, "").strip()
    if text:
        from drivingscene.errors import InputError

        unit = text[-1].upper() if text[-1].isalpha() else ""
        try:
            value = float(text[: len(text) - len(unit)]) * _UNITS[unit]
        except (KeyError, ValueError):
            value = -1
        if not value >= 0:
            raise InputError(f"{MEMORY_LIMIT_ENV}: expected a number of bytes (e.g. 8G), found {text!r}")
        return int(value)
    rooms = [r for r in (_cgroup_room(), _address_space_room()) if r is not None]
    return min([_meminfo_available(), *rooms])


def _meminfo_available() -> int:
    try:
        with open("/proc/meminfo") as f:
            return next(int(line.split()[1]) for line in f if line.startswith("MemAvailable:")) * 1024
    except (OSError, StopIteration, ValueError):
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def _address_space_room() -> int | None:
    """Bytes of address space left under the process's ``ulimit -v`` (RLIMIT_AS), None without one:
    past it an allocation fails however much memory the machine has."""
    import resource

    limit = resource.getrlimit(resource.RLIMIT_AS)[0]
    if limit == resource.RLIM_INFINITY:
        return None
    try:
        with open("/proc/self/status") as f:
            used = next(int(line.split()[1]) for line in f if line.startswith("VmSize:")) * 1024
    except (OSError, StopIteration, ValueError):
        return None
    return max(0, limit - used)


def _cgroup_room() -> int | None:
    """Bytes left under the cgroup v2 memory limit, None without one."""
    try:
        with open("/sys/fs/cgroup/memory.max") as f:
            limit = f.read().strip()
        if limit == "max":
            return None
        with open("/sys/fs/cgroup/memory.current") as f:
            return max(0, int(limit) - int(f.read().strip()))
    except (OSError, ValueError):
        return None


def gib(num_bytes: float) -> str:
    """``12.3 GiB`` (one decimal; two below 1 GiB)."""
    value = num_bytes / 2**30
    return f"{value:.1f} GiB" if value >= 1 else f"{value:.2f} GiB"
