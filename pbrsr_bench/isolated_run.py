"""One benchmark run in its own process: ``python -m pbrsr_bench.isolated_run spec.json``.

Runs :func:`pbrsr_core.pipeline.upscale_asset` and, for PBR-SR, saves the maps at
intermediate iterations (``snap_<it>.npz``, as they would be exported) with the wall time at
which they existed (time spent making and saving snapshots is not counted; ``"snapshots":
false`` in the spec saves none). ``"config"`` in the spec changes numbers of the options'
preset (``PbrsrConfig.with_``). Writes ``result.json`` beside the spec; for options the
pipeline refuses on this asset (``UnprocessableAsset``: a ``max_size`` that keeps every map,
say) only ``{"refused": message}``.
"""

from __future__ import annotations

import json
import resource
import sys
import time
from pathlib import Path

import numpy as np

from pbrsr_core.cli.environment import configure_from_env
from pbrsr_core.errors import UnprocessableAsset
from pbrsr_core.optim.presets import get_preset
from pbrsr_core.options import UpscaleOptions
from pbrsr_core.pipeline import upscale_asset

SNAPSHOT_AT = (0, 5, 10, 25, 50, 100, 200, 400, 800, 1600)


def peak_rss_mib() -> float:
    """This process's peak resident memory (VmHWM). Not ru_maxrss: Linux carries that over
    from the parent through fork and exec, so a child of a big benchmark process would report
    the parent's size."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def main(spec_path: str) -> None:
    configure_from_env()  # the PBRSR_* settings, as the pbrsr command that started the bench has
    spec = json.loads(Path(spec_path).read_text())
    work = Path(spec["work"])
    snaps: list[dict] = []
    overhead = 0.0
    t0 = time.perf_counter()

    def on_snapshot(it: int, maps) -> None:
        nonlocal overhead
        s0 = time.perf_counter()
        name = f"snap_{it:05d}.npz"
        np.savez(work / name, **{str(i): m for i, m in maps().items()})
        snaps.append({"it": it, "seconds": round(s0 - t0 - overhead, 3), "file": name})
        overhead += time.perf_counter() - s0

    options = UpscaleOptions(**spec["options"])
    # JSON has no tuples: a preset's tuple fields (prior_maps, ...) come back as lists
    changes = {
        k: tuple(v) if isinstance(v, list) else v for k, v in (spec.get("config") or {}).items()
    }
    try:
        report = upscale_asset(
            Path(spec["input"]),
            Path(spec["out"]),
            options,
            work_dir=work / "job",
            snapshots=(SNAPSHOT_AT, on_snapshot) if spec.get("snapshots", True) else None,
            config=get_preset(options.preset).with_(**changes) if changes else None,
        )
    except UnprocessableAsset as exc:  # these options cannot run on this asset
        (work / "result.json").write_text(json.dumps({"refused": exc.message}))
        return
    run_s = time.perf_counter() - t0 - overhead
    peak = peak_rss_mib()
    (work / "result.json").write_text(
        json.dumps(
            {
                "run_s": run_s,
                "peak_rss_mib": peak,
                "timings": report["timings"],
                "num_views": report.get("num_views", 0),
                "lr_model": report.get("lr_model"),
                "snapshots": snaps,
            }
        )
    )


if __name__ == "__main__":
    main(sys.argv[1])
