"""Load ``.glb``/``.gltf`` assets into :class:`~pbrsr_core.asset.model.Asset` and save them back
with chosen images replaced, losing nothing else.

Loading keeps the parsed JSON untouched in ``Asset.document`` and derives the typed views:
the merged world-space :class:`Mesh` of the default scene, every :class:`Material` with
resolved :class:`TextureRef`s, and every image decoded. Saving edits the JSON (only the entries
of replaced images and their bufferViews change) and writes atomically inside the output's
folder; see :mod:`pbrsr_core.asset.gltf_write`.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from ..errors import InvalidAsset, LimitExceeded, UnprocessableAsset, UnsupportedAsset
from ..limits import Limits
from .gltf_read import (
    GLB_MAGIC,
    buffer_view_bytes,
    check_buffer_views,
    get_index,
    load_buffers,
    parse_glb,
    parse_json,
    read_accessor,
)
from .gltf_textures import texture_sources
from .gltf_write import encode_images, save_asset
from .images import read_texture
from .jpeg import quant_tables
from .mesh_codecs import DRACO, decode_geometry, meshopt_placeholders, placeholder_extent
from .model import (
    EXTENSION_ROLES,
    REPEAT,
    SRGB_ROLES,
    Asset,
    DecodedGeometry,
    ImageData,
    Material,
    Mesh,
    TextureRef,
    UnwrappedPrimitive,
)
from .tangents import generate_tangents, safe_normalize
from .texture_codecs import Ktx2Encoding, transfer
from .unwrap import unwrap_triangles
from .uris import decode_data_uri, is_data_uri, read_resource, relative_path, safe_stem

__all__ = ["encode_images", "load_asset", "save_asset", "texture_transform_matrix", "node_matrix"]

_SLOT_KEYS = {
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


def _num_list(v, n: int, what: str) -> list[float]:
    if (
        not isinstance(v, list)
        or len(v) != n
        or not all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v
        )
    ):
        raise InvalidAsset(f"{what} must be {n} finite numbers")
    return [float(x) for x in v]


def node_matrix(node: dict, what: str = "node") -> np.ndarray:
    """The node's local 4x4 (column-vector convention) from ``matrix`` or TRS."""
    if "matrix" in node:
        return np.array(_num_list(node["matrix"], 16, f"{what}.matrix")).reshape(4, 4).T
    t = _num_list(node.get("translation", [0.0, 0.0, 0.0]), 3, f"{what}.translation")
    x, y, z, w = _num_list(node.get("rotation", [0.0, 0.0, 0.0, 1.0]), 4, f"{what}.rotation")
    s = _num_list(node.get("scale", [1.0, 1.0, 1.0]), 3, f"{what}.scale")
    n = math.sqrt(x * x + y * y + z * z + w * w) or 1.0
    x, y, z, w = x / n, y / n, z / n, w / n
    r = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    m = np.eye(4)
    m[:3, :3] = r * np.array(s)[None, :]
    m[:3, 3] = t
    return m


# ----------------------------------------------------------------------------- materials
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


def _texture_ref(doc: dict, info: dict, what: str) -> TextureRef | None:
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


def _material(doc: dict, i: int) -> Material:
    m = doc["materials"][i]
    what = f"material {i}"
    pbr = m.get("pbrMetallicRoughness") or {}
    mat = Material(index=i, name=str(m.get("name", "")))
    if "baseColorFactor" in pbr:
        r, g, b, a = _num_list(pbr["baseColorFactor"], 4, what)
        mat.base_color_factor = (r, g, b, a)
    mat.metallic_factor = float(pbr.get("metallicFactor", 1.0))
    mat.roughness_factor = float(pbr.get("roughnessFactor", 1.0))
    if "emissiveFactor" in m:
        r, g, b = _num_list(m["emissiveFactor"], 3, what)
        mat.emissive_factor = (r, g, b)
    for role, (parent, key) in _SLOT_KEYS.items():
        holder = pbr if parent else m
        if key in holder:
            setattr(mat, role, _texture_ref(doc, holder[key], f"{what}.{key}"))
    if "normalTexture" in m:
        mat.normal_scale = float(m["normalTexture"].get("scale", 1.0))
    if "occlusionTexture" in m:
        mat.occlusion_strength = float(m["occlusionTexture"].get("strength", 1.0))
    exts = m.get("extensions") or {}
    for role, (ext, key, _) in EXTENSION_ROLES.items():
        holder = exts.get(ext)
        if isinstance(holder, dict) and isinstance(holder.get(key), dict):
            ref = _texture_ref(doc, holder[key], f"{what}.{ext}.{key}")
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
def _image_label(img: dict, i: int, default_ext: str = "") -> str:
    uri = img.get("uri")
    if isinstance(uri, str) and not is_data_uri(uri):
        return str(relative_path(uri, f"image {i}"))
    name = img.get("name")
    return f"{safe_stem(name if isinstance(name, str) else '', f'image{i}')}{default_ext}"


