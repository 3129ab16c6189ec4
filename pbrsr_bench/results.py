"""How a benchmark writes its result: ``<name>.json`` and the plot ``<name>.png`` beside it;
the plots draw with matplotlib on the non-interactive Agg backend."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the Agg backend (imported when a plot is drawn)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def write_result(
    result: dict, out_dir: Path, name: str, plot: Callable[[dict, Path], None]
) -> dict:
    """Write ``result`` to ``out_dir/<name>.json`` and ``plot`` it to ``out_dir/<name>.png``;
    returns ``result``."""
    (out_dir / f"{name}.json").write_text(json.dumps(result, indent=2))
    plot(result, out_dir / f"{name}.png")
    return result
