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


def resolve_start(source: str, kind: str, stride: int) -> str:
    """The start weights of a network for ``kind`` maps: ``random`` and ``waifu2x-photo`` as
    they are, a ``.safetensors`` file as it is, and a texture prior (``pbr-upconv7``,
    ``texture:<folder>``) as its file for ``kind`` (of ``stride`` where it has one)."""
    if source in ("random", "waifu2x-photo") or source.endswith(".safetensors"):
        return source
    from ..texture import NAME, WEIGHTS_DIR, weight_files

    if source == NAME:
        folder = WEIGHTS_DIR
    elif source.startswith("texture:"):
        folder = Path(source[len("texture:") :]).expanduser()
    else:
        raise PriorUnavailable(
            f"cannot start from {source!r}: use random, waifu2x-photo, {NAME}, "
            "texture:<folder> or a .safetensors file"
        )
    files = weight_files(folder)
    for key in ((kind, stride), *((kind, s) for s in (2, 4) if s != stride)):
        if key in files:
            return str(files[key])
    raise PriorUnavailable(f"{source!r} has no weights for {kind} maps")