def _load_images(
    doc: dict,
    folder: Path,
    buffers: list[bytes],
    limits: Limits,
    resources: dict[str, bytes],
    roles: dict[int, set[str]],
) -> list[ImageData]:
    """Every image decoded, with the material roles that use it (``roles``)."""
    out = []
    for i, img in enumerate(doc.get("images", [])):
        what = f"image {i}"
        label = _image_label(img, i)
        uri = img.get("uri")
        if "bufferView" in img:
            data = buffer_view_bytes(doc, buffers, img["bufferView"], what)
        elif isinstance(uri, str):
            if is_data_uri(uri):
                data, _ = decode_data_uri(uri, limits.max_data_uri_bytes, what)
            else:
                data = read_resource(folder, uri, limits.max_file_bytes, what)
                resources[label] = data
        else:
            raise InvalidAsset(f"{what} has neither a uri nor a bufferView")
        used_as = roles.get(i, set())
        try:
            pixels, depth, mime, encoding = read_texture(data, label, limits)
        except (UnsupportedAsset, InvalidAsset):
            if used_as:
                raise
            # an image no material slot uses and pbrsr cannot decode (e.g. the DDS image of
            # MSFT_texture_dds): kept as an empty placeholder, saved byte for byte
            declared = img.get("mimeType")
            pixels = np.zeros((0, 0, 4), dtype=np.float32)
            depth, mime = 8, declared if isinstance(declared, str) else "application/octet-stream"
            encoding = None
        if isinstance(encoding, Ktx2Encoding):
            pixels = transfer(pixels, encoding.srgb, bool(used_as & SRGB_ROLES))
        jpeg = quant_tables(data) if mime == "image/jpeg" else None
        out.append(
            ImageData(
                index=i,
                name=label,
                pixels=pixels,
                bit_depth=depth,
                mime=mime,
                roles=set(used_as),
                jpeg=jpeg,
                encoding=encoding,
            )
        )
    return out


# ----------------------------------------------------------------------------- geometry
def _scene_roots(doc: dict) -> list[int]:
    nodes = doc.get("nodes", [])
    scenes = doc.get("scenes", [])
    if scenes:
        si = doc.get("scene", 0)
        if not isinstance(si, int) or not 0 <= si < len(scenes):
            raise InvalidAsset(f"the default scene {si!r} does not exist")
        roots = scenes[si].get("nodes", [])
    else:
        children = {c for n in nodes for c in (n.get("children") or []) if isinstance(c, int)}
        roots = [i for i in range(len(nodes)) if i not in children]
    for r in roots:
        if not isinstance(r, int) or not 0 <= r < len(nodes):
            raise InvalidAsset(f"the scene refers to node {r!r}, which does not exist")
    return list(roots)


def _triangles(mode: int, idx: np.ndarray) -> np.ndarray:
    """Triangle list (T, 3) from an index list for modes 4 (list), 5 (strip), 6 (fan)."""
    if mode == 4:
        n = idx.shape[0] - idx.shape[0] % 3
        return idx[:n].reshape(-1, 3)
    if idx.shape[0] < 3:
        return np.zeros((0, 3), dtype=np.int64)
    k = np.arange(idx.shape[0] - 2)
    if mode == 5:
        even = (k % 2) == 0
        a = idx[k]
        b = np.where(even, idx[k + 1], idx[k + 2])
        c = np.where(even, idx[k + 2], idx[k + 1])
        return np.stack([a, b, c], axis=1)
    return np.stack([np.full_like(k, idx[0]), idx[k + 1], idx[k + 2]], axis=1)


