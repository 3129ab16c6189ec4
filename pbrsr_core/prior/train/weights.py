"""A trained network as a safetensors file: its tensors and, in the metadata, what it is
(architecture, widths, map kinds, training scale) and how it was made."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

from ...errors import PriorUnavailable
from ..waifu2x import UpConv7

if TYPE_CHECKING:
    from .loop import TrainConfig

ARCH = "upconv7"


def save_network(net: UpConv7, path: Path, config: TrainConfig, extra: dict[str, str]) -> None:
    """Write ``net``'s weights (float32) with metadata: ``arch``, ``widths``, ``slope``,
    ``kinds``, ``scale``, the training config as JSON and ``extra``."""
    from safetensors.torch import save_file

    meta = {
        "arch": ARCH,
        "widths": ",".join(str(w) for w in net.widths),
        "slope": str(net.slope),
        "stride": str(net.stride),
        "kinds": ",".join(config.kinds),
        "scale": str(config.scale),
        "config": json.dumps(asdict(config)),
        **{k: str(v) for k, v in extra.items()},
    }
    tensors = {k: v.detach().float().contiguous() for k, v in net.state_dict().items()}
    tmp = path.with_suffix(".tmp")
    save_file(tensors, str(tmp), metadata=meta)
    tmp.replace(path)


def read_metadata(path: Path) -> dict[str, str]:
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), framework="pt") as f:
            return dict(f.metadata() or {})
    except (OSError, ValueError, RuntimeError, SafetensorError) as exc:
        raise PriorUnavailable(f"'{path}' is not a safetensors weights file: {exc}") from exc


def load_network(path: Path) -> UpConv7:
    """The network stored in ``path`` (written by :func:`save_network`)."""
    from safetensors.torch import load_file

    path = Path(path)
    if not path.is_file():
        raise PriorUnavailable(f"no weights file at '{path}'")
    meta = read_metadata(path)
    if meta.get("arch") != ARCH:
        raise PriorUnavailable(f"'{path.name}' is not a pbrsr {ARCH} weights file")
    try:
        widths = tuple(int(w) for w in meta["widths"].split(","))
        net = UpConv7(
            widths, slope=float(meta.get("slope", "0.1")), stride=int(meta.get("stride", "2"))
        )
        net.load_state_dict(load_file(str(path)))
    except (KeyError, ValueError, RuntimeError) as exc:
        raise PriorUnavailable(
            f"'{path.name}': weights do not match their metadata: {exc}"
        ) from exc
    return net.eval()
