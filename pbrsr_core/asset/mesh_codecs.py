"""Compressed geometry: ``EXT_meshopt_compression`` bufferViews and ``KHR_draco_mesh_compression``
primitives, decoded for reading (pbrsr never re-encodes geometry: saving keeps the compressed
bytes as they are, see :mod:`pbrsr_core.asset.gltf_write`).

:func:`decode_geometry` runs both when a document has compressed geometry.

* meshopt: :func:`decode_meshopt_views` decodes every compressed bufferView (the ``meshopt``
  package, meshoptimizer's codec) into its parent buffer, so accessors read it like any other
  data. A fallback buffer without a ``uri`` (:func:`meshopt_placeholders`) has no bytes in the
  file: it is made in memory from the decoded views only.
* Draco: :func:`decode_draco` decodes each compressed primitive (``DracoPy``) and returns the
  data of the accessors its extension names (attributes by their Draco unique id, and the
  indices), in each accessor's component type; those accessors have no bufferView.

Both check every field and size before a decoder sees the bytes and turn a decoder's failure
into :class:`InvalidAsset`; the decoded size is bounded by ``Limits.max_unpacked_bytes``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import InvalidAsset, LimitExceeded
from ..limits import Limits
from .gltf_read import COMPONENT_DTYPES, TYPE_SIZES, buffer_view_bytes, get_index
from .model import DecodedGeometry

MESHOPT = "EXT_meshopt_compression"
DRACO = "KHR_draco_mesh_compression"

MESHOPT_MODES = ("ATTRIBUTES", "TRIANGLES", "INDICES")
MESHOPT_FILTERS = ("NONE", "OCTAHEDRAL", "QUATERNION", "EXPONENTIAL")
DRACO_MAGIC = b"DRACO"
_DRACO_HEADER = 11  # "DRACO", major, minor, encoder type, method, flags (u16)
_DRACO_MESH, _DRACO_EDGEBREAKER, _DRACO_METADATA = 1, 1, 0x8000


def _ext(obj: dict, name: str) -> dict | None:
    exts = obj.get("extensions")
    ext = exts.get(name) if isinstance(exts, dict) else None
    return ext if isinstance(ext, dict) else None


def _int(obj: dict, key: str, what: str, default: int | None = None) -> int:
    v = obj.get(key, default)
    if not isinstance(v, int) or isinstance(v, bool) or v < 0:
        raise InvalidAsset(f"{what} has an invalid {key} {v!r:.40}")
    return v


# ----------------------------------------------------------------------------- meshopt
def meshopt_view(bv: dict) -> dict | None:
    """The ``EXT_meshopt_compression`` object of a bufferView, or None."""
    return _ext(bv, MESHOPT)


def meshopt_placeholders(doc: dict, is_glb: bool) -> set[int]:
    """Indices of the buffers without a ``uri`` that only compressed bufferViews use as their
    parent (the extension's fallback buffers; a GLB's buffer 0 is its BIN chunk instead)."""
    buffers = doc.get("buffers", [])
    views = doc.get("bufferViews", [])
    if not any(isinstance(bv, dict) and meshopt_view(bv) is not None for bv in views):
        return set()
    out = set()
    for i, buf in enumerate(buffers):
        if not isinstance(buf, dict) or "uri" in buf or (is_glb and i == 0):
            continue
        users = [bv for bv in views if isinstance(bv, dict) and bv.get("buffer") == i]
        if users and all(meshopt_view(bv) is not None for bv in users):
            out.add(i)
    return out


def placeholder_extent(doc: dict, index: int, limits: Limits) -> int:
    """The bytes a fallback buffer without a ``uri`` needs in memory: the end of the last
    bufferView in it (checked against its ``byteLength`` and the decoded-size limit)."""
    buf = doc["buffers"][index]
    what = f"buffer {index}"
    blen = _int(buf, "byteLength", what)
    end = 0
    for j, bv in enumerate(doc.get("bufferViews", [])):
        if bv.get("buffer") != index:
            continue
        off = _int(bv, "byteOffset", f"bufferView {j}", 0)
        end = max(end, off + _int(bv, "byteLength", f"bufferView {j}"))
    if end > blen:
        raise InvalidAsset(f"a bufferView reaches past the end of {what} ({blen} bytes)")
    if end > limits.max_unpacked_bytes:
        raise LimitExceeded(
            f"the EXT_meshopt_compression data of {what} decodes to {end} bytes; the limit is "
            f"{limits.max_unpacked_bytes}"
        )
    return end


def _check_meshopt(ext: dict, bv: dict, what: str, buffers: list, placeholders: set[int]) -> None:
    b = get_index(ext, "buffer", len(buffers), what)
    if b in placeholders:
        raise InvalidAsset(f"{what} reads its compressed data from a fallback buffer")
    off = _int(ext, "byteOffset", what, 0)
    blen = _int(ext, "byteLength", what)
    if off + blen > len(buffers[b]):
        raise InvalidAsset(f"{what} reaches past the end of buffer {b}")
    stride = _int(ext, "byteStride", what)
    count = _int(ext, "count", what)
    mode, filt = ext.get("mode"), ext.get("filter", "NONE")
    if mode not in MESHOPT_MODES:
        raise InvalidAsset(f"{what} has an unknown mode {mode!r:.40}")
    if filt not in MESHOPT_FILTERS:
        raise InvalidAsset(f"{what} has an unknown filter {filt!r:.40}")
    if "byteStride" in bv and bv["byteStride"] != stride:
        raise InvalidAsset(
            f"{what} has byteStride {stride}, but its bufferView has {bv['byteStride']!r:.20}"
        )
    if bv.get("byteLength") != stride * count:
        raise InvalidAsset(
            f"{what} holds {count} elements of {stride} bytes, but its bufferView is "
            f"{bv.get('byteLength')!r:.20} bytes (it must be byteStride x count)"
        )
    if mode == "ATTRIBUTES":
        if not 0 < stride <= 256 or stride % 4:
            raise InvalidAsset(f"{what}: ATTRIBUTES need a byteStride of 4 to 256 in fours")
    else:
        if stride not in (2, 4):
            raise InvalidAsset(f"{what}: {mode} need a byteStride of 2 or 4")
        if filt != "NONE":
            raise InvalidAsset(f"{what}: {mode} take no filter")
        if mode == "TRIANGLES" and count % 3:
            raise InvalidAsset(f"{what}: TRIANGLES need a count divisible by 3")
    if filt == "OCTAHEDRAL" and stride not in (4, 8):
        raise InvalidAsset(f"{what}: the OCTAHEDRAL filter needs a byteStride of 4 or 8")
    if filt == "QUATERNION" and stride != 8:
        raise InvalidAsset(f"{what}: the QUATERNION filter needs a byteStride of 8")


def decode_meshopt_views(
    doc: dict, buffers: list[bytes], placeholders: set[int], limits: Limits
) -> list[bytes]:
    """``buffers`` with every ``EXT_meshopt_compression`` bufferView decoded (filter undone)
    into its parent buffer's range. Buffers no compressed view writes into are returned as
    they are; the others are copies. Fallback buffers (``placeholders``) come as zeroed
    buffers of their :func:`placeholder_extent`."""
    views = doc.get("bufferViews", [])
    jobs = [(j, bv, ext) for j, bv in enumerate(views) if (ext := meshopt_view(bv)) is not None]
    if not jobs:
        return buffers
    import meshopt

    out: list = list(buffers)
    total = 0
    for j, bv, ext in jobs:
        what = f"bufferView {j}'s {MESHOPT}"
        parent = get_index(bv, "buffer", len(buffers), f"bufferView {j}")
        _check_meshopt(ext, bv, what, buffers, placeholders)
        count, stride = ext["count"], ext["byteStride"]
        total += count * stride
        if total > limits.max_unpacked_bytes:
            raise LimitExceeded(
                f"the {MESHOPT} bufferViews decode to more than {limits.max_unpacked_bytes} "
                "bytes (the limit)"
            )
        off = bv.get("byteOffset", 0)
        if not isinstance(off, int) or off < 0 or off + count * stride > len(buffers[parent]):
            raise InvalidAsset(f"bufferView {j} reaches past the end of buffer {parent}")
        if count == 0:
            continue
        src_off = ext.get("byteOffset", 0)
        data = bytes(buffers[ext["buffer"]][src_off : src_off + ext["byteLength"]])
        filt = ext.get("filter", "NONE")
        try:
            rows = meshopt.decode_gltf_buffer(
                data, count, stride, ext["mode"], None if filt == "NONE" else filt
            )
        except (ValueError, RuntimeError) as exc:
            raise InvalidAsset(
                f"{what} data cannot be decoded (truncated or corrupt: {str(exc)[:80]})"
            ) from None
        if not isinstance(out[parent], bytearray):
            out[parent] = bytearray(out[parent])
        out[parent][off : off + count * stride] = np.ascontiguousarray(rows).tobytes()
    return out


# ----------------------------------------------------------------------------- Draco
def draco_primitives(doc: dict) -> list[tuple[int, int, dict, dict]]:
    """(mesh index, primitive index, primitive, its ``KHR_draco_mesh_compression``) of every
    Draco-compressed primitive."""
    out = []
    for mi, mesh in enumerate(doc.get("meshes", [])):
        prims = mesh.get("primitives") if isinstance(mesh, dict) else None
        for pi, prim in enumerate(prims if isinstance(prims, list) else []):
            if isinstance(prim, dict) and (ext := _ext(prim, DRACO)) is not None:
                out.append((mi, pi, prim, ext))
    return out


def _accessor(doc: dict, index, what: str) -> tuple[dict, np.dtype, int, int]:
    accessors = doc.get("accessors", [])
    if not isinstance(index, int) or isinstance(index, bool) or not 0 <= index < len(accessors):
        raise InvalidAsset(f"{what} refers to accessor {index!r:.40}, which does not exist")
    acc = accessors[index]
    dtype = COMPONENT_DTYPES.get(acc.get("componentType"))
    ncomp = TYPE_SIZES.get(acc.get("type"))
    if dtype is None or ncomp is None:
        raise InvalidAsset(f"accessor {index} ({what}) has an invalid componentType or type")
    return acc, dtype, ncomp, _int(acc, "count", f"accessor {index}")


def _decoded_values(data: np.ndarray, dtype: np.dtype, what: str) -> np.ndarray:
    """Draco's output in the accessor's component type: floats stay floats, integers must fit."""
    if dtype.kind == "f":
        return data.astype(dtype)
    if data.dtype.kind == "f":
        raise InvalidAsset(f"{what} decodes to floats, but its accessor holds integers")
    info = np.iinfo(dtype)
    if data.size and (data.min() < info.min or data.max() > info.max):
        raise InvalidAsset(f"{what} decodes to values outside its accessor's component type")
    return data.astype(dtype)


def _varint(data: bytes, pos: int, what: str) -> tuple[int, int]:
    value = 0
    for k in range(10):
        if pos + k >= len(data):
            raise InvalidAsset(f"{what}: the Draco data ends inside its header")
        byte = data[pos + k]
        value |= (byte & 0x7F) << (7 * k)
        if not byte & 0x80:
            return value, pos + k + 1
    raise InvalidAsset(f"{what}: the Draco header has a malformed number")


def draco_header_counts(data: bytes, what: str) -> tuple[int, int, bool] | None:
    """(triangles, vertices, whether the vertex count is exact) that a Draco 2.2 mesh without
    metadata declares in its header, read before any decoding (edgebreaker declares the
    vertices it encodes, at most the points it decodes to); None for a layout it does not
    parse (other versions, metadata first). A point cloud is InvalidAsset."""
    major, minor, encoder, method = data[5], data[6], data[7], data[8]
    if encoder != _DRACO_MESH:
        raise InvalidAsset(f"{what}: the Draco data is a point cloud, not a mesh")
    flags = int.from_bytes(data[9:11], "little")
    if (major, minor) != (2, 2) or flags & _DRACO_METADATA:
        return None
    pos = _DRACO_HEADER
    if method == _DRACO_EDGEBREAKER:
        vertices, pos = _varint(data, pos + 1, what)  # after the traversal type
        faces, _ = _varint(data, pos, what)
        return faces, vertices, False
    faces, pos = _varint(data, pos, what)
    vertices, _ = _varint(data, pos, what)
    return faces, vertices, True


def decode_draco(doc: dict, buffers: list[bytes], limits: Limits) -> dict[int, np.ndarray]:
    """{accessor index: (count, ncomp) array in the accessor's component type} for the
    indices and every attribute each Draco primitive's extension maps to a Draco attribute."""
    prims = draco_primitives(doc)
    if not prims:
        return {}
    import DracoPy

    views = doc.get("bufferViews", [])
    out: dict[int, np.ndarray] = {}
    decoded: dict[int, Any] = {}  # bufferView -> DracoPy mesh
    for mi, pi, prim, ext in prims:
        what = f"mesh {mi} primitive {pi}'s {DRACO}"
        bvi = get_index(ext, "bufferView", len(views), what)
        amap = ext.get("attributes")
        if not isinstance(amap, dict) or not amap:
            raise InvalidAsset(f"{what} has no attributes")
        attrs = prim.get("attributes") or {}
        for sem, uid in amap.items():
            if sem not in attrs:
                raise InvalidAsset(f"{what} compresses {sem!r:.40}, which the primitive lacks")
            if not isinstance(uid, int) or isinstance(uid, bool) or uid < 0:
                raise InvalidAsset(f"{what} maps {sem!r:.40} to an invalid Draco id {uid!r:.40}")
        # sizes first: the accessors' counts bound what the decoder may produce
        counts = set()
        for sem in amap:
            counts.add(_accessor(doc, attrs[sem], f"{what} {sem}")[3])
        if len(counts) > 1:
            raise InvalidAsset(f"{what}: its attributes' accessors differ in count")
        nverts = counts.pop()
        tri_count = None
        if "indices" in prim:
            _, idt, inc, icount = _accessor(doc, prim["indices"], f"{what} indices")
            if inc != 1 or idt.kind != "u" or icount % 3:
                raise InvalidAsset(f"{what}: its indices accessor is not a triangle list")
            tri_count = icount // 3
            if tri_count > limits.max_triangles:
                raise LimitExceeded(
                    f"{what} has {tri_count} triangles; the limit is {limits.max_triangles}"
                )
        if nverts > 3 * limits.max_triangles + 3:
            raise LimitExceeded(f"{what} has {nverts} vertices, over what the limits allow")
        data = bytes(buffer_view_bytes(doc, buffers, bvi, what))
        if len(data) < _DRACO_HEADER or not data.startswith(DRACO_MAGIC):
            raise InvalidAsset(f"{what}: bufferView {bvi} does not hold Draco data")
        declared = draco_header_counts(data, what) if tri_count is not None else None
        if declared is not None:
            n_tri, n_vert, exact = declared
            if n_tri != tri_count or n_vert > nverts or (exact and n_vert != nverts):
                raise InvalidAsset(
                    f"{what}: the Draco data declares {n_tri} triangles and {n_vert} "
                    f"vertices; its accessors hold {tri_count} and {nverts}"
                )
        if bvi not in decoded:
            try:
                decoded[bvi] = DracoPy.decode(data)
            except Exception as exc:  # DracoPy raises its own and ValueError/RuntimeError
                raise InvalidAsset(
                    f"{what}: the Draco data cannot be decoded (truncated or corrupt: "
                    f"{str(exc)[:80]})"
                ) from None
        mesh = decoded[bvi]
        if tri_count is not None:
            faces = getattr(mesh, "faces", None)
            if faces is None or np.asarray(faces).reshape(-1).size != tri_count * 3:
                raise InvalidAsset(
                    f"{what}: the Draco data has a different number of triangles than its "
                    f"indices accessor ({tri_count})"
                )
            faces = np.asarray(faces).reshape(-1, 1)
            if faces.size and int(faces.max()) >= nverts:
                raise InvalidAsset(f"{what}: the Draco data indexes past its {nverts} vertices")
            out[prim["indices"]] = _decoded_values(
                faces, _accessor(doc, prim["indices"], what)[1], f"{what} indices"
            )
        for sem, uid in amap.items():
            attr = mesh.get_attribute_by_unique_id(uid)
            if attr is None:
                raise InvalidAsset(f"{what}: the Draco data has no attribute {uid} ({sem})")
            acc_index = attrs[sem]
            _, dtype, ncomp, count = _accessor(doc, acc_index, f"{what} {sem}")
            values = np.asarray(attr["data"])
            if values.ndim == 1:
                values = values.reshape(-1, 1)
            if values.shape != (count, ncomp):
                raise InvalidAsset(
                    f"{what}: Draco attribute {uid} ({sem}) is {values.shape[0]} x "
                    f"{values.shape[1]}, its accessor {count} x {ncomp}"
                )
            out[acc_index] = _decoded_values(values, dtype, f"{what} {sem}")
    return out


def decode_geometry(
    doc: dict, buffers: list[bytes], placeholders: set[int], limits: Limits
) -> DecodedGeometry | None:
    """The meshopt and Draco geometry of ``doc`` decoded, or None when it has none."""
    decoded = decode_meshopt_views(doc, buffers, placeholders, limits)
    accessors = decode_draco(doc, decoded, limits)
    if decoded is buffers and not accessors:
        return None
    return DecodedGeometry(buffers=decoded, accessors=accessors)
