"""glTF materials as pbrsr reads them: each :class:`Material` with its factors and resolved
:class:`TextureRef`s (texCoord set, KHR_texture_transform, the KHR_materials_* textures)."""

from __future__ import annotations

import math

import numpy as np

from ..errors import InvalidAsset, UnsupportedAsset
from .gltf_read import (
    get_index,
    num_list,
)
from .gltf_textures import texture_sources
from .model import (
    EXTENSION_ROLES,
    REPEAT,
    Material,
    TextureRef,
)

SLOT_KEYS = {
    "base_color": ("pbrMetallicRoughness", "baseColorTexture"),
    "metallic_roughness": ("pbrMetallicRoughness", "metallicRoughnessTexture"),
    "normal": (None, "normalTexture"),
    "occlusion": (None, "occlusionTexture"),
    "emissive": (None, "emissiveTexture"),
}


# ----------------------------------------------------------------------------- transforms
def texture_transform_matrix(ext: dict) -> tuple[float, ...]:
    """KHR_texture_transform -> row-major 3x3 ``T * R * S`` exactly as the extension's GLSL
    builds it, applied to column vectors ``(u, v, 1)``: ``u' = sx*cos(r)*u - sy*sin(r)*v + ox``,
    ``v' = sx*sin(r)*u + sy*cos(r)*v + oy``."""
    ox, oy = (ext.get("offset") or [0.0, 0.0])[:2]
    r = float(ext.get("rotation", 0.0))
    sx, sy = (ext.get("scale") or [1.0, 1.0])[:2]
    c, s = math.cos(r), math.sin(r)
    t = np.array([[1, 0, ox], [0, 1, oy], [0, 0, 1]], dtype=np.float64)
    # the spec's GLSL mat3(c, s, 0, -s, c, 0, 0, 0, 1) is column-major: rows (c, -s), (s, c)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=np.float64)
    sc = np.array([[sx, 0, 0], [0, sy, 0], [0, 0, 1]], dtype=np.float64)
    return tuple(float(x) for x in (t @ rot @ sc).reshape(-1))


MAX_TEXCOORD_SETS = 32
"""Texture coordinate sets (TEXCOORD_0..31) a material may name; real assets use one or two."""


def _texcoord_set(value, what: str) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or value < 0:
        raise InvalidAsset(f"{what} has an invalid texCoord {value!r:.40}")
    if value >= MAX_TEXCOORD_SETS:
        raise UnsupportedAsset(
            f"{what} names texture coordinate set {value}; pbrsr reads sets 0 to "
            f"{MAX_TEXCOORD_SETS - 1}"
        )
    return value


def texture_ref(doc: dict, info: dict, what: str) -> TextureRef | None:
    if not isinstance(info, dict):
        raise InvalidAsset(f"{what} is not an object")
    textures = doc.get("textures", [])
    ti = get_index(info, "index", len(textures), what)
    tex = textures[ti]
    image, _ = texture_sources(doc, ti)
    if image is None:
        return None
    texcoord = _texcoord_set(info.get("texCoord", 0), what)
    uv_transform = None
    ktt = (info.get("extensions") or {}).get("KHR_texture_transform")
    if isinstance(ktt, dict):
        uv_transform = texture_transform_matrix(ktt)
        if "texCoord" in ktt:
            texcoord = _texcoord_set(ktt["texCoord"], f"{what}'s KHR_texture_transform")
    wrap_s = wrap_t = REPEAT
    mag = minf = None
    if "sampler" in tex:
        si = get_index(tex, "sampler", len(doc.get("samplers", [])), f"texture {ti}")
        smp = doc["samplers"][si]
        wrap_s = smp.get("wrapS", REPEAT)
        wrap_t = smp.get("wrapT", REPEAT)
        mag, minf = smp.get("magFilter"), smp.get("minFilter")
    return TextureRef(
        image=image,
        texcoord=texcoord,
        uv_transform=uv_transform,
        wrap_s=wrap_s,
        wrap_t=wrap_t,
        mag_filter=mag,
        min_filter=minf,
    )


def read_material(doc: dict, i: int) -> Material:
    m = doc["materials"][i]
    what = f"material {i}"
    pbr = m.get("pbrMetallicRoughness") or {}
    mat = Material(index=i, name=str(m.get("name", "")))
    if "baseColorFactor" in pbr:
        r, g, b, a = num_list(pbr["baseColorFactor"], 4, what)
        mat.base_color_factor = (r, g, b, a)
    mat.metallic_factor = float(pbr.get("metallicFactor", 1.0))
    mat.roughness_factor = float(pbr.get("roughnessFactor", 1.0))
    if "emissiveFactor" in m:
        r, g, b = num_list(m["emissiveFactor"], 3, what)
        mat.emissive_factor = (r, g, b)
    for role, (parent, key) in SLOT_KEYS.items():
        holder = pbr if parent else m
        if key in holder:
            setattr(mat, role, texture_ref(doc, holder[key], f"{what}.{key}"))
    if "normalTexture" in m:
        mat.normal_scale = float(m["normalTexture"].get("scale", 1.0))
    if "occlusionTexture" in m:
        mat.occlusion_strength = float(m["occlusionTexture"].get("strength", 1.0))
    exts = m.get("extensions") or {}
    for role, (ext, key, _) in EXTENSION_ROLES.items():
        holder = exts.get(ext)
        if isinstance(holder, dict) and isinstance(holder.get(key), dict):
            ref = texture_ref(doc, holder[key], f"{what}.{ext}.{key}")
            if ref is not None:
                mat.extension_textures[role] = ref
    es = exts.get("KHR_materials_emissive_strength")
    if isinstance(es, dict):
        mat.emissive_strength = float(es.get("emissiveStrength", 1.0))
    mode = m.get("alphaMode", "OPAQUE")
    mat.alpha_mode = mode if mode in ("OPAQUE", "MASK", "BLEND") else "OPAQUE"
    mat.alpha_cutoff = float(m.get("alphaCutoff", 0.5))
    mat.double_sided = bool(m.get("doubleSided", False))
    return mat


# ----------------------------------------------------------------------------- images
