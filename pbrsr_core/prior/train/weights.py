"""A trained network as a safetensors file: its tensors and, in the metadata, what it is
(architecture, widths, map kinds, training scale) and how it was made."""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from ...errors import InvalidOptions, PriorUnavailable
from ..compact import START as COMPACT_START
from ..compact import Compact
from ..span import Span
from ..spandrel_prior import SpandrelNet
from ..srmd import SRMD
from ..srmd import START as SRMD_START
from ..waifu2x import UpConv7

if TYPE_CHECKING:
    from .loop import TrainConfig

Network = UpConv7 | Compact | Span | SRMD | SpandrelNet
ARCHS = ("upconv7", "compact", "span", "srmd", "spandrel")
SPANDREL = "spandrel:"
"""Start weights of this prefix: any SR model spandrel recognises, fine-tuned as it is (its
architecture and scale are the file's; :class:`~pbrsr_core.prior.spandrel_prior.SpandrelNet`)."""
HALF_ARCHS = ("srmd",)
"""Architectures whose weights are stored as float16, as their ncnn start weights are: an SRMD
network takes 3.1 MB where float32 would take 6.2 MB."""


def arch_of(net: Network) -> str:
    if isinstance(net, SpandrelNet):
        return "spandrel"
    if isinstance(net, Span):
        return "span"
    if isinstance(net, SRMD):
        return "srmd"
    return "compact" if isinstance(net, Compact) else "upconv7"


def new_network(arch: str, widths: tuple[int, ...], stride: int, residual: bool = False) -> Network:
    """A network of ``arch`` at random weights: UpConv7 of ``widths``, a compact network of
    ``len(widths) - 1`` body convolutions of ``widths[0]`` features, a SPAN network of
    ``len(widths)`` blocks of ``widths[0]`` features, or an SRMD network of ``len(widths)``
    convolutions of ``widths[0]`` features (all three: all widths equal). A ``residual``
    UpConv7 (bicubic plus the network) starts with its last layer at zero, so at step 0 it is
    bicubic exactly, as a SPAN network always does. A ``spandrel`` network has no random
    start: its weights file (``--from spandrel:FILE``) is what it is."""
    if arch == "spandrel":
        raise ValueError("a spandrel network starts from its weights: --from spandrel:<file>")
    if arch in ("compact", "span", "srmd"):
        if len(set(widths)) != 1:
            raise ValueError(f"a {arch} network has equal widths, not {widths}")
        if residual:
            raise ValueError(f"residual is an upconv7 option, not one of a {arch} network")
        if arch == "span":
            return Span(widths[0], len(widths), stride)
        if arch == "srmd":
            return SRMD(widths[0], len(widths), stride)
        return Compact(widths[0], len(widths) - 1, stride)
    if arch == "upconv7":
        net = UpConv7(widths, stride=stride, residual=residual)
        if residual:
            last = net.layers()[-1]
            torch.nn.init.zeros_(last.weight)
            assert last.bias is not None
            torch.nn.init.zeros_(last.bias)
        return net
    raise ValueError(f"unknown architecture {arch!r}: use {', '.join(ARCHS)}")


def head_prefix(net: Network) -> str:
    """The state-dict prefix of the layer that upscales (the part a new stride replaces)."""
    return "head." if isinstance(net, Compact | Span | SRMD) else f"mods.{len(net.widths)}."


def save_network(net: Network, path: Path, config: TrainConfig, extra: dict[str, str]) -> None:
    """Write ``net``'s weights (float32; :data:`HALF_ARCHS` float16) with metadata: ``arch``,
    its shape (UpConv7: ``widths``, ``slope``, ``residual``; compact and SRMD: ``feat``,
    ``convs``; SPAN: ``feat``, ``blocks``; spandrel: its ``architecture``, the tensors its
    model's own state dict, which spandrel recognises it by), ``stride``, ``pass``
    (``first``, or ``later``: a network trained behind another that runs the first x2 pass),
    ``kinds``, ``scale``, the training config as JSON and ``extra``."""
    from safetensors.torch import save_file

    if isinstance(net, SpandrelNet):
        shape = {"architecture": net.architecture}
    elif isinstance(net, Compact | SRMD):
        shape = {"feat": str(net.feat), "convs": str(net.convs)}
    elif isinstance(net, Span):
        shape = {"feat": str(net.feat), "blocks": str(net.blocks)}
    else:
        shape = {"slope": str(net.slope), "residual": "1" if net.residual else "0"}
    meta = {
        "arch": arch_of(net),
        "widths": ",".join(str(w) for w in net.widths),
        **shape,
        "stride": str(net.stride),
        "pass": "later" if config.first else "first",
        "kinds": ",".join(config.kinds),
        "scale": str(config.scale),
        "config": json.dumps(asdict(config)),
        **{k: str(v) for k, v in extra.items()},
    }
    dtype = torch.float16 if arch_of(net) in HALF_ARCHS else torch.float32
    state = net.weights() if isinstance(net, SpandrelNet) else net.state_dict()
    tensors = {k: v.detach().to("cpu", dtype).contiguous() for k, v in state.items()}
    tmp = path.with_suffix(".tmp")
    save_file(tensors, str(tmp), metadata=meta)
    tmp.replace(path)


