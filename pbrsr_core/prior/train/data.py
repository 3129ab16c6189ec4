"""Training data for texture priors: a folder of CC0 materials, split by material, sampled
as (LR, HR) crop pairs by the evaluation protocol's degradation.

A texture folder holds one directory per material with a ``manifest.json`` beside them
listing each material's map files (the layout of ``shared/textures``). Map types are three
signals, each trained as a 3-channel image as the direct prior sees it (prior/direct.py):

- ``colour``: the basecolor map, sRGB as stored;
- ``data``: one scalar map of a material (roughness, metallic, ao or height) in all three
  channels, as the direct prior runs a data map: channel by channel, each a greyscale image;
- ``normal``: the tangent-space normal map, encoded (OpenGL, +Y up).

Each sample is an HR crop, one of the eight flips/rotations of the square applied so that
a normal map stays a normal map (:func:`dihedral`), then blurred and bicubic-downsampled by
:func:`pbrsr_core.degrade.degrade_tensor` (normal LR crops are renormalised, as
``pbrsr degrade`` writes them). With a JPEG stage (``jpeg``: a quality range), a share of
the LR crops (half by default) are then compressed as a JPEG file would store them
(:func:`jpeg_lr`), as real assets ship their maps. A share of the crops may be procedural
drawings instead (``graphics``, :mod:`.graphics`). Batches are a pure function of
``(seed, step)``, so a run resumed from a checkpoint draws exactly the batches it would have
drawn.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ...asset.jpeg import compress, standard_quant
from ...degrade import check_kernels, downsample
from ...errors import InvalidOptions
from ..symmetry import dihedral
from .graphics import data_graphics_crop, graphics_crop, normal_graphics_crop

KINDS = ("colour", "data", "normal")
SCALAR_MAPS = ("roughness", "metallic", "ao", "height")
HOLDOUT_QUOTA = {"basecolor": 12, "normal": 4, "roughness": 4, "metallic": 3, "ao": 2, "height": 3}
"""How many held-out materials must carry each map: at least ten materials in all and
several of each map type."""


@dataclass
class Material:
    name: str
    maps: dict[str, np.ndarray] = field(default_factory=dict)  # map -> (H, W, C) uint8

    def has(self, kind: str) -> bool:
        if kind == "colour":
            return "basecolor" in self.maps
        if kind == "normal":
            return "normal" in self.maps
        return any(m in self.maps for m in SCALAR_MAPS)

    def size(self, kind: str) -> tuple[int, int]:
        key = {"colour": "basecolor", "normal": "normal"}.get(kind)
        if key is None:
            key = next(m for m in SCALAR_MAPS if m in self.maps)
        return self.maps[key].shape[:2]


def texture_folder(given: Path | None = None) -> Path:
    """The texture set to read: ``given``, else $PBRSR_TEXTURES, else the shared texture set
    beside the repository; :class:`InvalidOptions` when it is not a folder."""
    env = os.environ.get("PBRSR_TEXTURES")
    shared = Path(__file__).resolve().parents[4] / "shared" / "textures"
    root = given or (Path(env) if env else shared)
    if not root.is_dir():
        raise InvalidOptions(f"texture folder {root} not found (pass --textures)")
    return root


def read_manifest(root: Path) -> dict[str, dict]:
    """``root/manifest.json`` as a dict of material name -> entry (with ``files``)."""
    path = Path(root) / "manifest.json"
    if not path.is_file():
        raise InvalidOptions(f"no manifest.json in the texture folder {root}")
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise InvalidOptions(f"{path} is not readable JSON: {exc}") from exc
    if not isinstance(manifest, dict) or not all(
        isinstance(v, dict) and isinstance(v.get("files"), dict) for v in manifest.values()
    ):
        raise InvalidOptions(f"{path}: expected {{material: {{'files': {{map: file}}}}}}")
    return manifest


def _rank(name: str) -> str:
    return hashlib.sha256(name.encode("utf-8")).hexdigest()


def split_materials(manifest: dict[str, dict]) -> tuple[list[str], list[str]]:
    """(train, held out): a deterministic split by material. Materials are taken in the
    order of their names' SHA-256; one is held out while it brings a map type still short of
    its quota: :data:`HOLDOUT_QUOTA`, at most a fifth of the materials with that map (so a
    small folder keeps most of each map type for training). The same manifest always gives
    the same split."""
    counts: dict[str, int] = {}
    for entry in manifest.values():
        for m in entry["files"]:
            counts[m] = counts.get(m, 0) + 1
    need = {m: min(q, counts.get(m, 0) // 5) for m, q in HOLDOUT_QUOTA.items()}
    held = []
    for name in sorted(manifest, key=_rank):
        maps = set(manifest[name]["files"])
        if any(need.get(m, 0) > 0 for m in maps):
            held.append(name)
            for m in maps:
                if m in need:
                    need[m] -= 1
    train = sorted(set(manifest) - set(held))
    return train, sorted(held)


def _read_rgb8(path: Path, channels: int) -> np.ndarray:
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(str(path))
    if buf.has_error:
        raise InvalidOptions(f"cannot read {path}: {buf.geterror()}")
    px = buf.get_pixels(oiio.UINT8)
    if px is None or px.ndim != 3:
        raise InvalidOptions(f"cannot read {path}")
    if channels == 1:
        return np.ascontiguousarray(px[..., :1] if px.shape[2] < 3 else px[..., 1:2])
    if px.shape[2] == 1:
        px = np.repeat(px, 3, axis=2)
    return np.ascontiguousarray(px[..., :3])


def load_materials(root: Path, names: list[str], manifest: dict[str, dict]) -> list[Material]:
    """Decode every map of the named materials into memory (uint8)."""
    out = []
    for name in names:
        mat = Material(name)
        for key, file in manifest[name]["files"].items():
            if key not in ("basecolor", "normal", *SCALAR_MAPS):
                continue
            path = Path(root) / name / file
            mat.maps[key] = _read_rgb8(path, 3 if key in ("basecolor", "normal") else 1)
        out.append(mat)
    return out


def normalize_encoded(t: torch.Tensor) -> torch.Tensor:
    """Encoded normals (N, 3, H, W) -> unit length, z >= 0, re-encoded."""
    n = t * 2.0 - 1.0
    n = torch.cat([n[:, :2], n[:, 2:3].clamp_min(0.0)], 1)
    n = n / (n * n).sum(1, keepdim=True).clamp_min(1e-12).sqrt()
    return (n + 1.0) * 0.5


def degrade_pair(hr: torch.Tensor, scale: int, kind: str, kernel: str = "gaussian") -> torch.Tensor:
    """The LR input for HR crops (N, 3, H, W): blur + bicubic down (the protocol), or another
    ``kernel`` of :data:`~pbrsr_core.degrade.KERNELS`, clamped (normal maps renormalised)."""
    lr = downsample(hr, scale, kernel).clamp_(0.0, 1.0)
    return normalize_encoded(lr) if kind == "normal" else lr


def jpeg_lr(
    lr: torch.Tensor, rng: np.random.Generator, qualities: tuple[int, int], share: float
) -> torch.Tensor:
    """The JPEG stage of the LR model: with probability ``share``, ``lr`` (1, 3, h, w)
    compressed at a quality drawn uniformly from ``qualities`` (inclusive), chroma at full
    resolution (4:4:4) or subsampled (4:2:0) with equal odds; else ``lr`` unchanged."""
    if rng.random() >= share:
        return lr
    quality = int(rng.integers(qualities[0], qualities[1] + 1))
    return compress(lr, standard_quant(quality, subsampled=bool(rng.random() < 0.5)))


class CropSampler:
    """Draws training batches from materials of one or more map kinds.

    ``batch(step)`` returns ``(lr, hr, kinds)``: lr (B, 3, P/s, P/s), hr (B, 3, P, P) float32
    in [0, 1], and the kind of each sample. Kinds are drawn in turn from ``kinds`` (one kind
    per sample, a joint model sees all three), materials uniformly among those that have the
    kind, crop positions uniformly, and one of the eight symmetries; ``kernels``: the LR
    crop's downsampling kernel (:func:`degrade_pair`), drawn uniformly per crop where there
    are several; ``jpeg`` (a quality range) adds :func:`jpeg_lr` after the degradation for
    ``jpeg_share`` of the crops."""

    def __init__(
        self,
        materials: list[Material],
        kinds: tuple[str, ...],
        scale: int,
        patch: int,
        batch_size: int,
        seed: int,
        jpeg: tuple[int, int] | None = None,
        jpeg_share: float = 0.5,
        graphics: float = 0.0,
        kernels: tuple[str, ...] = ("gaussian",),
    ) -> None:
        for k in kinds:
            if k not in KINDS:
                raise InvalidOptions(f"unknown map kind {k!r}: use {', '.join(KINDS)}")
        check_kernels(kernels)
        if patch % scale:
            raise InvalidOptions(f"the patch ({patch}) must be a multiple of the scale ({scale})")
        self.by_kind = {k: [m for m in materials if m.has(k)] for k in kinds}
        empty = [k for k, ms in self.by_kind.items() if not ms]
        if empty:
            raise InvalidOptions(f"no training material has a {', '.join(empty)} map")
        for k, ms in self.by_kind.items():
            small = [m.name for m in ms if min(m.size(k)) < patch]
            if small:
                raise InvalidOptions(f"{k} maps smaller than the {patch} px patch: {small}")
        self.kinds, self.scale, self.patch = kinds, scale, patch
        self.batch_size, self.seed = batch_size, seed
        self.jpeg, self.jpeg_share = jpeg, jpeg_share
        self.graphics, self.kernels = graphics, kernels

    def _crop(self, rng: np.random.Generator, kind: str) -> np.ndarray:
        if self.graphics and rng.random() < self.graphics:
            drawings = {
                "colour": graphics_crop,
                "data": data_graphics_crop,
                "normal": normal_graphics_crop,
            }
            return drawings[kind](rng, self.patch)
        mats = self.by_kind[kind]
        mat = mats[rng.integers(len(mats))]
        h, w = mat.size(kind)
        y = int(rng.integers(h - self.patch + 1))
        x = int(rng.integers(w - self.patch + 1))
        win = (slice(y, y + self.patch), slice(x, x + self.patch))
        if kind == "colour":
            return mat.maps["basecolor"][win]
        if kind == "normal":
            return mat.maps["normal"][win]
        have = [m for m in SCALAR_MAPS if m in mat.maps]
        return np.repeat(mat.maps[have[rng.integers(len(have))]][win], 3, axis=2)

    def batch(self, step: int) -> tuple[torch.Tensor, torch.Tensor, list[str]]:
        rng = np.random.default_rng([self.seed, step])
        kinds = [
            self.kinds[(step * self.batch_size + i) % len(self.kinds)]
            for i in range(self.batch_size)
        ]
        hrs, lrs = [], []
        for kind in kinds:
            crop = torch.from_numpy(self._crop(rng, kind)).permute(2, 0, 1)[None].float() / 255.0
            hr = dihedral(crop, int(rng.integers(8)), kind).contiguous()
            hrs.append(hr)
            kernel = self.kernels[0]
            if len(self.kernels) > 1:  # one draw more only then: the protocol's runs repeat
                kernel = self.kernels[int(rng.integers(len(self.kernels)))]
            lr = degrade_pair(hr, self.scale, kind, kernel)
            lrs.append(lr if self.jpeg is None else jpeg_lr(lr, rng, self.jpeg, self.jpeg_share))
        return torch.cat(lrs), torch.cat(hrs), kinds


def validation_crops(
    materials: list[Material], kind: str, patch: int, per_material: int = 2
) -> list[tuple[str, np.ndarray]]:
    """Fixed HR crops (name, (patch, patch, 3) uint8) of held-out materials for ``kind``:
    ``per_material`` crops at positions set by the material's name, so every run and every
    prior is scored on the same pixels. A data crop is one scalar map in all three channels,
    the crops of a material taking its scalar maps in turn (each at least once); its name
    ends in the map's (``material#i:roughness``, :func:`crop_map`)."""
    out = []
    for mat in materials:
        if not mat.has(kind) or min(mat.size(kind)) < patch:
            continue
        rng = np.random.default_rng(int(_rank(mat.name)[:8], 16))
        h, w = mat.size(kind)
        have = [m for m in SCALAR_MAPS if m in mat.maps]
        n = max(per_material, len(have)) if kind == "data" else per_material
        for i in range(n):
            y = int(rng.integers(h - patch + 1))
            x = int(rng.integers(w - patch + 1))
            win = (slice(y, y + patch), slice(x, x + patch))
            if kind == "colour":
                crop = mat.maps["basecolor"][win]
            elif kind == "normal":
                crop = mat.maps["normal"][win]
            else:
                crop = np.repeat(mat.maps[have[i % len(have)]][win], 3, axis=2)
            tag = f":{have[i % len(have)]}" if kind == "data" else ""
            out.append((f"{mat.name}#{i}{tag}", np.ascontiguousarray(crop)))
    return out


def crop_map(name: str) -> str:
    """The scalar map (roughness, metallic, ao, height) a :func:`validation_crops` data crop
    holds."""
    return name.rpartition(":")[2]
