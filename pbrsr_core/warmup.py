"""Compile the numba kernels ahead of the first job.

The renderer's and the optimiser's CPU kernels are compiled by numba on first use and cached
on disk (``cache=True``, beside their modules, or under ``NUMBA_CACHE_DIR``). Compiling them
all takes about 35 s on a 2-core CPU, which would otherwise land on a user's first upscale or
on a new worker's first job. :func:`warm_up` runs the whole PBR-SR pipeline once on a tiny
procedural asset (every map kind: colour, ORM, normal), which compiles every specialisation a
job uses; ``scripts/setup`` and the Docker image call it (``python -m pbrsr_core.warmup``).
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path


def warm_up() -> float:
    """Run the pipeline once on a 16^2 demo asset; return the seconds it took."""
    from .asset import make_demo_asset
    from .options import UpscaleOptions
    from .pipeline import upscale_asset

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="pbrsr-warmup-") as d:
        src = make_demo_asset(Path(d) / "in" / "demo.glb", size=16)
        # optimisation steps: without them the renderer's backward and the optimiser's
        # kernels would stay uncompiled
        options = UpscaleOptions(
            method="pbrsr", preset="balanced", prior="bicubic", scale=2, iterations=2
        )
        upscale_asset(src, Path(d) / "out", options)
    return time.perf_counter() - t0


if __name__ == "__main__":
    seconds = warm_up()
    if "--quiet" not in sys.argv:
        print(f"warm-up: numba kernels compiled and cached ({seconds:.1f} s)")
