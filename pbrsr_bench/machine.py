"""The machine a benchmark ran on, and how fast it computes.

A CPU's name and core count do not fix its speed: on two 2-core machines that both report
"AMD EPYC", the same network run took 1.8 times as long on one as on the other. So next to the
name, :func:`machine` states what a reference convolution computes per second there, on the
torch threads the benchmark uses and on one, and run times from different machines can be
set against each other.
"""

from __future__ import annotations

import math
import os
import platform
import time
from pathlib import Path

# the reference: a 3x3 convolution of 64 channels to 64 in float32, the kind of layer the
# priors' networks are built of
_CHANNELS = 64
_SIZE = 128


def conv_gflops(threads: int, size: int = _SIZE, repeats: int = 5) -> float:
    """GFLOPS of the reference convolution on a ``size``² input on ``threads`` torch threads:
    the fastest of ``repeats`` runs after one warm-up. torch's thread count is restored."""
    import torch

    if threads < 1 or size < 3 or repeats < 1:
        raise ValueError("threads and repeats must be at least 1, size at least 3")
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        g = torch.Generator().manual_seed(0)
        x = torch.randn(1, _CHANNELS, size, size, generator=g)
        w = torch.randn(_CHANNELS, _CHANNELS, 3, 3, generator=g)
        best = math.inf
        with torch.no_grad():
            torch.nn.functional.conv2d(x, w, padding=1)
            for _ in range(repeats):
                start = time.perf_counter()
                torch.nn.functional.conv2d(x, w, padding=1)
                best = min(best, time.perf_counter() - start)
    finally:
        torch.set_num_threads(previous)
    flops = 2 * _CHANNELS * _CHANNELS * 9 * size * size
    return flops / max(best, 1e-9) / 1e9


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo; elsewhere what ``platform`` knows)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> str:
    """The CPU, its cores, torch's thread count and the reference convolution's speed on those
    threads and on one, measured now (a second or two). The CPU's, also where the benchmark
    runs on a GPU: its results name their device themselves."""
    import torch

    threads = torch.get_num_threads()
    speed = f"{conv_gflops(threads):.0f} GFLOPS"
    if threads > 1:
        speed += f", {conv_gflops(1):.0f} on one thread"
    return (
        f"{cpu_model()}, {os.cpu_count()} cores, {threads} torch threads (a 3x3 convolution of "
        f"{_CHANNELS} channels, float32: {speed})"
    )
