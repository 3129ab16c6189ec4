"""Texture priors: networks (UpConv7, compact, SPAN or SRMD) trained on PBR texture maps
(``pbrsr priors finetune``), one set of weights per map kind (colour, data, normal) or one
shared by several kinds, of stride 2, 4 or 8.

The shipped sets (:data:`SHIPPED`) are files in ``pbrsr_core/prior/weights/<set>/`` (each made
by the command in its folder's MODEL_CARD.md); ``texture:<folder or file>`` loads any set
``pbrsr priors train/finetune`` wrote. :meth:`TexturePrior.for_kind` gives the network for
one map kind; a kind without weights of its own uses the ``fallback`` prior (waifu2x-photo).
A kind may also have a ``later`` network (``pbrsr priors train --first``): trained behind its
first-pass network, it runs every x2 pass after the first (x4: first, later; x8: first,
later, later).
The prior itself, called on images of no stated kind (the optimiser's renders), runs the colour
network, or the fallback where the set has no colour network. An SRMD network whose file holds
an int8 calibration (``pbrsr priors calibrate``) runs in int8 where the prior's precision is
int8 (:mod:`pbrsr_core.prior.int8`).
"""

from __future__ import annotations

import threading
from pathlib import Path

import torch

from ..errors import PriorUnavailable
from .base import Prior
from .int8 import METADATA_KEY, Calibration, Int8SRMD
from .spandrel_prior import SpandrelNet, SpandrelPrior
from .srmd import SRMD
from .train.weights import Network, file_sha256, load_network, read_metadata

WEIGHTS_ROOT = Path(__file__).resolve().parent / "weights"
SHIPPED: dict[str, tuple[str, ...]] = {
    # UpConv7 x2 networks fine-tuned from waifu2x-photo, one per kind
    "pbr-upconv7": tuple(
        f"pbr-upconv7/pbr-upconv7-{k}.safetensors" for k in ("colour", "data", "normal")
    ),
    # pbr-upconv7's networks for the first pass, then narrow residual networks trained behind
    # them for the later passes of colour and normal maps (data maps: pbr-upconv7's own)
    "pbr-upconv7-fast": (
        *(f"pbr-upconv7/pbr-upconv7-{k}.safetensors" for k in ("colour", "data", "normal")),
        *(f"pbr-upconv7-fast/pbr-upconv7-fast-{k}.safetensors" for k in ("colour", "normal")),
    ),
    # pbr-upconv7's x2 colour and normal networks, SRMD networks fine-tuned from srmdnf_x4
    # that make x4 of colour and normal maps in one pass (x8: colour's SRMD network, then its
    # x2 one; normal maps: three x2 passes, see X4_ONLY), and pbr-upconv7's data network
    # fine-tuned on single scalar maps, half of them JPEG-compressed
    "pbr-srmd": (
        *(f"pbr-upconv7/pbr-upconv7-{k}.safetensors" for k in ("colour", "normal")),
        *(f"pbr-srmd/pbr-srmd-{k}.safetensors" for k in ("colour", "data", "normal")),
    ),
}
"""Shipped set name -> its weights files under :data:`WEIGHTS_ROOT` (one per kind and
stride; a kind without one uses the fallback)."""


X4_ONLY: dict[str, frozenset[str]] = {
    # at x8 the SRMD normal network then the x2 one scores below three x2 passes on 128² JPEG
    # normal maps (docs/BENCHMARKS.md, x8)
    "pbr-srmd": frozenset({"normal"}),
}
"""Shipped set name -> kinds whose x4 network runs for x4 only (their x8: x2 passes)."""

X2_CANDIDATE: dict[str, frozenset[str]] = {
    # at x4 the x2 passes lead on drawn maps, SRMD on photographic atlases: with both offered
    # the self-check's pick gains +5.22 dB over bicubic on 30 real colour maps against +5.10,
    # and the twelve WebXR assets' renders +3.87 against +3.82 (docs/METHOD.md); at x8 the
    # pick among x8 chains came out worse, so it is offered at x4 only
    "pbr-srmd": frozenset({"colour"}),
}
"""Shipped set name -> kinds whose x2 network's passes are a self-check candidate of their own
at x4, beside the kind's stride-4 network (:meth:`TexturePrior.candidates`)."""


