"""Which images of an asset are maps to upscale, and their conversions between the stored
encoding (numpy, as in the file) and the optimisation space (torch, linear colour)."""

from __future__ import annotations

import re
from collections.abc import Collection

import numpy as np
import torch

from .asset.model import MIRRORED_REPEAT, NORMAL_ROLES, REPEAT, SRGB_ROLES, Asset, ImageData
from .colour import linear_to_srgb, srgb_to_linear
from .errors import UnprocessableAsset
from .prior.direct import HIDDEN_ALPHA


def kind_of(roles: set[str]) -> str:
    """How an image is treated: ``normal``, ``colour`` (sRGB baseColor/emissive) or ``data``
    (metallicRoughness / occlusion, linear)."""
    if roles & NORMAL_ROLES:
        return "normal"
    if roles & SRGB_ROLES:
        return "colour"
    return "data"


def role_label(roles: set[str]) -> str:
    """A short label for file names and reports: ``base_color``, ``orm``, ``normal``..."""
    if {"metallic_roughness", "occlusion"} <= roles:
        return "orm"
    return "+".join(sorted(roles)) if roles else "unused"


def image_wrap(asset: Asset, index: int) -> tuple[str | None, str | None] | None:
    """How image ``index`` continues past its edges where the scene shows it, per axis
    (wrapS, wrapT): "repeat" or "mirror" when a texture using it has that sampler mode and
    the mesh samples it beyond [0, 1] on that axis (its UVs, through any KHR_texture_transform,
    leave the unit square: the texture visibly repeats); else None. None when no axis does
    (an atlas inside the unit square needs no context)."""
    from .uvmask import transform_uv

    mesh = asset.mesh
    tris, mats = mesh.t_pos_idx, mesh.t_mat
    modes: list[set[int]] = [set(), set()]
    for m in asset.materials:
        for ref in m.textures().values():
            if ref.image != index or ref.texcoord not in mesh.v_uv:
                continue
            corners = tris[mats == m.index].reshape(-1)
            if corners.numel() == 0:
                continue
            uv = transform_uv(mesh.v_uv[ref.texcoord][corners].double(), ref)
            low, high = uv.amin(0), uv.amax(0)
            for axis, mode in ((0, ref.wrap_s), (1, ref.wrap_t)):
                if low[axis] < -1e-3 or high[axis] > 1 + 1e-3:
                    modes[axis].add(mode)

    def mode_of(found: set[int]) -> str | None:
        if REPEAT in found:
            return "repeat"
        return "mirror" if MIRRORED_REPEAT in found else None

    wrap = (mode_of(modes[0]), mode_of(modes[1]))
    return None if wrap == (None, None) else wrap


def image_cutout(asset: Asset, index: int) -> float | None:
    """For a cutout's colour (an image with alpha that a material with alphaMode MASK or
    BLEND reads as base colour): the alpha up to which its texels are never seen (MASK: its
    alphaCutoff; BLEND: about 0); the lowest over the materials that use it. None otherwise."""
    img = asset.images[index]
    if img.pixels.ndim != 3 or img.pixels.shape[2] not in (2, 4):
        return None
    seen_from = [
        m.alpha_cutoff if m.alpha_mode == "MASK" else HIDDEN_ALPHA
        for m in asset.materials
        if m.base_color is not None and m.base_color.image == index
    ]
    opaque = any(
        m.alpha_mode == "OPAQUE"
        for m in asset.materials
        if m.base_color is not None and m.base_color.image == index
    )
    return None if opaque or not seen_from else min(seen_from)


def upscalable_images(asset: Asset) -> list[ImageData]:
    """Images some material slot uses, in glTF order (each once, however often shared)."""
    return [img for img in asset.images if img.roles]


def listed(image: ImageData, roles: Collection[str] | None) -> bool:
    """Whether ``maps`` (``roles``; None: every map) has ``image`` upscaled: any of its roles
    is listed."""
    return roles is None or bool(image.roles & set(roles))


def map_scales(
    images: list[ImageData],
    scale: int,
    max_size: int | None,
    roles: Collection[str] | None = None,
    others: str = "keep",
) -> dict[int, int]:
    """Per image index, the factor its map is upscaled by: ``scale``, or with ``max_size`` the
    largest of ``scale``, ``scale / 2``, ... whose output is at most ``max_size`` px on a side;
    1 (the map kept as it is) where even x2 would be larger, or, with ``roles``, where none of
    the image's roles is listed and ``others`` is ``keep`` (``bicubic``: such a map has the
    factor a listed one would). Refused (UnprocessableAsset) when no image has a listed role,
    or when every map would be kept."""
    chosen = [img for img in images if listed(img, roles)]
    if images and not chosen:
        asked = ", ".join(roles or ())
        present = ", ".join(sorted({role for img in images for role in img.roles}))
        raise UnprocessableAsset(
            f"nothing to upscale: no map of this asset has a role in maps ({asked}); "
            f"its maps' roles: {present}"
        )
    out = {img.index: 1 for img in images}
    for img in images if others == "bicubic" else chosen:
        f = scale
        while max_size is not None and f > 1 and max(img.width, img.height) * f > max_size:
            f //= 2
        out[img.index] = f
    if out and all(f == 1 for f in out.values()):
        raise UnprocessableAsset(
            f"nothing to upscale: every map would be over max_size ({max_size} px) at x2"
        )
    return out


def bicubic_only(
    images: list[ImageData], factors: dict[int, int], roles: Collection[str] | None
) -> set[int]:
    """The images :func:`map_scales` upscales although none of their roles is listed in
    ``roles`` (``other_maps`` bicubic): bicubic's, never a prior's or the optimiser's."""
    return {img.index for img in images if factors[img.index] > 1 and not listed(img, roles)}


def to_param(image: ImageData) -> torch.Tensor:
    """Stored pixels -> optimisation space (H, W, C): colour RGB linearised (alpha stays)."""
    px = torch.from_numpy(np.ascontiguousarray(image.pixels, dtype=np.float32))
    return encoded_to_param(px, kind_of(image.roles))


def encoded_to_param(px: torch.Tensor, kind: str) -> torch.Tensor:
    if kind != "colour":
        return px.clone()
    out = px.clone()
    c = min(3, px.shape[-1])
    out[..., :c] = srgb_to_linear(px[..., :c])
    return out


def param_to_encoded(t: torch.Tensor, kind: str) -> np.ndarray:
    """Optimisation space -> stored encoding, float32 numpy in [0, 1], finite."""
    t = torch.nan_to_num(t.detach().float().cpu(), nan=0.0, posinf=1.0, neginf=0.0)
    if kind == "colour":
        t = t.clone()
        c = min(3, t.shape[-1])
        t[..., :c] = linear_to_srgb(t[..., :c])
    return t.clamp(0.0, 1.0).numpy().astype(np.float32)


def safe_stem(name: str) -> str:
    stem = re.sub(r"\.[A-Za-z0-9]{2,4}$", "", name.rsplit("/", 1)[-1])
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", stem).strip("._") or "image"
    return stem[:60]


def map_file_stem(image: ImageData) -> str:
    return f"{image.index:02d}_{role_label(image.roles)}_{safe_stem(image.name)}"
