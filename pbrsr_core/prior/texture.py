"""Texture priors: networks (UpConv7 or compact) trained on PBR texture maps (``pbrsr priors
finetune``), one set of weights per map kind (colour, data, normal) or one shared by several
kinds, of stride 2 or 4.

The shipped sets (:data:`SHIPPED`) are files in ``pbrsr_core/prior/weights/<set>/`` (each made
by the command in its folder's MODEL_CARD.md); ``texture:<folder or file>`` loads any set
``pbrsr priors train/finetune`` wrote. :meth:`TexturePrior.for_kind` gives the network for
one map kind; a kind without weights of its own uses the ``fallback`` prior (waifu2x-photo).
The prior itself, called on images of no stated kind (the optimiser's renders), runs the colour
network, or the fallback where the set has no colour network.
"""

from __future__ import annotations

import threading
from pathlib import Path

import torch

from ..errors import PriorUnavailable
from .base import Prior
from .train.weights import Network, load_network, read_metadata

WEIGHTS_ROOT = Path(__file__).resolve().parent / "weights"
SHIPPED: dict[str, tuple[str, ...]] = {
    # UpConv7 x2 networks fine-tuned from waifu2x-photo, one per kind
    "pbr-upconv7": tuple(
        f"pbr-upconv7/pbr-upconv7-{k}.safetensors" for k in ("colour", "data", "normal")
    ),
}
"""Shipped set name -> its weights files under :data:`WEIGHTS_ROOT` (one per kind and
stride; a kind without one uses the fallback)."""


def shipped_files(name: str) -> list[Path]:
    """The weights files of the shipped set ``name``."""
    return [WEIGHTS_ROOT / f for f in SHIPPED[name]]


KINDS = ("colour", "data", "normal")


def weight_files(source: Path | list[Path]) -> dict[tuple[str, int], Path]:
    """(kind, stride) -> weights file of a folder (every ``*.safetensors`` in it, else in its
    subfolders: the layout ``pbrsr priors train -o`` writes), of one file or of a list of
    files, from each file's ``kinds`` and ``stride`` metadata."""
    if isinstance(source, list):
        files = [Path(f) for f in source]
    else:
        source = Path(source)
        files = [source]
        if source.is_dir():
            files = sorted(source.glob("*.safetensors")) or sorted(source.glob("*/*.safetensors"))
    if not files or not all(f.is_file() for f in files):
        raise PriorUnavailable(f"no texture prior weights at '{source}'")
    out: dict[tuple[str, int], Path] = {}
    for f in files:
        meta = read_metadata(f)
        stride = int(meta.get("stride", "2")) if meta.get("stride", "2").isdigit() else 0
        for kind in meta.get("kinds", "").split(","):
            if kind in KINDS and stride in (2, 4):
                if (kind, stride) in out:
                    raise PriorUnavailable(
                        f"'{source}' has two x{stride} weights files for {kind} maps"
                    )
                out[kind, stride] = f
    if not out:
        raise PriorUnavailable(f"'{source}' holds no weights for colour, data or normal maps")
    return out


def passes(strides: set[int], scale: int) -> list[int] | None:
    """The network strides whose product is ``scale``, largest first (None if none is)."""
    plan, left = [], scale
    for s in sorted(strides, reverse=True):
        while left % s == 0 and left > 1:
            plan.append(s)
            left //= s
    return plan if left == 1 else None


def installed_stats(name: str) -> tuple[int | None, int | None]:
    """(parameters of the network that runs x4 colour, else of the first, bytes on disk of
    the set) of the shipped set ``name``; (None, None) where its files are missing."""
    try:
        files = weight_files(shipped_files(name))
    except PriorUnavailable:
        return None, None
    first = files.get(("colour", 4)) or next(iter(files.values()))
    params = sum(p.numel() for p in load_network(first).parameters())
    return params, sum(f.stat().st_size for f in set(files.values()))