def shipped_files(name: str) -> list[Path]:
    """The weights files of the shipped set ``name``."""
    return [WEIGHTS_ROOT / f for f in SHIPPED[name]]


KINDS = ("colour", "data", "normal")
Strides = frozenset[int] | None
"""The network strides a run may use: a subset of a kind's, or None for all of them."""


Key = tuple[str, int, str]
"""(map kind, stride, pass: ``first`` or ``later``) of a weights file."""


def weight_files(source: Path | list[Path]) -> dict[Key, Path]:
    """(kind, stride, pass) -> weights file of a folder (every ``*.safetensors`` in it, else
    in its subfolders: the layout ``pbrsr priors train -o`` writes), of one file or of a list
    of files, from each file's ``kinds``, ``stride`` and ``pass`` metadata."""
    if isinstance(source, list):
        files = [Path(f) for f in source]
    else:
        source = Path(source)
        files = [source]
        if source.is_dir():
            files = sorted(source.glob("*.safetensors")) or sorted(source.glob("*/*.safetensors"))
    if not files or not all(f.is_file() for f in files):
        raise PriorUnavailable(f"no texture prior weights at '{source}'")
    out: dict[Key, Path] = {}
    metas = {f: read_metadata(f) for f in files}
    for f, meta in metas.items():
        stride = int(meta.get("stride", "2")) if meta.get("stride", "2").isdigit() else 0
        step = meta.get("pass", "first")
        if step not in ("first", "later") or (step == "later" and stride != 2):
            raise PriorUnavailable(f"'{f.name}': unknown pass {step!r} of an x{stride} network")
        for kind in meta.get("kinds", "").split(","):
            if kind in KINDS and stride in (2, 4, 8):
                if (kind, stride, step) in out:
                    raise PriorUnavailable(
                        f"'{source}' has two x{stride} {step}-pass weights files for {kind} maps"
                    )
                out[kind, stride, step] = f
    if not out:
        raise PriorUnavailable(f"'{source}' holds no weights for colour, data or normal maps")
    orphans = {k for k, _, p in out if p == "later"} - {k for k, _, p in out if p == "first"}
    if orphans:
        raise PriorUnavailable(
            f"'{source}' has later-pass weights but no first-pass network for "
            f"{', '.join(sorted(orphans))} maps"
        )
    for (kind, _, step), f in out.items():
        first = out.get((kind, 2, "first"))
        want = metas[f].get("first_sha256") if step == "later" else None
        if want and (first is None or file_sha256(first) != want):
            raise PriorUnavailable(
                f"'{f.name}' was trained behind another first-pass network than the set's "
                f"x2 {kind} network"
            )
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
    """(parameters of the networks that run x4 colour, else of the first file's kind's,
    bytes on disk of the set) of the shipped set ``name``; (None, None) where its files are
    missing."""
    try:
        files = weight_files(shipped_files(name))
    except PriorUnavailable:
        return None, None
    kind = "colour" if any(k == "colour" for k, _, _ in files) else next(iter(files))[0]
    nets = {(s, p): load_network(f) for (k, s, p), f in files.items() if k == kind}
    params = _parameters(
        {s: n for (s, p), n in nets.items() if p == "first"}, nets.get((2, "later"))
    )
    return params, sum(f.stat().st_size for f in set(files.values()))


