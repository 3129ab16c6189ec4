"""How much memory a run will need, from the sizes an asset declares, before anything is
allocated for it; and how much this process may use.

The estimate is a base, a fixed working set and a cost per output value (texel x channel),
each set above the peaks measured (peak RSS of ``pbrsr upscale``'s process, ``/usr/bin/time
-f %M``; 2 cores, about 20 GiB free, so the prior's tiles at their largest): x4 of the
Avocado's three 512² maps (37.7 M output values) and of the cabinet's three 1024² maps (151 M),
x2 of the Avocado's three 2048² maps (151 M) and of the BoomBox's four (201 M).
Bicubic: 1014 and 2245 MiB, 11 bytes per value over the base. The fast preset at x4 (the
prior at x2): 1349 and 3961 MiB, 23 bytes per value. The prior at the full scale (balanced,
quality, fast at x2): 2696-3178 MiB at 37.7 M values and 4209-5336 MiB at 151-201 M, 17 bytes
per value over a working set of about 2 GiB (a 512² tile's activations at the second x2
pass); the direct prior 2743 and 3306-3367 MiB, 6 bytes per value. A worker and the CLI
refuse a run whose estimate exceeds the memory it may use instead of being killed by the
kernel half-way through it.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

from .errors import LimitExceeded

MIB = 1024 * 1024
BASE_BYTES = 600 * MIB
"""The process before the run: torch, numba, the prior's weights."""
WORKING_BYTES = {"bicubic": 0, "prior_part": 0, "prior_full": 2048 * MIB, "direct": 2048 * MIB}
"""The working set that does not grow with the maps: a prior's tiles at their passes."""
BYTES_PER_VALUE = {"bicubic": 14, "prior_part": 28, "prior_full": 22, "direct": 12}
"""Per output value: bicubic; a PBR-SR preset that runs the prior at part of the scale (the
rest bicubic), or at the full scale (the maps, the check's candidates, the blends, the
back-projection); the direct prior."""
RENDER_BYTES_PER_PIXEL = 48
"""G-buffer bytes per rendered pixel of a training view (bounded by the G-buffer cache)."""
STEP_BYTES_PER_PIXEL = 400
"""Per pixel of a step's batch of views: shading forward and backward."""


def estimate_peak_bytes(
    sizes: Iterable[tuple[int, int, int]], scale: int, method: str, config=None
) -> int:
    """Peak memory of a run over images of ``sizes`` (width, height, channels) at ``scale``;
    ``config``: the PBR-SR preset (``PbrsrConfig``) when ``method`` is pbrsr."""
    values = sum(w * h * c for w, h, c in sizes) * scale * scale
    if method in ("bicubic", "direct"):
        kind = method
    elif config is not None and (config.max_prior_scale or scale) < scale:
        kind = "prior_part"
    else:
        kind = "prior_full"
    total = BASE_BYTES + WORKING_BYTES[kind] + BYTES_PER_VALUE[kind] * values
    if method == "pbrsr" and config is not None and config.iterations > 0:
        res = config.max_render_res
        pixels = res * res
        gbuffers = min(config.max_views * pixels * RENDER_BYTES_PER_PIXEL,
                       config.gbuffer_cache_mb * MIB)  # fmt: skip
        total += gbuffers + config.batch_views * pixels * STEP_BYTES_PER_PIXEL
    return int(total)


def _read_int(path: Path) -> int | None:
    try:
        text = path.read_text().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def _meminfo(key: str) -> int | None:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def _rss_bytes() -> int:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return 0


def available_bytes() -> int | None:
    """What this process may grow to: its resident size plus the memory the machine has
    available (``MemAvailable``), capped by the cgroup's limit when there is one; None where
    the system does not say."""
    free = _meminfo("MemAvailable")
    if free is None:
        return None
    total = _rss_bytes() + free
    limit = _read_int(Path("/sys/fs/cgroup/memory.max"))
    used = _read_int(Path("/sys/fs/cgroup/memory.current"))
    if limit is not None and used is not None:
        total = min(total, _rss_bytes() + max(limit - used, 0))
    return total


def check_memory(estimate: int, budget: int | None, what: str) -> None:
    """Refuse (LimitExceeded) a run whose ``estimate`` is over ``budget`` bytes (None: no
    budget known, no check)."""
    if budget is not None and estimate > budget:
        raise LimitExceeded(
            f"{what} needs about {estimate / 2**30:.1f} GiB of memory and this machine has "
            f"{budget / 2**30:.1f} GiB for it: try a lower scale, a max_size, the fast preset "
            "or a machine with more memory"
        )


def memory_budget(setting_mib: int) -> int | None:
    """A budget from a setting in MiB (0: what the machine has now, :func:`available_bytes`)."""
    if setting_mib > 0:
        return setting_mib * MIB
    return available_bytes() if os.name == "posix" else None
