"""Variants of an asset with its geometry compressed, for the benchmarks and tests.

:func:`draco_variant` and :func:`meshopt_variant` read a plain ``.glb``/``.gltf`` and write a
``.glb`` with every image embedded and each triangle-list primitive's geometry compressed
(``KHR_draco_mesh_compression`` through DracoPy, ``EXT_meshopt_compression`` through the
``meshopt`` package), the extension required. Everything else of the document is kept;
bufferViews nothing uses any more are dropped. A primitive the codec cannot take as it is
(strips, skinning or morph attributes, accessors shared with another primitive) stays
uncompressed.
"""

from __future__ import annotations

import copy
import json
import mimetypes
import struct
from collections.abc import Callable
from pathlib import Path, PurePosixPath

import numpy as np

from pbrsr_core.asset import load_asset
from pbrsr_core.asset.gltf_build import ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER
from pbrsr_core.asset.gltf_read import (
    CHUNK_BIN,
    CHUNK_JSON,
    buffer_view_bytes,
    read_accessor,
    read_accessor_raw,
)
from pbrsr_core.asset.gltf_write import _walk_refs, atomic_write
from pbrsr_core.asset.mesh_codecs import DRACO, MESHOPT
from pbrsr_core.asset.model import Asset
from pbrsr_core.asset.uris import is_data_uri, relative_path

DRACO_BITS = {"POSITION": 14, "NORMAL": 10, "TEXCOORD": 12}
"""Draco quantisation bits per attribute kind (glTF-Transform's defaults); TANGENT and the
texture coordinate sets after the first are stored as lossless float generic attributes."""

_SEMANTICS = ("POSITION", "NORMAL", "TANGENT")