class TexturePrior(Prior):
    """Networks trained on texture maps: per kind networks of stride 2, 4 or 8 (any of them); a
    scale runs as the fewest passes whose strides multiply to it (x8: x4 then x2), but for
    the ``x4_only`` kinds, whose x4 network runs only for x4 (x8: three x2 passes)."""

    bytes_per_pixel = 8192.0  # as waifu2x-photo: the same network shape
    default_overlap = 32
    one_pass_bytes_per_pixel = 2048.0
    """Peak memory per LR pixel of one pass of a stride-4 network, which runs untiled on the
    CPU up to 1024² (:meth:`tile_limits`): SRMD's x4 of a 1024² input peaks at 1.1 GiB above
    the loaded prior, 1.0 GiB in 9 tiles."""

    def __init__(
        self,
        source: Path | list[Path],
        device: torch.device | str = "cpu",
        *,
        name: str | None = None,
        fallback: str = "waifu2x-photo",
        x4_only: frozenset[str] = frozenset(),
        x2_candidate: frozenset[str] = frozenset(),
    ) -> None:
        super().__init__()
        self.device = torch.device(device)
        self.name = name or f"texture:{source}"
        self.files = weight_files(source)
        loaded: dict[Path, Network] = {}
        self.nets: dict[str, dict[int, Network]] = {}
        self.later: dict[str, Network] = {}
        """Per kind, the network of the x2 passes after the first (where the set has one)."""
        self.calibrations: dict[Network, Calibration] = {}
        """SRMD networks with an int8 calibration in their file -> it."""
        self._int8: dict[Network, Int8SRMD] = {}
        for (kind, stride, step), f in self.files.items():
            if f not in loaded:
                net = load_network(f).to(self.device)
                loaded[f] = net.to(memory_format=torch.channels_last)  # type: ignore[call-overload]  # torch's stubs omit memory_format
                text = read_metadata(f).get(METADATA_KEY)
                if text is not None and isinstance(net, SRMD):
                    try:
                        self.calibrations[net] = Calibration.from_json(text, net.convs)
                    except PriorUnavailable as exc:
                        raise PriorUnavailable(f"'{f.name}': {exc}") from exc
            if step == "later":
                self.later[kind] = loaded[f]
            else:
                self.nets.setdefault(kind, {})[stride] = loaded[f]
        self.spandrel = any(isinstance(n, SpandrelNet) for n in loaded.values())
        """Any of the networks a spandrel model (fine-tuned from ``spandrel:<file>``): tiles
        sized for SpandrelPrior's memory per pixel (transformers need far more than CNNs)."""
        if self.spandrel:
            self.bytes_per_pixel = SpandrelPrior.bytes_per_pixel
        self.fallback = fallback
        self.x4_only = x4_only
        """Kinds whose x4 network makes x4 only; their other scales are x2 passes."""
        self.x2_candidate = frozenset(
            k for k in x2_candidate if {2, 4} <= set(self.nets.get(k, {}))
        )
        """Kinds whose x2 passes are a candidate of their own at x4 (:meth:`candidates`)."""
        self._views: dict[str, Prior] = {}
        self._lock = threading.Lock()
        # images of no stated kind (the optimiser's renders) are colour images: the colour
        # network, or the fallback where the set has none
        self.kind = "colour" if "colour" in self.nets else None
        if self.kind is None:
            self.scales = self.for_kind("colour").scales
            self.one_pass_scales = self.for_kind("colour").one_pass_scales
        else:
            self.scales = self._scales(self.kind)
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

    def candidates(self, kind: str, scale: int) -> list[Prior]:
        """The kind's own network, then the fallback: a network trained on textures need not
        beat the photo prior on every map, so the self-check keeps whichever reconstructs
        the map better (prior/selfcheck.py). At x4, an ``x2_candidate`` kind also offers its
        x2 network's two passes (:meth:`x2_passes`)."""
        own = self.for_kind(kind)
        if kind not in self.nets:
            return [own]
        from .registry import load_prior

        out = [own, load_prior(self.fallback, self.device)]
        if scale == 4 and kind in self.x2_candidate:
            out.append(self.x2_passes(kind))
        return out

    def x2_passes(self, kind: str) -> Prior:
        """The kind's x2 network alone, every scale made by its passes, as a prior of its own
        (named ``<set>[<kind>/x2]``)."""
        key = f"{kind}/x2"
        with self._lock:
            if key not in self._views:
                self._views[key] = _KindView(self, kind, frozenset({2}))
            return self._views[key]

    def num_parameters(self) -> int:
        if self.kind is None:
            return self.for_kind("colour").num_parameters()
        return _parameters(self.nets[self.kind], self.later.get(self.kind))

    def _passes(self, kind: str, scale: int, only: Strides = None) -> list[int] | None:
        strides = set(self.nets[kind]) if only is None else set(only)
        if kind in self.x4_only and scale != 4:
            strides.discard(4)
        return passes(strides, scale)

    def _scales(self, kind: str, only: Strides = None) -> tuple[int, ...]:
        return tuple(s for s in (2, 4, 8) if self._passes(kind, s, only))

    def _tile_limits(self, kind: str, scale: int, only: Strides = None) -> tuple[float, int]:
        # one pass of a stride-4 network has every layer but its head at the LR size: the
        # overlap a tile recomputes costs more than the memory traffic of a larger tile (SRMD,
        # x4 of a 1024² input on a 2-core EPYC: 28.9 s untiled, 32.2 s in 9 tiles)
        if self._passes(kind, scale, only) == [4] and not self.spandrel:
            return self.one_pass_bytes_per_pixel, 1024
        return self.bytes_per_pixel, self.cpu_tile_max

    def tile_limits(self, scale: int) -> tuple[float, int]:
        if self.kind is None:
            return self.for_kind("colour").tile_limits(scale)
        return self._tile_limits(self.kind, scale)

    def _int8_ready(self, kind: str, only: Strides = None) -> bool:
        firsts = self.nets[kind] if only is None else {s: self.nets[kind][s] for s in only}
        nets = [*firsts.values(), self.later.get(kind) if 2 in firsts else None]
        return any(net in self.calibrations for net in nets if net is not None)

    def int8_ready(self) -> bool:
        if self.kind is None:
            return self.for_kind("colour").int8_ready()
        return self._int8_ready(self.kind)

    def _run(
        self, kind: str, x: torch.Tensor, scale: int, int8: bool = False, only: Strides = None
    ) -> torch.Tensor:
        nets, later = self.nets[kind], self.later.get(kind)
        with self._lock:
            for i, stride in enumerate(self._passes(kind, scale, only) or []):
                net = later if i and stride == 2 and later is not None else nets[stride]
                if int8 and net in self.calibrations:
                    if net not in self._int8:
                        self._int8[net] = Int8SRMD(net, self.calibrations[net])  # type: ignore[arg-type]  # calibrated networks are SRMD
                    x = self._int8[net](x).clamp_(0.0, 1.0)
                else:
                    x = net(x).clamp_(0.0, 1.0)
        return x

    def _forward(self, x: torch.Tensor, scale: int) -> torch.Tensor:
        if self.kind is None:
            return self.for_kind("colour")._forward(x, scale)
        return self._run(self.kind, x, scale, self.precision_in_use() == "int8")

    def describe(self) -> dict:
        info = super().describe()
        info["kinds"] = {
            k: sorted(f.name for (kind, _, _), f in self.files.items() if kind == k)
            or self.fallback
            for k in KINDS
        }
        if self.x4_only:
            info["x4_only"] = sorted(self.x4_only)
        return info