class _Builder:
    def __init__(
        self,
        doc: dict,
        buffers: list[bytes],
        limits: Limits,
        unwrap: bool = True,
        geometry: DecodedGeometry | None = None,
    ):
        self.doc, self.limits = doc, limits
        self.buffers = geometry.buffers if geometry else buffers
        self.decoded = geometry.accessors if geometry else None
        self.unwrap = unwrap
        self.unwrapped: dict[tuple[int, int], UnwrappedPrimitive] = {}
        self.pos: list[np.ndarray] = []
        self.nrm: list[np.ndarray] = []
        self.tng: list[np.ndarray] = []
        self.uv: list[dict[int, np.ndarray]] = []
        self.tri: list[np.ndarray] = []
        self.mat: list[np.ndarray] = []
        self.nv = 0
        self.nt = 0
        self.missing_uv: list[tuple[int, int, int]] = []

    def walk(self, roots: list[int]) -> None:
        nodes = self.doc.get("nodes", [])
        stack: list[tuple[int, np.ndarray, frozenset[int]]] = [
            (r, np.eye(4), frozenset()) for r in reversed(roots)
        ]
        while stack:
            ni, parent, seen = stack.pop()
            if ni in seen:
                raise InvalidAsset(f"node {ni} is its own ancestor (a cycle in the hierarchy)")
            node = nodes[ni]
            world = parent @ node_matrix(node, f"node {ni}")
            if "mesh" in node:
                mi = get_index(node, "mesh", len(self.doc.get("meshes", [])), f"node {ni}")
                self.add_mesh(mi, world)
            children = node.get("children") or []
            for c in reversed(children):
                if not isinstance(c, int) or not 0 <= c < len(nodes):
                    raise InvalidAsset(f"node {ni} has a child {c!r} that does not exist")
                stack.append((c, world, seen | {ni}))

    def add_mesh(self, mi: int, world: np.ndarray) -> None:
        mesh = self.doc["meshes"][mi]
        mname = mesh.get("name") or f"mesh {mi}"
        for pi, prim in enumerate(mesh.get("primitives") or []):
            self.add_primitive(mi, pi, prim, f"'{mname}' (mesh {mi}, primitive {pi})", world)

    def add_primitive(self, mi: int, pi: int, prim: dict, what: str, world: np.ndarray) -> None:
        doc, bufs = self.doc, self.buffers

        def read(index, label: str) -> np.ndarray:
            return read_accessor(doc, bufs, index, label, self.decoded)

        mode = prim.get("mode", 4)
        if mode not in (4, 5, 6):
            return  # points and lines carry no textured surface
        if DRACO in (prim.get("extensions") or {}):
            mode = 4  # Draco decodes to a triangle list
        attrs = prim.get("attributes") or {}
        if "POSITION" not in attrs:
            return
        pos = read(attrs["POSITION"], f"{what} POSITION")
        if pos.shape[1] != 3:
            raise InvalidAsset(f"{what}: POSITION is not VEC3")
        if not np.isfinite(pos).all():
            raise InvalidAsset(f"the mesh {what} has NaN or infinite vertex positions")
        nv = nv0 = pos.shape[0]
        if "indices" in prim:
            idx = read(prim["indices"], f"{what} indices")[:, 0]
            if idx.dtype.kind == "f":
                raise InvalidAsset(f"{what}: indices must be integers")
            if idx.size and (idx.max() >= nv or idx.min() < 0):
                raise InvalidAsset(
                    f"{what} has vertex index {int(idx.max())} but only {nv} vertices"
                )
        else:
            idx = np.arange(nv, dtype=np.int64)
        tri = _triangles(mode, idx.astype(np.int64))
        if self.nt + tri.shape[0] > self.limits.max_triangles:
            raise LimitExceeded(
                f"the asset has more than {self.limits.max_triangles} triangles (the limit)"
            )
        mat_index = prim.get("material", -1)
        if mat_index != -1:
            mat_index = get_index(prim, "material", len(doc.get("materials", [])), what)

        # TEXCOORD sets the material needs but the primitive lacks: unwrap (xatlas) or refuse
        present = {int(k[9:]) for k in attrs if k.startswith("TEXCOORD_") and k[9:].isdigit()}
        needed = self._needed_texcoords(mat_index) if mat_index >= 0 else set()
        vmap: np.ndarray | None = None
        generated: dict[int, np.ndarray] = {}
        if needed - present:
            if not self.unwrap:
                for n_needed in sorted(needed - present):
                    self.missing_uv.append((mi, pi, n_needed))
            else:
                un = self.unwrapped.get((mi, pi))
                if un is None:
                    base = unwrap_triangles(pos, tri, what=f"the mesh {what}")
                    # every missing set up to the highest needed one (sets must be contiguous)
                    sets = [n for n in range(max(needed) + 1) if n not in present]
                    un = UnwrappedPrimitive(
                        vmapping=base.vmapping,
                        indices=base.indices,
                        uvs={n: base.uvs[0] for n in sets},
                    )
                    self.unwrapped[(mi, pi)] = un
                vmap, tri, generated = un.vmapping, un.indices.copy(), un.uvs
                pos = pos[vmap]
                nv = pos.shape[0]

        def gather(a: np.ndarray) -> np.ndarray:
            return a if vmap is None else a[vmap]

        m3 = world[:3, :3]
        det = float(np.linalg.det(m3))
        wpos = pos @ m3.T + world[:3, 3]
        nmat = np.linalg.inv(m3).T if abs(det) > 1e-30 else m3
        if det < 0:
            tri = tri[:, [0, 2, 1]]

        uvs: dict[int, np.ndarray] = {}
        for key, acc in attrs.items():
            if key.startswith("TEXCOORD_") and key[9:].isdigit():
                uv = read(acc, f"{what} {key}")
                if uv.shape != (nv0, 2):
                    raise InvalidAsset(f"{what}: {key} must be VEC2 with one value per vertex")
                if not np.isfinite(uv).all():
                    raise InvalidAsset(f"{what}: {key} has NaN or infinite values")
                uvs[int(key[9:])] = gather(uv)
        for k, uv in generated.items():
            uvs[k] = uv.astype(np.float64)

        if "NORMAL" in attrs:
            n = read(attrs["NORMAL"], f"{what} NORMAL")
            if n.shape != (nv0, 3):
                raise InvalidAsset(f"{what}: NORMAL must be VEC3 with one value per vertex")
            n = np.nan_to_num(n, nan=0.0, posinf=0.0, neginf=0.0)
            wn = safe_normalize(gather(n) @ nmat.T)
        else:
            # glTF: flat normals when none are given -> one vertex per triangle corner
            flat = tri.reshape(-1)
            wpos = wpos[flat]
            uvs = {k: v[flat] for k, v in uvs.items()}
            nv = wpos.shape[0]
            tri = np.arange(nv, dtype=np.int64).reshape(-1, 3)
            p = wpos.reshape(-1, 3, 3)
            fn = safe_normalize(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]))
            wn = np.repeat(fn, 3, axis=0)
            attrs = {k: v for k, v in attrs.items() if k != "TANGENT"}

        if "TANGENT" in attrs:
            t = read(attrs["TANGENT"], f"{what} TANGENT")
            if t.shape != (nv0, 4):
                raise InvalidAsset(f"{what}: TANGENT must be VEC4 with one value per vertex")
            t = gather(np.nan_to_num(t, nan=0.0, posinf=0.0, neginf=0.0))
            txyz = t[:, :3] @ m3.T
            txyz = txyz - wn * np.sum(wn * txyz, axis=1, keepdims=True)
            ln = np.linalg.norm(txyz, axis=1, keepdims=True)
            bad = ln[:, 0] < 1e-12
            txyz = txyz / np.where(bad[:, None], 1.0, ln)
            w = np.where(t[:, 3] < 0, -1.0, 1.0) * (-1.0 if det < 0 else 1.0)
            tng = np.concatenate([txyz, w[:, None]], axis=1)
            if bad.any():
                gen = generate_tangents(wpos, wn, uvs.get(self._normal_texcoord(mat_index)), tri)
                tng[bad] = gen[bad]
        else:
            tng = generate_tangents(wpos, wn, uvs.get(self._normal_texcoord(mat_index)), tri)

        self.pos.append(wpos)
        self.nrm.append(wn)
        self.tng.append(tng)
        self.uv.append(uvs)
        self.tri.append(tri + self.nv)
        self.mat.append(np.full(tri.shape[0], mat_index, dtype=np.int64))
        self.nv += nv
        self.nt += tri.shape[0]

    def _mat_refs(self, mat_index: int) -> list[TextureRef]:
        if mat_index < 0:
            return []
        m = self.doc["materials"][mat_index]
        refs = []
        pbr = m.get("pbrMetallicRoughness") or {}
        for _role, (parent, key) in _SLOT_KEYS.items():
            holder = pbr if parent else m
            if key in holder:
                ref = _texture_ref(self.doc, holder[key], f"material {mat_index}.{key}")
                if ref is not None:
                    refs.append(ref)
        return refs

    def _needed_texcoords(self, mat_index: int) -> set[int]:
        return {r.texcoord for r in self._mat_refs(mat_index)}

    def _normal_texcoord(self, mat_index: int) -> int:
        if mat_index >= 0:
            nt = self.doc["materials"][mat_index].get("normalTexture")
            if isinstance(nt, dict):
                ref = _texture_ref(self.doc, nt, f"material {mat_index}.normalTexture")
                if ref is not None:
                    return ref.texcoord
        return 0

    def build(self) -> Mesh:
        if not self.pos:
            empty = torch.zeros((0, 3), dtype=torch.float32)
            return Mesh(
                v_pos=empty,
                v_nrm=empty.clone(),
                v_tng=torch.zeros((0, 4), dtype=torch.float32),
                v_uv={},
                t_pos_idx=torch.zeros((0, 3), dtype=torch.int64),
                t_mat=torch.zeros((0,), dtype=torch.int64),
            )
        sets = sorted({k for d in self.uv for k in d})
        v_uv = {}
        for k in sets:
            parts = [
                d.get(k, np.zeros((p.shape[0], 2))) for d, p in zip(self.uv, self.pos, strict=True)
            ]
            v_uv[k] = torch.from_numpy(np.concatenate(parts).astype(np.float32))

        def cat(xs, dtype=np.float32):
            return torch.from_numpy(np.ascontiguousarray(np.concatenate(xs).astype(dtype)))

        return Mesh(
            v_pos=cat(self.pos),
            v_nrm=cat(self.nrm),
            v_tng=cat(self.tng),
            v_uv=v_uv,
            t_pos_idx=cat(self.tri, np.int64),
            t_mat=cat(self.mat, np.int64),
        )


