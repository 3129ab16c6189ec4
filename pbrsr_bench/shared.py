"""Where the benchmarks find the shared real assets and HDR environment maps.

``$PBRSR_SHARED_ASSETS`` when set, else the ``shared/assets`` folder beside the repository
(``../shared/assets`` from its root). Benchmarks use the folder when it exists and say so when
it does not; the tests never need it.
"""

from __future__ import annotations

import os
from pathlib import Path


def shared_assets_dir() -> Path:
    env = os.environ.get("PBRSR_SHARED_ASSETS", "").strip()
    if env:
        return Path(env).expanduser()
    return Path(__file__).resolve().parents[1].parent / "shared" / "assets"


SHARED_ASSETS = shared_assets_dir()