class _Variant:
    """The source document being rewritten: every bufferView's bytes held apart from the
    buffers, so views can be added, compressed and dropped before one BIN is laid out."""

    def __init__(self, asset: Asset):
        if asset.geometry is not None:
            raise ValueError(f"'{asset.source.name}' already has compressed geometry")
        self.asset = asset
        self.doc = copy.deepcopy(asset.document)
        views = self.doc.get("bufferViews", [])
        self.payload: dict[int, bytes] = {
            j: bytes(buffer_view_bytes(asset.document, asset.buffers, j, f"bufferView {j}"))
            for j in range(len(views))
        }
        self.compressed: dict[int, bytes] = {}  # bufferView -> its meshopt data
        for i, img in enumerate(self.doc.get("images", [])):
            uri = img.get("uri")
            if isinstance(uri, str) and not is_data_uri(uri):
                rel = str(relative_path(uri, f"image {i}"))
                mime = img.get("mimeType") or mimetypes.guess_type(PurePosixPath(rel).name)[0]
                img.pop("uri")
                img["bufferView"] = self.view(asset.resources[rel])
                img["mimeType"] = mime or "application/octet-stream"

    def view(self, data: bytes, **fields) -> int:
        views = self.doc.setdefault("bufferViews", [])
        views.append({"buffer": 0, "byteLength": len(data), **fields})
        self.payload[len(views) - 1] = data
        return len(views) - 1

    def read(self, index: int) -> tuple[np.ndarray, dict]:
        """Accessor ``index`` of the source in its own component type, and its JSON."""
        return read_accessor_raw(self.asset.document, self.asset.buffers, index)

    def values(self, index: int) -> np.ndarray:
        """Accessor ``index`` of the source as float64 (normalized integers scaled)."""
        return read_accessor(self.asset.document, self.asset.buffers, index)

    def primitives(self) -> list[dict]:
        """Each triangle list a codec can take: POSITION, NORMAL, TANGENT and TEXCOORD_n
        only, no morph targets, accessors used by no other primitive."""
        uses: dict[int, int] = {}
        prims = [p for mesh in self.doc.get("meshes", []) for p in mesh.get("primitives", [])]
        for prim in prims:
            refs = list(prim.get("attributes", {}).values()) + [prim.get("indices")]
            refs += [a for t in prim.get("targets", []) for a in t.values()]
            for a in refs:
                if isinstance(a, int):
                    uses[a] = uses.get(a, 0) + 1
        out = []
        for prim in prims:
            attrs = prim.get("attributes", {})
            if (
                prim.get("mode", 4) == 4
                and "indices" in prim
                and "POSITION" in attrs
                and not prim.get("targets")
                and all(s in _SEMANTICS or s.startswith("TEXCOORD_") for s in attrs)
                and all(uses[a] == 1 for a in [*attrs.values(), prim["indices"]])
            ):
                out.append(prim)
        return out

    def require(self, *names: str) -> None:
        for key in ("extensionsUsed", "extensionsRequired"):
            have = self.doc.setdefault(key, [])
            have.extend(n for n in names if n not in have)

    def write(self, dst: Path) -> Path:
        """Drop unused bufferViews, lay out the BIN (and the meshopt fallback buffer) and
        write ``dst`` as a GLB."""
        doc, views = self.doc, self.doc.get("bufferViews", [])
        used: set[int] = set()
        _walk_refs(doc, "bufferView", lambda d: used.add(d["bufferView"]))
        keep = [j for j in range(len(views)) if j in used]
        new_index = {j: k for k, j in enumerate(keep)}
        _walk_refs(doc, "bufferView", lambda d: d.update(bufferView=new_index[d["bufferView"]]))
        binary, fallback = bytearray(), 0
        out_views = []
        for j in keep:
            bv = views[j]
            data = self.payload[j]
            if j in self.compressed:
                bv["buffer"], bv["byteOffset"] = 1, fallback
                fallback += len(data) + (-len(data) % 4)
                ext = bv["extensions"][MESHOPT]
                binary += b"\x00" * (-len(binary) % 4)
                ext.update(buffer=0, byteOffset=len(binary), byteLength=len(self.compressed[j]))
                binary += self.compressed[j]
            else:
                binary += b"\x00" * (-len(binary) % 4)
                bv["buffer"], bv["byteOffset"] = 0, len(binary)
                binary += data
            out_views.append(bv)
        doc["bufferViews"] = out_views
        doc["buffers"] = [{"byteLength": len(binary)}]
        if fallback:
            doc["buffers"].append(
                {"byteLength": fallback, "extensions": {MESHOPT: {"fallback": True}}}
            )
        js = json.dumps(doc, separators=(",", ":")).encode()
        js += b" " * (-len(js) % 4)
        binary += b"\x00" * (-len(binary) % 4)
        body = struct.pack("<II", len(js), CHUNK_JSON) + js
        body += struct.pack("<II", len(binary), CHUNK_BIN) + bytes(binary)
        dst = Path(dst)
        return atomic_write(dst, struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)


def _plain_float(acc: dict, count: int) -> None:
    """Turn ``acc`` into a float accessor of ``count`` elements with no data of its own."""
    for k in ("bufferView", "byteOffset", "normalized", "sparse", "min", "max"):
        acc.pop(k, None)
    acc.update(componentType=5126, count=count)