# ----------------------------------------------------------------------------- entry point
def load_asset(path: Path, limits: Limits = Limits(), *, unwrap_missing_uvs: bool = True) -> Asset:
    """Read a ``.glb`` or ``.gltf`` file (the kind is taken from the bytes, not the name).

    External files are resolved relative to the file's folder and must stay inside it.
    Raises InvalidAsset / UnsupportedAsset / LimitExceeded / UnprocessableAsset with a message
    naming the glTF object at fault.
    """
    path = Path(path)
    if not path.is_file():
        raise InvalidAsset(f"the file '{path.name}' does not exist")
    size = path.stat().st_size
    if size == 0:
        raise InvalidAsset(f"the file '{path.name}' is empty")
    if size > limits.max_file_bytes:
        raise LimitExceeded(
            f"the file '{path.name}' is {size} bytes; the limit is {limits.max_file_bytes}"
        )
    raw = path.read_bytes()
    kind: Literal["glb", "gltf"]
    if raw[:4] == GLB_MAGIC:
        doc, bin_chunk = parse_glb(raw)
        kind = "glb"
    else:
        head = raw[:64].lstrip(b"\xef\xbb\xbf \t\r\n")
        if not head.startswith(b"{"):
            raise UnsupportedAsset(
                f"the file '{path.name}' is neither glTF JSON nor GLB (nor a zip of them)"
            )
        doc, bin_chunk = parse_json(raw), None
        kind = "gltf"
    del raw
    folder = path.parent
    resources: dict[str, bytes] = {}
    placeholders = {
        i: placeholder_extent(doc, i, limits) for i in meshopt_placeholders(doc, kind == "glb")
    }
    buffers = load_buffers(doc, folder, bin_chunk, kind == "glb", limits, resources, placeholders)
    check_buffer_views(doc, buffers)
    geometry = decode_geometry(doc, buffers, set(placeholders), limits)

    materials = [_material(doc, i) for i in range(len(doc.get("materials", [])))]
    roles: dict[int, set[str]] = {}
    for m in materials:
        for role, ref in m.textures().items():
            roles.setdefault(ref.image, set()).add(role)
    builder = _Builder(doc, buffers, limits, unwrap_missing_uvs, geometry)
    builder.walk(_scene_roots(doc))
    mesh = builder.build()
    decoded_buffers = geometry.buffers if geometry else buffers  # meshopt views decoded
    images = _load_images(doc, folder, decoded_buffers, limits, resources, roles)
    asset = Asset(
        document=doc,
        buffers=buffers,
        images=images,
        materials=materials,
        mesh=mesh,
        source=path,
        kind=kind,
        resources=resources,
        generated_uvs=dict(builder.unwrapped),
        geometry=geometry,
    )
    if builder.missing_uv:
        mi, pi, n = builder.missing_uv[0]
        raise UnprocessableAsset(
            f"mesh {mi} primitive {pi} has a textured material that needs TEXCOORD_{n}, "
            "which it lacks: turn on unwrapping to generate UVs (or add UVs in a DCC tool)"
        )
    return asset


def image_by_index(asset: Asset, index: int) -> ImageData:
    """The decoded image with glTF index ``index``."""
    for im in asset.images:
        if im.index == index:
            return im
    raise KeyError(index)