def update_metadata(path: Path, changes: dict[str, str]) -> None:
    """Rewrite ``path`` with ``changes`` merged into its metadata, its tensors and permissions
    as they are (written beside it, then moved over it)."""
    from safetensors.torch import load_file, save_file

    path = Path(path)
    meta = {**read_metadata(path), **changes}
    tensors = load_file(str(path))
    tmp = path.with_suffix(".tmp")
    save_file(tensors, str(tmp), metadata=meta)
    tmp.chmod(path.stat().st_mode)
    tmp.replace(path)


def file_sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def read_metadata(path: Path) -> dict[str, str]:
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), framework="pt") as f:
            return dict(f.metadata() or {})
    except (OSError, ValueError, RuntimeError, SafetensorError) as exc:
        raise PriorUnavailable(f"'{path}' is not a safetensors weights file: {exc}") from exc


def load_network(path: Path) -> Network:
    """The network stored in ``path`` (written by :func:`save_network`)."""
    from safetensors.torch import load_file

    path = Path(path)
    if not path.is_file():
        raise PriorUnavailable(f"no weights file at '{path}'")
    meta = read_metadata(path)
    arch = meta.get("arch")
    if arch not in ARCHS:
        raise PriorUnavailable(f"'{path.name}' is not a pbrsr network weights file")
    try:
        stride = int(meta.get("stride", "2"))
        net: Network
        if arch == "spandrel":
            net = SpandrelNet.from_weights(load_file(str(path)), path.name)
            if (net.architecture, net.stride) != (meta.get("architecture"), stride):
                raise ValueError(
                    f"spandrel reads a x{net.stride} {net.architecture} network, the file says "
                    f"x{stride} {meta.get('architecture')}"
                )
            return net.eval()
        if arch == "compact":
            net = Compact(int(meta["feat"]), int(meta["convs"]), stride)
        elif arch == "span":
            net = Span(int(meta["feat"]), int(meta["blocks"]), stride)
        elif arch == "srmd":
            net = SRMD(int(meta["feat"]), int(meta["convs"]), stride)
        else:
            widths = tuple(int(w) for w in meta["widths"].split(","))
            net = UpConv7(
                widths,
                slope=float(meta.get("slope", "0.1")),
                stride=stride,
                residual=meta.get("residual", "0") == "1",
            )
        net.load_state_dict(load_file(str(path)))
    except (KeyError, ValueError, RuntimeError, InvalidOptions) as exc:
        raise PriorUnavailable(
            f"'{path.name}': weights do not match their metadata: {exc}"
        ) from exc
    return net.eval()


def start_shape(start: str, arch: str) -> tuple[str, tuple[int, ...], bool]:
    """(architecture, widths, residual) of the start weights ``start`` (a
    :func:`resolve_start` result); ``random`` takes ``arch`` at its default widths."""
    if start.startswith(SPANDREL):
        return "spandrel", (), False
    if start == "random":
        if arch == "span":
            return arch, Span().widths, False
        if arch == "srmd":
            return arch, SRMD().widths, False
        return arch, (Compact().widths if arch == "compact" else UpConv7().widths), False
    if start == "waifu2x-photo":
        return "upconv7", UpConv7().widths, False
    if start == COMPACT_START:
        return "compact", Compact().widths, False
    if start == SRMD_START:
        return "srmd", SRMD().widths, False
    net = load_network(Path(start))
    return arch_of(net), net.widths, getattr(net, "residual", False)


def resolve_start(source: str, kind: str, stride: int, later: bool = False) -> str:
    """The start weights of a network for ``kind`` maps: ``random``, ``waifu2x-photo`` and
    ``realesr-animevideov3`` as they are, a ``.safetensors`` file and ``spandrel:<file>`` as
    they are, and a texture prior
    (a shipped set, ``texture:<folder>``) as its file for ``kind`` (of ``stride`` where it
    has one; with ``later``, its later-pass network where it has one)."""
    named = ("random", "waifu2x-photo", COMPACT_START, SRMD_START)
    if source in named or source.endswith(".safetensors") or source.startswith(SPANDREL):
        return source
    from ..texture import SHIPPED, shipped_files, weight_files

    folder: Path | list[Path]
    if source in SHIPPED:
        folder = shipped_files(source)
    elif source.startswith("texture:"):
        folder = Path(source[len("texture:") :]).expanduser()
    else:
        raise PriorUnavailable(
            f"cannot start from {source!r}: use random, waifu2x-photo, {COMPACT_START}, "
            f"{SRMD_START}, "
            f"{', '.join(SHIPPED)}, texture:<folder>, spandrel:<file> or a .safetensors file"
        )
    files = weight_files(folder)
    keys = [(kind, stride, "first"), *((kind, s, "first") for s in (8, 4, 2) if s != stride)]
    for key in ([(kind, 2, "later")] if later else []) + keys:
        if key in files:
            return str(files[key])
    raise PriorUnavailable(f"{source!r} has no weights for {kind} maps")
