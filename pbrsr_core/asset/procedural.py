"""Deterministic procedural assets: the demo object, a feature-rich test asset factory, and a
flat textured quad for analytic render tests. Same arguments, same bytes.

* :func:`make_demo_asset`: a rounded box (about 3k triangles) with a brick-and-paint albedo, a
  packed ORM texture (mortar rough and occluded, a polished metal band), and a tangent-space
  normal map derived from the same height field as the albedo's bricks.
* :func:`make_test_asset`: a small scene whose ``features`` switch on every glTF feature the
  asset I/O must preserve (see :data:`TEST_FEATURES`).
* :func:`make_quad_asset`: one quad in the z = 0 plane, facing +z, with given maps.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from .gltf_build import ARRAY_BUFFER, GltfBuilder
from .model import CLAMP_TO_EDGE, MIRRORED_REPEAT, REPEAT
from .tangents import generate_tangents

TEST_FEATURES: frozenset[str] = frozenset(
    {
        "orm",  # one ORM image shared by occlusion and metallicRoughness
        "occlusion",  # a separate occlusion image
        "emissive",  # emissive texture + KHR_materials_emissive_strength
        "normal_scale",  # normalTexture.scale != 1
        "texture_transform",  # KHR_texture_transform with a texCoord override
        "texcoord1",  # a texture read through TEXCOORD_1
        "sampler_wrap",  # samplers with CLAMP_TO_EDGE / MIRRORED_REPEAT and filters
        "shared_image",  # one image used by two materials
        "alpha_mask",  # RGBA baseColor, alphaMode MASK
        "alpha_blend",  # RGBA baseColor, alphaMode BLEND
        "data_uri",  # (gltf only) buffer and images as data URIs
        "png16",  # a 16-bit PNG
        "exr",  # (gltf only) an EXR image (half)
        "jpeg",  # a JPEG baseColor
        "hierarchy",  # nested nodes with TRS and matrix transforms
        "animation",
        "skin",
        "camera",
        "extras",
        "extensions",  # an extension pbrsr does not know, on a node
        "no_normals",  # the main mesh has no NORMAL (flat normals are generated)
        "tangents",  # the main mesh stores TANGENT (otherwise they are generated)
        "strip",  # a TRIANGLE_STRIP primitive
        "khr_materials",  # clearcoat, sheen, specular, transmission, volume, iridescence maps
    }
)
DEFAULT_TEST_FEATURES = frozenset(
    TEST_FEATURES - {"data_uri", "exr", "no_normals", "jpeg", "khr_materials"}
)


# ----------------------------------------------------------------------------- geometry
def uv_sphere(n_lat: int = 12, n_lon: int = 24, radius: float = 1.0):
    """A UV sphere: pos (V, 3), nrm (V, 3), uv (V, 2) in glTF convention, tri (T, 3)."""
    lat = np.linspace(0.0, math.pi, n_lat + 1)
    lon = np.linspace(0.0, 2 * math.pi, n_lon + 1)
    th, ph = np.meshgrid(lat, lon, indexing="ij")
    nrm = np.stack([np.sin(th) * np.cos(ph), np.cos(th), -np.sin(th) * np.sin(ph)], axis=-1)
    uv = np.stack([ph / (2 * math.pi), th / math.pi], axis=-1)
    nrm = nrm.reshape(-1, 3)
    uv = uv.reshape(-1, 2)
    tris = []
    w = n_lon + 1
    for i in range(n_lat):
        for j in range(n_lon):
            a, b, c, d = i * w + j, i * w + j + 1, (i + 1) * w + j, (i + 1) * w + j + 1
            if i > 0:
                tris.append((a, c, b))
            if i < n_lat - 1:
                tris.append((b, c, d))
    return nrm * radius, nrm, uv, np.array(tris, dtype=np.int64)


def grid_quad(n: int = 1, half: float = 1.0):
    """A square in z = 0 facing +z, n x n cells: pos, nrm, uv (top-left (0, 0) at (-h, +h)),
    tri."""
    t = np.linspace(0.0, 1.0, n + 1)
    u, v = np.meshgrid(t, t, indexing="xy")
    pos = np.stack([(2 * u - 1) * half, (1 - 2 * v) * half, np.zeros_like(u)], axis=-1)
    pos = pos.reshape(-1, 3)
    uv = np.stack([u, v], axis=-1).reshape(-1, 2)
    nrm = np.tile([0.0, 0.0, 1.0], (pos.shape[0], 1))
    tris = []
    for i in range(n):
        for j in range(n):
            a, b = i * (n + 1) + j, i * (n + 1) + j + 1
            c, d = a + n + 1, b + n + 1
            tris += [(a, c, b), (b, c, d)]
    return pos, nrm, uv, np.array(tris, dtype=np.int64)


def rounded_box(n: int = 16, radius: float = 0.25):
    """A cube of half-size 1 with rounded edges; each face has the full [0, 1]^2 UV square.
    Returns pos (V, 3), nrm (V, 3), uv (V, 2), tri (T, 3)."""
    faces = [  # (normal axis, sign, u axis, v axis) with u right / v down seen from outside
        (np.array([1, 0, 0]), np.array([0, 0, -1]), np.array([0, -1, 0])),
        (np.array([-1, 0, 0]), np.array([0, 0, 1]), np.array([0, -1, 0])),
        (np.array([0, 1, 0]), np.array([1, 0, 0]), np.array([0, 0, 1])),
        (np.array([0, -1, 0]), np.array([1, 0, 0]), np.array([0, 0, -1])),
        (np.array([0, 0, 1]), np.array([1, 0, 0]), np.array([0, -1, 0])),
        (np.array([0, 0, -1]), np.array([-1, 0, 0]), np.array([0, -1, 0])),
    ]
    t = np.linspace(0.0, 1.0, n + 1)
    u2, v2 = np.meshgrid(t, t, indexing="xy")
    u, v = u2.reshape(-1), v2.reshape(-1)
    cells = []
    for i in range(n):
        for j in range(n):
            a, b = i * (n + 1) + j, i * (n + 1) + j + 1
            c, d = a + n + 1, b + n + 1
            cells += [(a, c, b), (b, c, d)]
    cell = np.array(cells, dtype=np.int64)
    P, N, UV, T = [], [], [], []
    inner = 1.0 - radius
    for k, (nz, ax_u, ax_v) in enumerate(faces):
        cube = (
            nz[None, :]
            + (2 * u - 1)[:, None] * ax_u[None, :]
            + (2 * v - 1)[:, None] * ax_v[None, :]
        )
        core = np.clip(cube, -inner, inner)
        d = cube - core
        ln = np.linalg.norm(d, axis=1, keepdims=True)
        nrm = d / np.maximum(ln, 1e-12)
        P.append(core + radius * nrm)
        N.append(nrm)
        UV.append(np.stack([u, v], axis=1))
        T.append(cell + k * (n + 1) ** 2)
    return np.concatenate(P), np.concatenate(N), np.concatenate(UV), np.concatenate(T)


# ----------------------------------------------------------------------------- textures
def _hash01(a: np.ndarray, b: np.ndarray, seed: int = 0) -> np.ndarray:
    x = np.sin(a * 12.9898 + b * 78.233 + seed * 37.719) * 43758.5453
    return x - np.floor(x)


def brick_maps(size: int) -> dict[str, np.ndarray]:
    """Brick wall maps on a size x size grid: albedo (sRGB RGB), orm (R occlusion, G
    roughness, B metallic), normal (encoded tangent-space, OpenGL +Y up), height."""
    y, x = np.mgrid[0:size, 0:size].astype(np.float64)
    u, v = (x + 0.5) / size, (y + 0.5) / size
    rows, cols = 8, 4
    r = v * rows
    row = np.floor(r)
    c = u * cols + 0.5 * (row % 2)
    col = np.floor(c)
    fu, fv = c - col, r - row
    edge = np.minimum(np.minimum(fu, 1 - fu) * 2.0 / cols * rows, np.minimum(fv, 1 - fv))
    mortar_w = 0.08
    height = np.clip((edge - mortar_w) / 0.12, 0.0, 1.0)
    height = height * height * (3 - 2 * height)
    h_brick = _hash01(row, col % cols)
    grain = _hash01(np.floor(u * size / 2), np.floor(v * size / 2), 3)
    base = np.stack(
        [0.55 + 0.2 * h_brick, 0.25 + 0.1 * h_brick, 0.18 + 0.05 * h_brick], axis=-1
    ) * (0.9 + 0.1 * grain[..., None])
    painted = (_hash01(row, col % cols, 7) > 0.7)[..., None]
    paint = np.array([0.85, 0.82, 0.70]) * (0.95 + 0.05 * grain[..., None])
    mortar = np.array([0.62, 0.60, 0.57])
    band = (np.abs(v - 0.5) < 0.06)[..., None]
    metal = np.array([0.95, 0.78, 0.45])
    albedo = np.where(painted, paint, base)
    albedo = albedo * height[..., None] + mortar * (1 - height[..., None])
    albedo = np.where(band, metal, albedo)
    rough = np.where(painted[..., 0], 0.45, 0.85 + 0.1 * grain) * height + 0.95 * (1 - height)
    rough = np.where(band[..., 0], 0.25 + 0.1 * grain, rough)
    metallic = np.where(band[..., 0], 1.0, 0.0)
    occl = 0.55 + 0.45 * height
    occl = np.where(band[..., 0], 1.0, occl)
    h = np.where(band[..., 0], 1.0, height) * 0.04  # height in UV-width units
    dhdx = (np.roll(h, -1, axis=1) - np.roll(h, 1, axis=1)) * size / 2
    dhdy = (np.roll(h, -1, axis=0) - np.roll(h, 1, axis=0)) * size / 2
    # +x = +u, +y = image up = -v
    n = np.stack([-dhdx * 8, dhdy * 8, np.ones_like(h)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    f32 = np.float32
    return {
        "albedo": np.clip(albedo, 0, 1).astype(f32),
        "orm": np.stack([occl, rough, metallic], axis=-1).clip(0, 1).astype(f32),
        "normal": (n * 0.5 + 0.5).astype(f32),
        "height": height.astype(f32),
    }


def leaf_maps(size: int, leaves: int = 14, seed: int = 5) -> dict[str, np.ndarray]:
    """A foliage card's maps: ``base_color`` RGBA (leaves with veins and mottling at alpha 1,
    the rest transparent with black under it, as exporters leave it; about 60 % of the texels
    transparent) and ``normal`` (encoded, OpenGL +Y up: each leaf folded along its midrib)."""
    rng = np.random.default_rng(seed)
    y, x = (np.mgrid[0:size, 0:size].astype(np.float64) + 0.5) / size
    rgb = np.zeros((size, size, 3))
    alpha = np.zeros((size, size))
    nx, ny = np.zeros((size, size)), np.zeros((size, size))
    for _ in range(leaves):
        cx, cy = rng.uniform(0.15, 0.85, 2)
        length, width = rng.uniform(0.16, 0.3), rng.uniform(0.05, 0.09)
        angle = rng.uniform(0.0, math.pi)
        ca, sa = math.cos(angle), math.sin(angle)
        along = (x - cx) * ca + (y - cy) * sa  # along the midrib, in [-length, length]
        across = -(x - cx) * sa + (y - cy) * ca
        t = np.clip(along / length, -1.0, 1.0)
        half_width = width * np.sqrt(np.clip(1.0 - t * t, 0.0, 1.0)) * (1.0 - 0.35 * t)
        inside = (np.abs(along) < length) & (np.abs(across) < half_width)
        vein = np.exp(-((across / 0.004) ** 2)) + 0.5 * np.exp(
            -(((np.abs(across) - 0.6 * np.abs(along - 0.3 * length) * 0.5) / 0.003) ** 2)
        ) * (np.abs(across) < half_width * 0.9)
        hue = rng.uniform(-0.08, 0.08)
        mottling = 0.85 + 0.15 * np.sin(90 * along + 17 * hue) * np.cos(70 * across)
        leaf = np.stack(
            [
                (0.22 + hue + 0.3 * vein) * mottling,
                (0.48 + 0.6 * hue + 0.25 * vein) * mottling,
                (0.12 + 0.15 * vein) * mottling,
            ],
            axis=-1,
        )
        rgb[inside] = leaf[inside]
        alpha[inside] = 1.0
        fold = np.sign(across) * 0.35  # the two halves tilt away from the midrib
        nx[inside] = (-fold * sa)[inside]
        ny[inside] = (fold * ca)[inside]
    n = np.stack([nx, -ny, np.ones_like(nx)], axis=-1)  # image y down -> tangent +Y up
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    f32 = np.float32
    return {
        "base_color": np.concatenate([np.clip(rgb, 0, 1), alpha[..., None]], -1).astype(f32),
        "normal": (n * 0.5 + 0.5).astype(f32),
    }


def _pattern(size: int, seed: int, channels: int = 3) -> np.ndarray:
    """A smooth colourful deterministic test pattern (H, W, C) float32 in [0, 1]."""
    y, x = np.mgrid[0:size, 0:size].astype(np.float64) / max(size, 1)
    chans = []
    for c in range(channels):
        f = 1.5 + ((seed * 3 + c) % 5)
        ph = seed * 0.7 + c * 1.3
        chans.append(
            0.5 + 0.4 * np.sin(2 * math.pi * f * x + ph) * np.cos(2 * math.pi * (f - 1) * y)
        )
    return np.stack(chans, axis=-1).astype(np.float32)


# ----------------------------------------------------------------------------- factories
def _write_one_node(b: GltfBuilder, path: Path, node: int) -> Path:
    """Write ``b`` with one scene holding ``node``, as ``.glb`` or ``.gltf`` by suffix."""
    b.doc["scenes"] = [{"nodes": [node]}]
    b.doc["scene"] = 0
    return b.write(path, kind="glb" if path.suffix.lower() == ".glb" else "gltf")


def make_demo_asset(path: Path, size: int = 128) -> Path:
    """Write the demo asset (``.glb`` or ``.gltf`` by suffix) with size x size textures."""
    path = Path(path)
    maps = brick_maps(size)
    pos, nrm, uv, tri = rounded_box(16, 0.25)
    b = GltfBuilder()
    b.doc["asset"]["extras"] = {"pbrsr": "procedural demo asset"}
    albedo = b.texture(b.image(maps["albedo"], name="bricks_albedo"))
    orm = b.texture(b.image(maps["orm"], name="bricks_orm"))
    normal = b.texture(b.image(maps["normal"], name="bricks_normal"))
    mat = b.add(
        "materials",
        {
            "name": "painted_bricks",
            "pbrMetallicRoughness": {
                "baseColorTexture": {"index": albedo},
                "metallicRoughnessTexture": {"index": orm},
            },
            "normalTexture": {"index": normal},
            "occlusionTexture": {"index": orm},
        },
    )
    mesh = b.add(
        "meshes",
        {
            "name": "rounded_box",
            "primitives": [b.primitive(pos, tri, nrm=nrm, uvs={0: uv}, material=mat)],
        },
    )
    return _write_one_node(b, path, b.add("nodes", {"name": "demo", "mesh": mesh}))


def make_cutout_asset(path: Path, size: int = 256) -> Path:
    """A foliage asset (``.glb`` or ``.gltf`` by suffix): three double-sided cards crossing at
    60 degrees around the vertical axis, one material with alphaMode MASK (cutoff 0.5) reading
    :func:`leaf_maps` at size x size (base colour with alpha, normal map)."""
    path = Path(path)
    maps = leaf_maps(size)
    b = GltfBuilder()
    b.doc["asset"]["extras"] = {"pbrsr": "procedural cutout asset"}
    color = b.texture(b.image(maps["base_color"], name="leaves_base_color"))
    normal = b.texture(b.image(maps["normal"], name="leaves_normal"))
    mat = b.add(
        "materials",
        {
            "name": "leaves",
            "pbrMetallicRoughness": {
                "baseColorTexture": {"index": color},
                "metallicFactor": 0.0,
                "roughnessFactor": 0.6,
            },
            "normalTexture": {"index": normal},
            "alphaMode": "MASK",
            "alphaCutoff": 0.5,
            "doubleSided": True,
        },
    )
    pos, nrm, uv, tri = grid_quad(4, 0.5)
    primitives = []
    for k in range(3):
        a = math.radians(60.0 * k)
        rot = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
        tng = np.tile([*(rot @ [1.0, 0.0, 0.0]), 1.0], (pos.shape[0], 1))
        primitives.append(
            b.primitive(pos @ rot.T, tri, nrm=nrm @ rot.T, uvs={0: uv}, tng=tng, material=mat)
        )
    mesh = b.add("meshes", {"name": "cards", "primitives": primitives})
    return _write_one_node(b, path, b.add("nodes", {"name": "foliage", "mesh": mesh}))


def make_quad_asset(
    path: Path,
    maps: dict[str, np.ndarray] | None = None,
    *,
    size: int = 16,
    kind: str | None = None,
    half: float = 1.0,
    subdiv: int = 1,
    factors: dict | None = None,
) -> Path:
    """A quad in z = 0 facing +z spanning [-half, half]^2 with UV (0, 0) at (-half, +half).

    ``maps`` {role: (H, W, C) float32}: roles base_color, metallic_roughness, normal,
    occlusion, emissive; default: a base_color pattern of ``size``. ``factors`` are merged
    into the material JSON (e.g. {"emissiveFactor": [1, 1, 1]}).
    """
    path = Path(path)
    kind = kind or ("glb" if path.suffix.lower() == ".glb" else "gltf")
    if maps is None:
        maps = {"base_color": _pattern(size, 1)}
    b = GltfBuilder()
    pbr: dict = {}
    mat: dict = {"name": "quad", "pbrMetallicRoughness": pbr}
    slots = {
        "base_color": (pbr, "baseColorTexture"),
        "metallic_roughness": (pbr, "metallicRoughnessTexture"),
        "normal": (mat, "normalTexture"),
        "occlusion": (mat, "occlusionTexture"),
        "emissive": (mat, "emissiveTexture"),
    }
    for role, img in maps.items():
        holder, key = slots[role]
        holder[key] = {"index": b.texture(b.image(np.asarray(img, np.float32), name=role))}
    if "emissive" in maps:
        mat.setdefault("emissiveFactor", [1.0, 1.0, 1.0])
    for k, v in (factors or {}).items():
        (pbr if k in ("baseColorFactor", "metallicFactor", "roughnessFactor") else mat)[k] = v
    m = b.add("materials", mat)
    pos, nrm, uv, tri = grid_quad(subdiv, half)
    tng = np.tile([1.0, 0.0, 0.0, 1.0], (pos.shape[0], 1))
    mesh = b.add(
        "meshes", {"primitives": [b.primitive(pos, tri, nrm=nrm, uvs={0: uv}, tng=tng, material=m)]}
    )
    b.doc["nodes"] = [{"mesh": mesh}]
    b.doc["scenes"] = [{"nodes": [0]}]
    b.doc["scene"] = 0
    return b.write(path, kind=kind, image_dir="")


def _khr_material_extensions(b: GltfBuilder, size: int) -> dict:
    """KHR_materials_* extensions with a texture of their own for each of their maps."""

    def tex(seed: int, channels: int, name: str) -> dict:
        return {"index": b.texture(b.image(_pattern(size // 2, seed, channels), name=name))}

    nrm = _pattern(size // 2, 21) * 0.3 + np.array([0.35, 0.35, 0.7], dtype=np.float32)
    exts = {
        "KHR_materials_clearcoat": {
            "clearcoatFactor": 1.0,
            "clearcoatTexture": tex(11, 3, "clearcoat"),
            "clearcoatRoughnessFactor": 0.5,
            "clearcoatRoughnessTexture": tex(12, 3, "clearcoat_roughness"),
            "clearcoatNormalTexture": {"index": b.texture(b.image(nrm, name="clearcoat_normal"))},
        },
        "KHR_materials_sheen": {
            "sheenColorFactor": [1.0, 1.0, 1.0],
            "sheenColorTexture": tex(13, 3, "sheen_color"),
            "sheenRoughnessFactor": 0.5,
            "sheenRoughnessTexture": tex(14, 4, "sheen_roughness"),
        },
        "KHR_materials_specular": {
            "specularTexture": tex(15, 4, "specular"),
            "specularColorTexture": tex(16, 3, "specular_color"),
        },
        "KHR_materials_transmission": {
            "transmissionFactor": 0.5,
            "transmissionTexture": tex(17, 3, "transmission"),
        },
        "KHR_materials_volume": {
            "thicknessFactor": 1.0,
            "thicknessTexture": tex(18, 3, "thickness"),
        },
        "KHR_materials_iridescence": {
            "iridescenceFactor": 1.0,
            "iridescenceTexture": tex(19, 3, "iridescence"),
            "iridescenceThicknessTexture": tex(20, 3, "iridescence_thickness"),
        },
    }
    for name in exts:
        b.use_extension(name)
    return exts


def make_test_asset(
    path: Path,
    *,
    size: int = 64,
    features: set[str] | frozenset[str] = DEFAULT_TEST_FEATURES,
    kind: str | None = None,
) -> Path:
    """Write a small asset exercising ``features`` (a subset of :data:`TEST_FEATURES`).

    Scene: a UV sphere with the main material (baseColor, metallicRoughness, normal, plus
    ORM/occlusion/emissive per features), a quad with a second material, optional strip
    primitive, hierarchy, animation, skin, camera. ``kind`` "glb" or "gltf" (default: the
    suffix). "data_uri" and "exr" need kind "gltf" (a GLB can embed only PNG/JPEG validly).
    """
    path = Path(path)
    kind = kind or ("glb" if path.suffix.lower() == ".glb" else "gltf")
    features = set(features)
    unknown = features - TEST_FEATURES
    if unknown:
        raise ValueError(f"unknown test features: {sorted(unknown)}")
    if kind == "glb" and features & {"data_uri", "exr"}:
        raise ValueError("'data_uri' and 'exr' need kind='gltf'")
    f = features.__contains__
    b = GltfBuilder()
    if f("extras"):
        b.doc["asset"]["extras"] = {"note": "pbrsr test asset", "n": 3}

    samplers = None
    if f("sampler_wrap"):
        b.add(
            "samplers",
            {
                "wrapS": CLAMP_TO_EDGE,
                "wrapT": MIRRORED_REPEAT,
                "magFilter": 9728,
                "minFilter": 9987,
            },
        )
        b.add("samplers", {"wrapS": REPEAT, "wrapT": CLAMP_TO_EDGE})
        samplers = (0, 1)

    # images
    base_rgba = _pattern(size, 1, 4 if f("alpha_mask") and f("shared_image") else 3)
    if base_rgba.shape[2] == 4:
        base_rgba[..., 3] = np.where(base_rgba[..., 3] > 0.5, 1.0, 0.2)
    if f("jpeg") and base_rgba.shape[2] == 3:
        base_img = b.image(base_rgba, fmt="jpeg", name="base color")
    else:
        base_img = b.image(base_rgba, name="base color")
    mr = _pattern(size, 2)
    mr_img = b.image(mr, bits=16 if f("png16") else 8, name="orm" if f("orm") else "metal_rough")
    nrm_px = _pattern(size, 3) * 0.3 + np.array([0.35, 0.35, 0.7], dtype=np.float32)
    if f("exr"):
        nrm_img = b.image(nrm_px, fmt="exr", bits=16, name="normal")
    else:
        nrm_img = b.image(nrm_px, name="normal")

    base_tex = b.texture(base_img, samplers[0] if samplers else None)
    mr_tex = b.texture(mr_img, samplers[1] if samplers else None)
    nrm_tex = b.texture(nrm_img)
    pbr: dict = {
        "baseColorTexture": {"index": base_tex},
        "metallicRoughnessTexture": {"index": mr_tex},
        "baseColorFactor": [1.0, 0.9, 0.8, 1.0],
        "metallicFactor": 0.7,
        "roughnessFactor": 0.9,
    }
    main: dict = {"name": "main", "pbrMetallicRoughness": pbr, "normalTexture": {"index": nrm_tex}}
    if f("normal_scale"):
        main["normalTexture"]["scale"] = 0.6
    if f("orm"):
        main["occlusionTexture"] = {"index": mr_tex, "strength": 0.8}
    if f("occlusion"):
        occ_tex = b.texture(b.image(_pattern(size // 2, 4, 1), name="occlusion"))
        key = "occlusionTexture" if not f("orm") else None
        if key:
            main[key] = {"index": occ_tex, "strength": 0.9}
        else:  # ORM already there: use the separate occlusion image on the second material
            pass
    if f("emissive"):
        em_tex = b.texture(b.image(_pattern(size // 2, 5), name="emissive"))
        main["emissiveTexture"] = {"index": em_tex}
        main["emissiveFactor"] = [1.0, 0.5, 0.25]
        main["extensions"] = {"KHR_materials_emissive_strength": {"emissiveStrength": 2.5}}
        b.use_extension("KHR_materials_emissive_strength")
        if f("texcoord1"):
            main["emissiveTexture"]["texCoord"] = 1
    elif f("texcoord1"):
        main["normalTexture"]["texCoord"] = 1
    if f("texture_transform"):
        pbr["baseColorTexture"]["extensions"] = {
            "KHR_texture_transform": {
                "offset": [0.25, -0.5],
                "rotation": 0.3,
                "scale": [2.0, 1.5],
                "texCoord": 1 if f("texcoord1") else 0,
            }
        }
        b.use_extension("KHR_texture_transform")
    if f("extras"):
        main["extras"] = {"author": "pbrsr"}
    if f("khr_materials"):
        main.setdefault("extensions", {}).update(_khr_material_extensions(b, size))
    main_mat = b.add("materials", main)

    second_mat = None
    if f("shared_image") or f("alpha_mask") or f("alpha_blend") or (f("occlusion") and f("orm")):
        sec: dict = {"name": "second", "pbrMetallicRoughness": {}, "doubleSided": True}
        if f("shared_image"):
            sec["pbrMetallicRoughness"]["baseColorTexture"] = {"index": base_tex}
        else:
            own = _pattern(size // 2, 6, 4)
            own[..., 3] = np.linspace(0.0, 1.0, own.shape[1])[None, :]
            sec["pbrMetallicRoughness"]["baseColorTexture"] = {
                "index": b.texture(b.image(own, name="second_rgba"))
            }
        if f("alpha_mask"):
            sec["alphaMode"] = "MASK"
            sec["alphaCutoff"] = 0.4
        elif f("alpha_blend"):
            sec["alphaMode"] = "BLEND"
        if f("occlusion") and f("orm"):
            sec["occlusionTexture"] = {"index": occ_tex}
        second_mat = b.add("materials", sec)
        if f("alpha_blend") and f("alpha_mask"):
            third = {
                "name": "third",
                "alphaMode": "BLEND",
                "pbrMetallicRoughness": {
                    "baseColorTexture": {
                        "index": sec["pbrMetallicRoughness"]["baseColorTexture"]["index"]
                    }
                },
            }
            b.add("materials", third)

    # geometry
    pos, nrm, uv, tri = uv_sphere(10, 20)
    uvs = {0: uv}
    if f("texcoord1"):
        uvs[1] = np.stack([uv[:, 1], uv[:, 0]], axis=1)
    tng = generate_tangents(pos, nrm, uv, tri) if f("tangents") and not f("no_normals") else None
    sphere_prim = b.primitive(
        pos, tri, nrm=None if f("no_normals") else nrm, uvs=uvs, tng=tng, material=main_mat
    )
    mesh0 = b.add("meshes", {"name": "sphere", "primitives": [sphere_prim]})
    if f("strip"):
        qpos, _, quv, _ = grid_quad(1, 0.5)
        strip_idx = np.array([0, 2, 1, 3], dtype=np.uint16)
        prim = {
            "attributes": {
                "POSITION": b.accessor(qpos.astype(np.float32), minmax=True),
                "TEXCOORD_0": b.accessor(quv.astype(np.float32)),
                **({"TEXCOORD_1": b.accessor(quv.astype(np.float32))} if f("texcoord1") else {}),
            },
            "indices": b.accessor(strip_idx, target=34963),
            "mode": 5,
            "material": main_mat,
        }
        b.doc["meshes"][mesh0]["primitives"].append(prim)

    nodes = b._list("nodes")
    root: dict[str, Any] = {"name": "root", "children": []}
    nodes.append(root)
    sphere_node = b.add("nodes", {"name": "sphere", "mesh": mesh0})
    if f("hierarchy"):
        root["translation"] = [0.5, 0.0, -0.25]
        root["rotation"] = [0.0, 0.3826834, 0.0, 0.9238795]
        root["scale"] = [1.0, 1.5, 1.0]
        mid = b.add(
            "nodes",
            {"name": "mid", "matrix": [0.5, 0, 0, 0, 0, 0.5, 0, 0, 0, 0, 0.5, 0, 1.0, 2.0, 3.0, 1]},
        )
        root["children"].append(mid)
        nodes[mid]["children"] = [sphere_node]
    else:
        root["children"].append(sphere_node)
    if f("extras"):
        nodes[sphere_node]["extras"] = {"tag": [1, 2, 3]}
    if f("extensions"):
        nodes[sphere_node]["extensions"] = {"EXT_pbrsr_unknown_test": {"keep": True, "v": 1.5}}
        b.use_extension("EXT_pbrsr_unknown_test")

    if second_mat is not None or f("skin"):
        qpos, qnrm, quv, qtri = grid_quad(2, 0.5)
        extra = {}
        if f("skin"):
            joints = np.zeros((qpos.shape[0], 4), dtype=np.uint8)
            joints[:, 1] = 1
            wgt = np.zeros((qpos.shape[0], 4), dtype=np.float32)
            wgt[:, 0] = np.where(qpos[:, 0] < 0, 1.0, 0.25)
            wgt[:, 1] = 1.0 - wgt[:, 0]
            extra = {"JOINTS_0": b.accessor(joints), "WEIGHTS_0": b.accessor(wgt)}
        qprim = b.primitive(
            qpos,
            qtri,
            nrm=qnrm,
            uvs={0: quv},
            material=second_mat if second_mat is not None else main_mat,
            extra_attrs=extra,
        )
        if f("texcoord1") and second_mat is None:
            qprim["attributes"]["TEXCOORD_1"] = b.accessor(quv.astype(np.float32))
        mesh1 = b.add("meshes", {"name": "quad", "primitives": [qprim]})
        qnode = {"name": "quad", "mesh": mesh1}
        if f("skin"):
            j0 = b.add("nodes", {"name": "joint0", "translation": [0.0, 0.0, 0.0]})
            j1 = b.add("nodes", {"name": "joint1", "translation": [0.0, 0.5, 0.0]})
            nodes[j0]["children"] = [j1]
            ibm = np.stack([np.eye(4), np.eye(4)]).astype(np.float32)
            ibm[1, 3, 1] = -0.5  # column-major: element [col 3][row 1]
            ibm_acc = b.accessor(ibm.reshape(2, 16), target=None)
            skin = b.add(
                "skins", {"joints": [j0, j1], "inverseBindMatrices": ibm_acc, "skeleton": j0}
            )
            qnode["skin"] = skin
            qn = b.add("nodes", qnode)
            b.doc["scenes"] = [{"nodes": [0, qn, j0]}]
        else:
            qnode["translation"] = [2.5, 0.0, 0.0]
            qn = b.add("nodes", qnode)
            root["children"].append(qn)
            b.doc["scenes"] = [{"nodes": [0]}]
    else:
        b.doc["scenes"] = [{"nodes": [0]}]
    if f("camera"):
        cam = b.add(
            "cameras",
            {
                "type": "perspective",
                "perspective": {"yfov": 0.7, "znear": 0.05, "zfar": 100.0, "aspectRatio": 1.5},
                "name": "cam",
            },
        )
        cn = b.add("nodes", {"name": "camera", "camera": cam, "translation": [0.0, 0.5, 6.0]})
        b.doc["scenes"][0]["nodes"].append(cn)
    if f("animation"):
        times = np.array([0.0, 0.5, 1.0], dtype=np.float32)
        rots = np.array(
            [[0, 0, 0, 1], [0, 0.7071068, 0, 0.7071068], [0, 1, 0, 0]], dtype=np.float32
        )
        t_acc = b.accessor(times, target=None, minmax=True)
        r_acc = b.accessor(rots, target=None)
        b.add(
            "animations",
            {
                "name": "spin",
                "samplers": [{"input": t_acc, "output": r_acc, "interpolation": "LINEAR"}],
                "channels": [{"sampler": 0, "target": {"node": sphere_node, "path": "rotation"}}],
            },
        )
    b.doc["scene"] = 0
    return b.write(path, kind=kind, data_uris=f("data_uri"))


__all__ = [
    "TEST_FEATURES",
    "DEFAULT_TEST_FEATURES",
    "make_demo_asset",
    "make_test_asset",
    "make_quad_asset",
    "brick_maps",
    "uv_sphere",
    "grid_quad",
    "rounded_box",
    "ARRAY_BUFFER",
]