class _KindView(Prior):
    """One kind's networks of a :class:`TexturePrior`, as a prior of its own; with ``only``,
    those of these strides alone."""

    def __init__(self, parent: TexturePrior, kind: str, only: Strides = None) -> None:
        super().__init__()
        self.parent, self.kind, self.only = parent, kind, only
        strides = sorted(parent.nets[kind] if only is None else only)
        part = kind if only is None else f"{kind}/x{strides[0]}"
        self.name = f"{parent.name}[{part}]"
        self.scales, self.device = parent._scales(kind, only), parent.device
        self.one_pass_scales = tuple(strides)
        self.bytes_per_pixel = parent.bytes_per_pixel
        self.default_overlap = parent.default_overlap

    def _nets(self) -> dict[int, Network]:
        nets = self.parent.nets[self.kind]
        return nets if self.only is None else {s: nets[s] for s in self.only}

    def num_parameters(self) -> int:
        return _parameters(self._nets(), self.parent.later.get(self.kind))

    def tile_limits(self, scale: int) -> tuple[float, int]:
        return self.parent._tile_limits(self.kind, scale, self.only)

    def int8_ready(self) -> bool:
        return self.parent._int8_ready(self.kind, self.only)

    def _forward(self, x: torch.Tensor, scale: int) -> torch.Tensor:
        int8 = self.precision_in_use() == "int8"
        return self.parent._run(self.kind, x, scale, int8, self.only)


def _parameters(nets: dict[int, Network], later: Network | None = None) -> int:
    """Parameters of the networks that run x4: the one-pass x4 network where there is one,
    else the x2 network and the later-pass network."""
    if 4 in nets:
        return sum(p.numel() for p in nets[4].parameters())
    used = [nets[min(nets)]] + ([later] if later is not None else [])
    return sum(p.numel() for net in used for p in net.parameters())