# ----------------------------------------------------------------------------- Draco
def draco_variant(src: Path, dst: Path, *, compression_level: int = 7) -> Path:
    """Write ``dst`` (a ``.glb``): ``src`` with each triangle list Draco-compressed (POSITION,
    NORMAL, TEXCOORD_n, TANGENT; quantisation :data:`DRACO_BITS`). Returns ``dst``."""
    import DracoPy

    var = _Variant(load_asset(Path(src)))
    accessors = var.doc["accessors"]
    for prim in var.primitives():
        attrs = prim["attributes"]
        data = {s: var.values(a) for s, a in attrs.items()}
        uv0 = data.get("TEXCOORD_0")
        # Draco's own attribute kinds take one set each; the rest go as generic attributes
        generic_ids = {
            s: 100 + k
            for k, s in enumerate(sorted(set(data) - {"POSITION", "NORMAL", "TEXCOORD_0"}))
        }
        generic = {uid: data[s].astype(np.float32) for s, uid in generic_ids.items()}
        faces = var.read(prim["indices"])[0].reshape(-1, 3).astype(np.uint32)
        blob = DracoPy.encode(
            data["POSITION"],
            faces,
            quantization_bits=DRACO_BITS["POSITION"],
            compression_level=compression_level,
            normals=data.get("NORMAL"),
            normal_quantization_bits=DRACO_BITS["NORMAL"],
            tex_coord=uv0,
            tex_coord_quantization_bits=DRACO_BITS["TEXCOORD"],
            generic_attributes=generic or None,
        )
        mesh = DracoPy.decode(blob)  # the ids and counts the decoder will see
        by_type = {a["attribute_type"]: a for a in mesh.attributes}
        ids = dict(generic_ids)
        ids["POSITION"] = by_type[DracoPy.AttributeType.POSITION]["unique_id"]
        if "NORMAL" in data:
            ids["NORMAL"] = by_type[DracoPy.AttributeType.NORMAL]["unique_id"]
        if uv0 is not None:
            ids["TEXCOORD_0"] = by_type[DracoPy.AttributeType.TEX_COORD]["unique_id"]
        nverts = int(np.asarray(mesh.points).shape[0])
        for a in attrs.values():
            _plain_float(accessors[a], nverts)
        positions = np.asarray(mesh.points, dtype=np.float32)
        accessors[attrs["POSITION"]]["min"] = [float(x) for x in positions.min(axis=0)]
        accessors[attrs["POSITION"]]["max"] = [float(x) for x in positions.max(axis=0)]
        idx = accessors[prim["indices"]]
        for k in ("bufferView", "byteOffset", "sparse", "min", "max"):
            idx.pop(k, None)
        idx.update(
            componentType=5123 if nverts <= 65535 else 5125,
            count=int(np.asarray(mesh.faces).size),
        )
        prim.setdefault("extensions", {})[DRACO] = {
            "bufferView": var.view(bytes(blob)),
            "attributes": {s: int(ids[s]) for s in attrs},
        }
        var.require(DRACO)
    return var.write(dst)


