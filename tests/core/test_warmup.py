"""The warm-up compiles every numba specialisation a job uses: after it, upscaling other
assets (glTF with external images, x4, the PBR-SR presets and the baselines) compiles
nothing new. Run in a fresh interpreter, so kernels other tests compiled do not count."""

from __future__ import annotations

import json
import subprocess
import sys

SCRIPT = r"""
import json, sys, tempfile
from pathlib import Path
import numba
from pbrsr_core.warmup import warm_up

def signatures():
    out = {}
    for name, mod in list(sys.modules.items()):
        if not name.startswith("pbrsr_core"):
            continue
        for attr, obj in vars(mod).items():
            if isinstance(obj, numba.core.registry.CPUDispatcher):
                out[f"{name}.{attr}"] = sorted(map(str, obj.signatures))
    return out

warm_up()
before = signatures()
from pbrsr_core.asset import make_test_asset
from pbrsr_core.options import UpscaleOptions
from pbrsr_core.pipeline import upscale_asset
with tempfile.TemporaryDirectory() as d:
    src = make_test_asset(Path(d) / "in" / "a.gltf", size=24, kind="gltf")
    for i, opts in enumerate([
        UpscaleOptions(method="pbrsr", preset="fast", prior="bicubic", scale=4),
        UpscaleOptions(method="pbrsr", preset="quality", prior="bicubic", scale=4),
        UpscaleOptions(method="pbrsr", preset="balanced", prior="bicubic", scale=4, iterations=3),
        UpscaleOptions(method="bicubic", scale=2),
    ]):
        upscale_asset(src, Path(d) / f"out{i}", opts)
after = signatures()
new = {k: sorted(set(v) - set(before.get(k, []))) for k, v in after.items()}
print(json.dumps({"kernels": len(before), "new": {k: v for k, v in new.items() if v}}))
"""


def test_warm_up_covers_every_kernel_a_job_compiles():
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=600, check=False
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["kernels"] >= 10  # the renderer's and the optimiser's kernels were found
    assert result["new"] == {}, result["new"]
