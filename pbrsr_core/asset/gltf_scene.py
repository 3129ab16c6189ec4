"""The default scene of a glTF document as one world-space :class:`Mesh`: node transforms,
triangle lists, tangents generated where missing, UVs unwrapped where asked."""

from __future__ import annotations

import math

import numpy as np
import torch

from ..errors import InvalidAsset, LimitExceeded
from ..limits import Limits
from .gltf_materials import SLOT_KEYS, texture_ref
from .gltf_read import (
    get_index,
    num_list,
    read_accessor,
)
from .mesh_codecs import DRACO
from .model import (
    DecodedGeometry,
    Mesh,
    TextureRef,
    UnwrappedPrimitive,
)
from .tangents import generate_tangents, safe_normalize
from .unwrap import unwrap_triangles


def node_matrix(node: dict, what: str = "node") -> np.ndarray:
    """The node's local 4x4 (column-vector convention) from ``matrix`` or TRS."""
    if "matrix" in node:
        return np.array(num_list(node["matrix"], 16, f"{what}.matrix")).reshape(4, 4).T
    t = num_list(node.get("translation", [0.0, 0.0, 0.0]), 3, f"{what}.translation")
    x, y, z, w = num_list(node.get("rotation", [0.0, 0.0, 0.0, 1.0]), 4, f"{what}.rotation")
    s = num_list(node.get("scale", [1.0, 1.0, 1.0]), 3, f"{what}.scale")
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
def scene_roots(doc: dict) -> list[int]:
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


class SceneBuilder:
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
        for _role, (parent, key) in SLOT_KEYS.items():
            holder = pbr if parent else m
            if key in holder:
                ref = texture_ref(self.doc, holder[key], f"material {mat_index}.{key}")
                if ref is not None:
                    refs.append(ref)
        return refs

    def _needed_texcoords(self, mat_index: int) -> set[int]:
        return {r.texcoord for r in self._mat_refs(mat_index)}

    def _normal_texcoord(self, mat_index: int) -> int:
        if mat_index >= 0:
            nt = self.doc["materials"][mat_index].get("normalTexture")
            if isinstance(nt, dict):
                ref = texture_ref(self.doc, nt, f"material {mat_index}.normalTexture")
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
