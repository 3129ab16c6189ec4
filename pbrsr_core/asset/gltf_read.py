"""Low-level glTF reading: the GLB container, buffers, bufferViews and accessors, checked.

Everything here raises :class:`InvalidAsset` / :class:`UnsupportedAsset` /
:class:`LimitExceeded` with the glTF object it is about (``accessor 3``), never an IndexError.
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Mapping
from pathlib import Path
from typing import Literal, overload

import numpy as np

from ..errors import InvalidAsset, LimitExceeded, UnsupportedAsset
from ..limits import Limits
from .gltf_schema import check_types
from .uris import decode_data_uri, is_data_uri, read_resource, relative_path

GLB_MAGIC = b"glTF"
CHUNK_JSON = 0x4E4F534A
CHUNK_BIN = 0x004E4942

COMPONENT_DTYPES: dict[int, np.dtype] = {
    5120: np.dtype("i1"),
    5121: np.dtype("u1"),
    5122: np.dtype("<i2"),
    5123: np.dtype("<u2"),
    5125: np.dtype("<u4"),
    5126: np.dtype("<f4"),
}
TYPE_SIZES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}

# required extensions that change how geometry or images must be decoded
UNSUPPORTED_REQUIRED = {
    "KHR_draco_mesh_compression": None,  # supported (mesh_codecs)
    "EXT_meshopt_compression": None,  # supported (mesh_codecs)
    "KHR_texture_basisu": None,  # supported (asset.texture_codecs)
    "EXT_texture_webp": None,  # supported
    "EXT_texture_avif": None,  # supported
    "KHR_mesh_quantization": None,  # supported
    "KHR_texture_transform": None,  # supported
}


def parse_glb(data: bytes) -> tuple[dict, bytes | None]:
    """Split a GLB into (parsed JSON, BIN chunk bytes or None), checking every length."""
    if len(data) < 12:
        raise InvalidAsset("the GLB file is truncated (shorter than its 12-byte header)")
    magic, version, length = struct.unpack("<4sII", data[:12])
    if magic != GLB_MAGIC:
        raise InvalidAsset("not a GLB file (bad magic)")
    if version == 1:
        raise UnsupportedAsset("this is a glTF 1.0 binary file; pbrsr reads glTF 2.0 only")
    if version != 2:
        raise UnsupportedAsset(f"GLB container version {version} is not supported (2 is)")
    if length > len(data):
        raise InvalidAsset(
            f"the GLB file is truncated: its header says {length} bytes, the file has {len(data)}"
        )
    if length < 20:
        raise InvalidAsset("the GLB file has no JSON chunk")
    pos = 12
    json_doc = None
    bin_chunk = None
    index = 0
    while pos < length:
        if pos + 8 > length:
            raise InvalidAsset("the GLB file ends inside a chunk header")
        clen, ctype = struct.unpack("<II", data[pos : pos + 8])
        start, end = pos + 8, pos + 8 + clen
        if end > length:
            raise InvalidAsset(
                f"GLB chunk {index} says it is {clen} bytes, past the end of the file"
            )
        if index == 0:
            if ctype != CHUNK_JSON:
                raise InvalidAsset("the first GLB chunk is not JSON")
            json_doc = parse_json(data[start:end])
        elif ctype == CHUNK_BIN:
            if bin_chunk is not None:
                raise InvalidAsset("the GLB file has more than one BIN chunk")
            bin_chunk = data[start:end]
        elif ctype == CHUNK_JSON:
            raise InvalidAsset("the GLB file has more than one JSON chunk")
        pos = end + (-clen % 4 if end < length else 0)
        index += 1
    if json_doc is None:
        raise InvalidAsset("the GLB file has no JSON chunk")
    return json_doc, bin_chunk


def parse_json(raw: bytes) -> dict:
    """The glTF JSON document, checked for being an object with a 2.x ``asset.version``."""
    try:
        text = raw.decode("utf-8-sig")
        doc = json.loads(text)
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise InvalidAsset(f"the glTF JSON cannot be parsed: {str(exc)[:120]}") from None
    if not isinstance(doc, dict):
        raise InvalidAsset("the glTF JSON is not an object")
    asset = doc.get("asset")
    if not isinstance(asset, dict) or not isinstance(asset.get("version"), str):
        raise InvalidAsset("the glTF JSON has no asset.version (is it a glTF file?)")
    version = asset["version"]
    if version.startswith("1"):
        raise UnsupportedAsset("this is a glTF 1.0 file; pbrsr reads glTF 2.0 only")
    if not version.startswith("2."):
        raise UnsupportedAsset(f"glTF version {version!r} is not supported (2.0 is)")
    min_version = asset.get("minVersion")
    if isinstance(min_version, str) and min_version not in ("2.0",):
        raise UnsupportedAsset(f"the asset needs glTF {min_version}; pbrsr reads 2.0")
    for ext in doc.get("extensionsRequired", []) or []:
        what = UNSUPPORTED_REQUIRED.get(ext) if isinstance(ext, str) else None
        if what:
            raise UnsupportedAsset(f"the asset requires {ext} ({what}), which pbrsr cannot read")
    for key in (
        "buffers",
        "bufferViews",
        "accessors",
        "images",
        "textures",
        "samplers",
        "materials",
        "meshes",
        "nodes",
        "scenes",
    ):
        if key in doc and not isinstance(doc[key], list):
            raise InvalidAsset(f"'{key}' in the glTF JSON is not an array")
        for i, item in enumerate(doc.get(key, [])):
            if not isinstance(item, dict):
                raise InvalidAsset(f"{key}[{i}] in the glTF JSON is not an object")
    check_types(doc)
    return doc


@overload
def get_index(obj: dict, key: str, n: int, what: str, required: Literal[True] = True) -> int: ...


@overload
def get_index(obj: dict, key: str, n: int, what: str, required: bool) -> int | None: ...


def get_index(obj: dict, key: str, n: int, what: str, required: bool = True) -> int | None:
    """``obj[key]`` as an index into an array of length ``n``, checked."""
    v = obj.get(key)
    if v is None:
        if required:
            raise InvalidAsset(f"{what} has no '{key}'")
        return None
    if not isinstance(v, int) or isinstance(v, bool) or not 0 <= v < n:
        raise InvalidAsset(f"{what} has '{key}' = {v!r}, which is out of range")
    return v


def load_buffers(
    doc: dict,
    folder: Path,
    bin_chunk: bytes | None,
    is_glb: bool,
    limits: Limits,
    resources: dict[str, bytes],
    placeholders: Mapping[int, int] | None = None,
) -> list[bytes]:
    """The bytes of every buffer, each at least ``byteLength`` long, except the buffers in
    ``placeholders`` ({index: size}: fallback buffers with no bytes in the file), which are
    zeroed buffers of that size."""
    out: list[bytes] = []
    for i, buf in enumerate(doc.get("buffers", [])):
        what = f"buffer {i}"
        blen = buf.get("byteLength")
        if not isinstance(blen, int) or blen < 0:
            raise InvalidAsset(f"{what} has no valid byteLength")
        uri = buf.get("uri")
        if placeholders and i in placeholders:
            out.append(bytes(placeholders[i]))
            continue
        if uri is None:
            if not (is_glb and i == 0):
                raise InvalidAsset(f"{what} has no uri")
            if bin_chunk is None:
                raise InvalidAsset("the GLB file's buffer 0 needs a BIN chunk, which is missing")
            data = bin_chunk
        elif not isinstance(uri, str):
            raise InvalidAsset(f"{what} has a uri that is not a string")
        elif is_data_uri(uri):
            data, _ = decode_data_uri(uri, limits.max_data_uri_bytes, what)
        else:
            rel = str(relative_path(uri, what))
            data = read_resource(folder, uri, limits.max_file_bytes, what)
            resources[rel] = data
        if len(data) < blen:
            raise InvalidAsset(f"{what} is {len(data)} bytes, shorter than its byteLength {blen}")
        out.append(data)
    return out


def check_buffer_views(doc: dict, buffers: list[bytes]) -> None:
    for i, bv in enumerate(doc.get("bufferViews", [])):
        what = f"bufferView {i}"
        b = get_index(bv, "buffer", len(buffers), what)
        off = bv.get("byteOffset", 0)
        blen = bv.get("byteLength")
        if not isinstance(off, int) or off < 0 or not isinstance(blen, int) or blen < 0:
            raise InvalidAsset(f"{what} has an invalid byteOffset/byteLength")
        if off + blen > len(buffers[b]):
            raise InvalidAsset(f"{what} reaches past the end of buffer {b}")
        stride = bv.get("byteStride")
        if stride is not None and (not isinstance(stride, int) or not 4 <= stride <= 252):
            raise InvalidAsset(f"{what} has an invalid byteStride {stride!r}")


def buffer_view_bytes(doc: dict, buffers: list[bytes], index: int, what: str) -> bytes:
    views = doc.get("bufferViews", [])
    if not isinstance(index, int) or not 0 <= index < len(views):
        raise InvalidAsset(f"{what} refers to bufferView {index!r}, which does not exist")
    bv = views[index]
    off = bv.get("byteOffset", 0)
    return buffers[bv["buffer"]][off : off + bv["byteLength"]]


def _read_elements(
    doc: dict,
    buffers: list[bytes],
    view_index: int,
    byte_offset: int,
    count: int,
    dtype: np.dtype,
    ncomp: int,
    what: str,
    stride: int | None = None,
) -> np.ndarray:
    view = buffer_view_bytes(doc, buffers, view_index, what)
    elem = dtype.itemsize * ncomp
    if stride is None:
        stride = doc["bufferViews"][view_index].get("byteStride") or elem
    if not isinstance(byte_offset, int) or byte_offset < 0:
        raise InvalidAsset(f"{what} has an invalid byteOffset")
    if count > 0 and byte_offset + stride * (count - 1) + elem > len(view):
        raise InvalidAsset(f"{what} reads {count} elements past the end of bufferView {view_index}")
    if count == 0:
        return np.zeros((0, ncomp), dtype=dtype)
    raw = np.frombuffer(view, dtype=np.uint8)
    if stride == elem:
        flat = raw[byte_offset : byte_offset + elem * count]
        return flat.view(dtype).reshape(count, ncomp).copy()
    rows = np.lib.stride_tricks.as_strided(
        raw[byte_offset:], shape=(count, elem), strides=(stride, 1), writeable=False
    )
    return np.ascontiguousarray(rows).view(dtype).reshape(count, ncomp).copy()


def read_accessor(
    doc: dict,
    buffers: list[bytes],
    index: int,
    what: str = "",
    decoded: Mapping[int, np.ndarray] | None = None,
) -> np.ndarray:
    """Accessor ``index`` as a (count, ncomp) array: float64 when ``normalized`` or float,
    else its integer type widened to int64. Sparse accessors are applied. Every read is
    bounds-checked against its bufferView. ``decoded``: the data of accessors that Draco
    primitives fill (:func:`pbrsr_core.asset.mesh_codecs.decode_draco`)."""
    data, acc = read_accessor_raw(doc, buffers, index, what, decoded)
    dtype = data.dtype
    if dtype.kind == "f":
        return data.astype(np.float64)
    if acc.get("normalized"):
        info = np.iinfo(dtype)
        out = data.astype(np.float64) / float(info.max)
        return np.maximum(out, -1.0) if dtype.kind == "i" else out
    return data.astype(np.int64)


def read_accessor_raw(
    doc: dict,
    buffers: list[bytes],
    index: int,
    what: str = "",
    decoded: Mapping[int, np.ndarray] | None = None,
) -> tuple[np.ndarray, dict]:
    """(Accessor ``index`` as a dense (count, ncomp) array of its own component type, sparse
    substitution applied; the accessor's JSON object). An accessor in ``decoded`` takes its
    data from there instead of a bufferView."""
    accessors = doc.get("accessors", [])
    label = f"accessor {index}" + (f" ({what})" if what else "")
    if not isinstance(index, int) or isinstance(index, bool) or not 0 <= index < len(accessors):
        raise InvalidAsset(f"{label} does not exist")
    acc = accessors[index]
    ctype = acc.get("componentType")
    if ctype not in COMPONENT_DTYPES:
        raise InvalidAsset(f"{label} has an unknown componentType {ctype!r}")
    atype = acc.get("type")
    if atype not in TYPE_SIZES:
        raise InvalidAsset(f"{label} has an unknown type {atype!r}")
    count = acc.get("count")
    if not isinstance(count, int) or count < 0:
        raise InvalidAsset(f"{label} has an invalid count")
    if atype in ("MAT2", "MAT3") and ctype != 5126:
        raise UnsupportedAsset(f"{label}: padded small-integer matrices are not supported")
    dtype = COMPONENT_DTYPES[ctype]
    ncomp = TYPE_SIZES[atype]
    if count > 1 << 31:
        raise LimitExceeded(f"{label} has {count} elements")
    if decoded is not None and index in decoded:
        data = decoded[index]
    elif "bufferView" in acc:
        data = _read_elements(
            doc,
            buffers,
            acc["bufferView"],
            acc.get("byteOffset", 0),
            count,
            dtype,
            ncomp,
            label,
        )
    else:
        data = np.zeros((count, ncomp), dtype=dtype)
    sparse = acc.get("sparse")
    if sparse is not None:
        data = data.copy()
        scount = sparse.get("count")
        idx_info, val_info = sparse.get("indices", {}), sparse.get("values", {})
        if not isinstance(scount, int) or not 1 <= scount <= count:
            raise InvalidAsset(f"{label} has an invalid sparse count")
        ictype = idx_info.get("componentType")
        if ictype not in (5121, 5123, 5125):
            raise InvalidAsset(f"{label} has invalid sparse index type")
        sidx = _read_elements(
            doc,
            buffers,
            idx_info.get("bufferView"),
            idx_info.get("byteOffset", 0),
            scount,
            COMPONENT_DTYPES[ictype],
            1,
            label + " sparse indices",
            stride=COMPONENT_DTYPES[ictype].itemsize,
        )[:, 0].astype(np.int64)
        svals = _read_elements(
            doc,
            buffers,
            val_info.get("bufferView"),
            val_info.get("byteOffset", 0),
            scount,
            dtype,
            ncomp,
            label + " sparse values",
            stride=dtype.itemsize * ncomp,
        )
        if sidx.size and (sidx.max() >= count or sidx.min() < 0):
            raise InvalidAsset(f"{label} has sparse indices out of range")
        data[sidx] = svals
    return data, acc


def num_list(v, n: int, what: str) -> list[float]:
    """``v`` as ``n`` finite floats (a JSON array of numbers), else :class:`InvalidAsset`."""
    if (
        not isinstance(v, list)
        or len(v) != n
        or not all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v
        )
    ):
        raise InvalidAsset(f"{what} must be {n} finite numbers")
    return [float(x) for x in v]