# ----------------------------------------------------------------------------- meshopt
def meshopt_variant(src: Path, dst: Path, *, filters: bool = True) -> Path:
    """Write ``dst`` (a ``.glb``): ``src`` with each triangle list's attributes and indices
    meshopt-compressed into bufferViews of their own, with a fallback buffer without a
    ``uri``. ``filters``: NORMAL and TANGENT as 8-bit octahedral (``KHR_mesh_quantization``),
    POSITION and TEXCOORD_n through the EXPONENTIAL filter, and animation rotations as 16-bit
    QUATERNION; otherwise every attribute as it is with no filter (bit-exact geometry)."""
    import meshopt

    var = _Variant(load_asset(Path(src)))
    accessors = var.doc["accessors"]

    def compress(
        acc_index: int, rows: np.ndarray, mode: str, filt: str, target: int | None, **acc_fields
    ) -> None:
        rows = np.ascontiguousarray(rows)
        count = rows.shape[0]
        stride = rows.nbytes // max(count, 1)
        blob = meshopt.encode_gltf_buffer(
            rows.reshape(count, -1) if mode == "ATTRIBUTES" else rows, mode
        )
        ext = {"byteStride": stride, "count": count, "mode": mode}
        if filt != "NONE":
            ext["filter"] = filt
        fields: dict = {"extensions": {MESHOPT: ext}}
        if target == ARRAY_BUFFER:
            fields["byteStride"] = stride
        if target is not None:
            fields["target"] = target
        j = var.view(rows.tobytes(), **fields)
        var.compressed[j] = bytes(blob)
        acc = accessors[acc_index]
        drop = ("byteOffset", "sparse", "min", "max") if acc_fields else ("byteOffset", "sparse")
        for k in drop:  # bounds in another component type would need converting: dropped
            acc.pop(k, None)
        acc.update(bufferView=j, **acc_fields)

    quantised = False
    for prim in var.primitives():
        for s, a in prim["attributes"].items():
            raw, acc = var.read(a)
            if filters and s in ("NORMAL", "TANGENT"):
                vec = np.zeros((raw.shape[0], 4), np.float32)
                vec[:, : raw.shape[1]] = var.values(a)
                rows = meshopt.encode_filter_oct(vec, 4, 8)
                compress(
                    a,
                    rows,
                    "ATTRIBUTES",
                    "OCTAHEDRAL",
                    ARRAY_BUFFER,
                    componentType=5120,
                    normalized=True,
                )
                quantised = True
            elif filters and raw.dtype == np.float32:
                rows = meshopt.encode_filter_exp(raw, 16, "SharedVector")
                compress(a, rows, "ATTRIBUTES", "EXPONENTIAL", ARRAY_BUFFER)
                if "min" in acc:  # the bounds of the values the filter gives back
                    back = meshopt.decode_gltf_buffer(
                        meshopt.encode_gltf_buffer(rows, "ATTRIBUTES"),
                        rows.shape[0],
                        rows.shape[1],
                        "ATTRIBUTES",
                        "EXPONENTIAL",
                    ).view(np.float32)
                    accessors[a]["min"] = [float(x) for x in back.min(axis=0)]
                    accessors[a]["max"] = [float(x) for x in back.max(axis=0)]
            else:
                elem = raw.dtype.itemsize * raw.shape[1]
                padded = np.zeros((raw.shape[0], elem + (-elem % 4)), np.uint8)
                padded[:, :elem] = raw.view(np.uint8).reshape(raw.shape[0], elem)
                compress(a, padded, "ATTRIBUTES", "NONE", ARRAY_BUFFER)
        idx = var.read(prim["indices"])[0].reshape(-1)
        if idx.dtype == np.uint8:  # the codec stores 16- or 32-bit indices
            compress(
                prim["indices"],
                idx.astype(np.uint16),
                "TRIANGLES",
                "NONE",
                ELEMENT_ARRAY_BUFFER,
                componentType=5123,
            )
        else:
            compress(prim["indices"], idx, "TRIANGLES", "NONE", ELEMENT_ARRAY_BUFFER)
        var.require(MESHOPT)
    if filters:
        for anim in var.doc.get("animations", []):
            for ch in anim.get("channels", []):
                sampler = anim["samplers"][ch["sampler"]]
                out, acc = var.read(sampler["output"])
                if ch["target"].get("path") == "rotation" and out.dtype == np.float32:
                    rows = meshopt.encode_filter_quat(out, 8, 16)
                    compress(
                        sampler["output"],
                        rows,
                        "ATTRIBUTES",
                        "QUATERNION",
                        None,
                        componentType=5122,
                        normalized=True,
                    )
                    var.require(MESHOPT)
    if quantised:
        var.require("KHR_mesh_quantization")
    return var.write(dst)


def draco_ktx2_variant(src: Path, dst: Path) -> Path:
    """Write ``dst`` (a ``.glb``): :func:`draco_variant` of ``src`` with every image as KTX2
    (``KHR_texture_basisu``: colour maps sRGB ETC1S, the others linear UASTC with Zstandard,
    mipmapped; pbrsr's own KTX2 writer), as web pipelines ship assets. Returns ``dst``."""
    from pbrsr_core.asset import save_asset

    draco = draco_variant(src, dst.with_name(f"{dst.stem}-draco.glb"))
    asset = load_asset(draco)
    save_asset(asset, dst, {im.index: im.pixels for im in asset.images}, image_format="ktx2")
    draco.unlink()
    return dst


BENCH_VARIANTS: dict[str, tuple[str, Callable[[Path, Path], Path]]] = {
    "WaterBottle-draco": ("WaterBottle", draco_variant),
    "WaterBottle-draco-ktx2": ("WaterBottle", draco_ktx2_variant),
}
"""Variants ``pbrsr bench upscale`` adds: {name: (shared asset it is made from, maker)}, so
the speed table shows what decoding compressed geometry and textures, and writing them back
the same way, cost."""