class TexturePrior(Prior):
    """Networks trained on texture maps: per kind an x2 network, an x4 network or both; a
    scale runs as the fewest passes whose strides multiply to it (x8: x4 then x2)."""

    bytes_per_pixel = 8192.0  # as waifu2x-photo: the same network shape
    default_overlap = 32

    def __init__(
        self,
        source: Path | list[Path],
        device: torch.device | str = "cpu",
        *,
        name: str | None = None,
        fallback: str = "waifu2x-photo",
    ) -> None:
        super().__init__()
        self.device = torch.device(device)
        self.name = name or f"texture:{source}"
        self.files = weight_files(source)
        loaded: dict[Path, Network] = {}
        self.nets: dict[str, dict[int, Network]] = {}
        for (kind, stride), f in self.files.items():
            if f not in loaded:
                net = load_network(f).to(self.device)
                loaded[f] = net.to(memory_format=torch.channels_last)  # type: ignore[call-overload]  # torch's stubs omit memory_format
            self.nets.setdefault(kind, {})[stride] = loaded[f]
        self.fallback = fallback
        self._views: dict[str, Prior] = {}
        self._lock = threading.Lock()
        # images of no stated kind (the optimiser's renders) are colour images: the colour
        # network, or the fallback where the set has none
        self.kind = "colour" if "colour" in self.nets else None
        if self.kind is None:
            self.scales = self.for_kind("colour").scales
            self.one_pass_scales = self.for_kind("colour").one_pass_scales
        else:
            self.scales = _scales(self.nets[self.kind])
            self.one_pass_scales = tuple(sorted(self.nets[self.kind]))
            self._views[self.kind] = self

    def for_kind(self, kind: str) -> Prior:
        with self._lock:
            view = self._views.get(kind)
            if view is None:
                if kind in self.nets:
                    view = _KindView(self, kind)
                else:
                    from .registry import load_prior

                    view = load_prior(self.fallback, self.device)
                self._views[kind] = view
            return view

    def candidates(self, kind: str) -> list[Prior]:
        """The kind's own network, then the fallback: a network trained on textures need not
        beat the photo prior on every map, so the self-check keeps whichever reconstructs
        the map better (prior/selfcheck.py)."""
        own = self.for_kind(kind)
        if kind not in self.nets:
            return [own]
        from .registry import load_prior

        return [own, load_prior(self.fallback, self.device)]

    def num_parameters(self) -> int:
        if self.kind is None:
            return self.for_kind("colour").num_parameters()
        return _parameters(self.nets[self.kind])

    def _run(self, kind: str, x: torch.Tensor, scale: int) -> torch.Tensor:
        nets = self.nets[kind]
        with self._lock:
            for stride in passes(set(nets), scale) or []:
                x = nets[stride](x).clamp_(0.0, 1.0)
        return x

    def _forward(self, x: torch.Tensor, scale: int) -> torch.Tensor:
        if self.kind is None:
            return self.for_kind("colour")._forward(x, scale)
        return self._run(self.kind, x, scale)

    def describe(self) -> dict:
        info = super().describe()
        info["kinds"] = {
            k: sorted(f.name for (kind, _), f in self.files.items() if kind == k) or self.fallback
            for k in KINDS
        }
        return info


class _KindView(Prior):
    """One kind's network of a :class:`TexturePrior`, as a prior of its own."""

    def __init__(self, parent: TexturePrior, kind: str) -> None:
        super().__init__()
        self.parent, self.kind = parent, kind
        self.name = f"{parent.name}[{kind}]"
        self.scales, self.device = _scales(parent.nets[kind]), parent.device
        self.one_pass_scales = tuple(sorted(parent.nets[kind]))
        self.bytes_per_pixel = parent.bytes_per_pixel
        self.default_overlap = parent.default_overlap

    def num_parameters(self) -> int:
        return _parameters(self.parent.nets[self.kind])

    def _forward(self, x: torch.Tensor, scale: int) -> torch.Tensor:
        return self.parent._run(self.kind, x, scale)


def _scales(nets: dict[int, Network]) -> tuple[int, ...]:
    return tuple(s for s in (2, 4, 8) if passes(set(nets), s))


def _parameters(nets: dict[int, Network]) -> int:
    """Parameters of the network that runs x4 (the one-pass x4 network where there is one)."""
    net = nets.get(4) or nets[min(nets)]
    return sum(p.numel() for p in net.parameters())
