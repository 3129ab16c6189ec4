"""Compute threads per worker: the cores this process may use, shared among the workers on
this host.

With ``PBRSR_WORKER_THREADS=0`` (automatic), each worker takes
``max(1, cores // workers)`` threads. ``cores`` is the smallest of the CPUs in the process's
affinity mask (``os.sched_getaffinity``, else ``os.cpu_count``) and the cgroup CPU quota
(``/sys/fs/cgroup/cpu.max``, rounded down). ``workers`` is ``PBRSR_WORKERS_PER_HOST``, or,
when that is 0, the number of live workers registered in Redis with this host name that take
jobs from this deployment's queues. A starting worker is not registered yet, so it counts
itself; the worker counts again before each job (``worker.runner``). The functions here only
do the arithmetic; :func:`apply_threads` sets the thread counts of torch and numba.
"""

from __future__ import annotations

import contextlib
import os
import socket
from collections.abc import Iterable
from pathlib import Path
from typing import Any

CPU_MAX = Path("/sys/fs/cgroup/cpu.max")


def parse_cpu_max(text: str | None) -> float | None:
    """The CPUs a cgroup v2 ``cpu.max`` grants (``"200000 100000"`` -> 2.0), or None when it
    sets no limit (``"max 100000"``), is missing or cannot be read."""
    if not text:
        return None
    parts = text.split()
    if not parts or parts[0] == "max":
        return None
    try:
        quota = int(parts[0])
        period = int(parts[1]) if len(parts) > 1 else 100_000
    except ValueError:
        return None
    if quota <= 0 or period <= 0:
        return None
    return quota / period


def read_cpu_max(path: Path = CPU_MAX) -> float | None:
    """:func:`parse_cpu_max` of ``path``; None when the file does not exist."""
    try:
        return parse_cpu_max(path.read_text())
    except OSError:
        return None


def usable_cores(affinity: int | None, cpu_count: int | None, quota: float | None) -> int:
    """The CPUs this process can keep busy: its affinity (else the machine's count), capped
    by the cgroup quota rounded down; at least 1."""
    cores = affinity or cpu_count or 1
    if quota is not None:
        cores = min(cores, int(quota))
    return max(1, cores)


def threads_per_worker(cores: int, workers: int, explicit: int = 0) -> int:
    """Threads of one worker: ``explicit`` when it is set (> 0), else the cores divided among
    ``workers`` (rounded down, at least 1)."""
    if explicit > 0:
        return explicit
    return max(1, cores // max(1, workers))


def process_cores(cpu_max: Path = CPU_MAX) -> int:
    """:func:`usable_cores` of this process."""
    affinity = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    return usable_cores(affinity, os.cpu_count(), read_cpu_max(cpu_max))


def count_host_workers(
    workers: Iterable[Any], queues: Iterable[str], hostname: str, exclude: str | None = None
) -> int:
    """How many of ``workers`` (RQ workers) run on ``hostname`` and take jobs from one of
    ``queues``, not counting the one named ``exclude``."""
    wanted = set(queues)
    return sum(
        1
        for w in workers
        if w.hostname == hostname and w.name != exclude and wanted & set(w.queue_names())
    )


def host_workers(connection: Any, queues: list[str], me: str) -> int:
    """Workers on this host for ``queues`` in Redis, counting the worker ``me`` once whether
    it is registered yet or not."""
    from rq import Worker

    return 1 + count_host_workers(Worker.all(connection), queues, socket.gethostname(), me)


def apply_threads(threads: int) -> dict[str, int]:
    """Set torch's intra-op and inter-op threads and numba's threads; returns what was set.

    Inter-op threads can only be set before torch has run parallel work; after that they stay
    as they are (and the returned ``interop`` says how many there are)."""
    import numba
    import torch

    torch.set_num_threads(threads)
    with contextlib.suppress(RuntimeError):  # torch already ran parallel work in this process
        torch.set_num_interop_threads(threads)
    limit = numba.config.NUMBA_NUM_THREADS  # type: ignore[attr-defined]  # set at run time
    numba_threads = max(1, min(threads, limit))
    numba.set_num_threads(numba_threads)
    return {
        "torch": torch.get_num_threads(),
        "interop": torch.get_num_interop_threads(),
        "numba": numba_threads,
    }
