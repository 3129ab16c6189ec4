"""Save an :class:`Asset` with chosen images replaced, editing (not regenerating) its JSON.

* ``.glb``: replaced images are embedded in the BIN chunk. The chunk is repacked: every
  bufferView that is not a replaced image, and every ``EXT_meshopt_compression`` range, keeps
  its bytes (and its byteOffset modulo 4, so accessor alignment holds; Draco data is a
  bufferView like any other); a replaced image's bufferView entry is rewritten in place when
  only that image uses it, otherwise a new bufferView is appended. When something other than a
  bufferView points into the BIN buffer, the old bytes are kept as they are and new images are
  appended instead. External files are copied; meshopt fallback buffers without a ``uri``
  stay without one.
* ``.gltf``: replaced images become files beside it (same folder as the original file, a safe
  version of its name, the output format's extension); images that were data URIs stay data
  URIs; unchanged external files are copied byte for byte; buffers stay data URIs or files as
  they were (a GLB's embedded buffer becomes ``<name>.bin``).

Textures keep ``KHR_texture_basisu`` / ``EXT_texture_webp`` / ``EXT_texture_avif`` exactly
where their images are still in that format, and gain or lose them where a requested format
changes it (:mod:`pbrsr_core.asset.gltf_textures`).

Every file is written atomically (temp file + rename) and only inside the output's folder.
"""

from __future__ import annotations

import base64
import copy
import json
import os
import struct
import tempfile
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor, wait
from pathlib import Path, PurePosixPath

import numpy as np

from ..errors import InvalidOptions, StorageError
from .gltf_read import CHUNK_BIN, CHUNK_JSON, COMPONENT_DTYPES, read_accessor_raw
from .gltf_textures import TEXTURE_EXTENSIONS, fallback_images, sync_texture_extensions
from .images import (
    TEXTURE_FORMATS,
    EncodedImage,
    ImageFormat,
    JpegEncoding,
    encode_image,
    jpeg_request,
    output_encoding,
    output_format,
)
from .mesh_codecs import DRACO, draco_primitives, meshopt_placeholders, meshopt_view
from .model import SRGB_ROLES, Asset, ImageData
from .texture_codecs import Ktx2Encoding, TextureEncoding, transfer
from .uris import encode_uri, is_data_uri, relative_path, resolve_inside, safe_stem

GLTF_MIMES = frozenset({"image/png", "image/jpeg", *TEXTURE_EXTENSIONS.values()})
"""Image types a glTF names (the core's and its image extensions'), which a GLB may embed."""


def _walk_refs(obj, key: str, fn) -> None:
    """Call ``fn(dict)`` for every dict in ``obj`` that has an int under ``key``."""
    stack = [obj]
    while stack:
        o = stack.pop()
        if isinstance(o, dict):
            if isinstance(o.get(key), int) and not isinstance(o.get(key), bool):
                fn(o)
            stack.extend(o.values())
        elif isinstance(o, list):
            stack.extend(o)


def _count_refs(doc: dict, key: str) -> dict[int, int]:
    counts: dict[int, int] = {}

    def inc(d):
        counts[d[key]] = counts.get(d[key], 0) + 1

    _walk_refs(doc, key, inc)
    return counts


def atomic_write(path: Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temp file in the same folder and a rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".pbrsr-", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except OSError as exc:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise StorageError(f"cannot write '{path.name}': {exc.strerror or exc}") from None
    return path


class _Writer:
    def __init__(self, asset: Asset, out_path: Path):
        self.asset = asset
        self.out_path = out_path
        self.out_dir = out_path.parent
        self.files: dict[str, bytes] = {}  # output-relative path -> bytes
        self.taken: set[str] = set()

    def target(self, rel: str) -> Path:
        return resolve_inside(self.out_dir, PurePosixPath(rel), "an output file")

    def unique(self, rel: str) -> str:
        p = PurePosixPath(rel)
        cand, k = rel, 1
        while cand.lower() in self.taken or cand.lower() == self.out_path.name.lower():
            cand = str(p.with_name(f"{p.stem}_{k}{p.suffix}"))
            k += 1
        self.taken.add(cand.lower())
        return cand

    def add_file(self, rel: str, data: bytes) -> None:
        self.files[rel] = data
        self.taken.add(rel.lower())

    def flush(self, main: bytes) -> list[Path]:
        written = [atomic_write(self.out_path, main)]
        for rel, data in self.files.items():
            written.append(atomic_write(self.target(rel), data))
        return written


_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_DTYPE_COMPONENT = {dt: c for c, dt in COMPONENT_DTYPES.items()}


def _append_accessor(
    doc: dict,
    out: bytearray,
    buffer: int,
    data: np.ndarray,
    atype: str,
    *,
    normalized: bool = False,
    target: int | None = _ARRAY_BUFFER,
    bounds: bool = False,
) -> int:
    """Append ``data`` (count, ncomp) of a glTF component dtype to ``out`` as its own
    bufferView (elements 4-byte aligned, so a byteStride is set when they are not) and a new
    accessor; returns the accessor index. ``bounds`` writes min/max (float data only)."""
    data = np.ascontiguousarray(data)
    dtype = data.dtype.newbyteorder("<") if data.dtype.itemsize > 1 else data.dtype
    data = data.astype(dtype, copy=False)
    count, ncomp = data.shape
    elem = dtype.itemsize * ncomp
    stride = elem if (elem % 4 == 0 or target != _ARRAY_BUFFER) else elem + (-elem % 4)
    if stride != elem:
        rows = np.zeros((count, stride), dtype=np.uint8)
        rows[:, :elem] = data.view(np.uint8).reshape(count, elem)
        payload = rows.tobytes()
    else:
        payload = data.tobytes()
    out += b"\x00" * _pad(len(out))
    view = {"buffer": buffer, "byteOffset": len(out), "byteLength": max(len(payload), 0)}
    if stride != elem:
        view["byteStride"] = stride
    if target is not None:
        view["target"] = target
    out += payload
    views = doc.setdefault("bufferViews", [])
    views.append(view)
    acc: dict = {
        "bufferView": len(views) - 1,
        "componentType": _DTYPE_COMPONENT[np.dtype(dtype.str.replace(">", "<"))],
        "count": int(count),
        "type": atype,
    }
    if normalized:
        acc["normalized"] = True
    if bounds and count and dtype.kind == "f":
        acc["min"] = [float(x) for x in data.min(axis=0)]
        acc["max"] = [float(x) for x in data.max(axis=0)]
    accessors = doc.setdefault("accessors", [])
    accessors.append(acc)
    return len(accessors) - 1


def _write_unwrapped(doc: dict, asset: Asset, out: bytearray, buffer: int) -> None:
    """Store every unwrapped primitive re-indexed: each attribute (and morph target) gathered
    through ``vmapping`` into a new accessor, new triangle-list indices, new TEXCOORD sets.
    Reads come from the source document and buffers (``doc`` is the copy being written)."""
    src = asset.document
    geometry = asset.geometry
    buffers = geometry.buffers if geometry else asset.buffers
    decoded = geometry.accessors if geometry else None
    for (mi, pi), un in sorted(asset.generated_uvs.items()):
        prim = doc["meshes"][mi]["primitives"][pi]
        cache: dict[int, int] = {}

        def gathered(acc_index: int, semantic: str, un=un, cache=cache) -> int:
            if acc_index not in cache:
                raw, acc = read_accessor_raw(src, buffers, acc_index, semantic, decoded)
                keep_bounds = semantic == "POSITION" or ("min" in acc and raw.dtype.kind == "f")
                cache[acc_index] = _append_accessor(
                    doc,
                    out,
                    buffer,
                    raw[un.vmapping],
                    acc["type"],
                    normalized=bool(acc.get("normalized")),
                    bounds=keep_bounds,
                )
            return cache[acc_index]

        attrs = prim.get("attributes") or {}
        for key in list(attrs):
            attrs[key] = gathered(attrs[key], key)
        for target in prim.get("targets") or []:
            for key in list(target):
                target[key] = gathered(target[key], key)
        for n, uv in sorted(un.uvs.items()):
            attrs[f"TEXCOORD_{n}"] = _append_accessor(
                doc, out, buffer, uv.astype(np.float32), "VEC2"
            )
        nv = un.vmapping.shape[0]
        itype = np.dtype("<u2") if nv < 65535 else np.dtype("<u4")
        prim["indices"] = _append_accessor(
            doc,
            out,
            buffer,
            un.indices.reshape(-1, 1).astype(itype),
            "SCALAR",
            target=_ELEMENT_ARRAY_BUFFER,
        )
        prim.pop("mode", None)  # strips and fans became triangle lists
        exts = prim.get("extensions")
        if isinstance(exts, dict) and exts.pop(DRACO, None) is not None and not exts:
            del prim["extensions"]  # the primitive is stored uncompressed
    if asset.generated_uvs and not draco_primitives(doc):
        for key in ("extensionsUsed", "extensionsRequired"):
            if DRACO in doc.get(key, []):
                doc[key] = [e for e in doc[key] if e != DRACO]
                if not doc[key]:
                    del doc[key]
    out += b"\x00" * _pad(len(out))


def encode_images(
    asset: Asset, new_images: Mapping[int, np.ndarray | EncodedImage], image_format: str = "same"
) -> dict[int, EncodedImage]:
    """{image index: :class:`EncodedImage`} for every replaced image, in the format
    :func:`output_format` picks for it (images given already encoded are kept as they are);
    ``image_format`` "jpeg:Q" or "jpeg:Q:420" writes the images that become JPEG at quality Q,
    the chroma at half resolution with 420 (:func:`jpeg_request`).

    The PNG/JPEG fallback of a replaced KTX2/WebP/AVIF image
    (:func:`~pbrsr_core.asset.gltf_textures.fallback_images`) is replaced by the same pixels,
    in its own format when ``image_format`` asks for KTX2/WebP/AVIF (a fallback must stay
    PNG/JPEG). A KTX2 image is written with :func:`output_encoding`'s parameters, its pixels
    moved from its role's colour space to its transfer function.

    The images are encoded on up to as many threads as the process may use cores: the PNG
    and JPEG encoders release the GIL (four 2048² PNGs: 1.85 s on one thread, 1.13 s on two,
    the same bytes)."""
    image_format, jpeg = jpeg_request(image_format)
    by_index = {im.index: im for im in asset.images}
    n_images = len(asset.document.get("images", []))
    out: dict[int, EncodedImage] = {}
    Encoding = TextureEncoding | JpegEncoding | None
    todo: dict[int, tuple[np.ndarray, int, ImageFormat, str, str, Encoding]] = {}
    fallbacks = fallback_images(asset.document)
    new_images = dict(new_images)
    for fallback, shown in fallbacks.items():
        if fallback not in new_images and isinstance(new_images.get(shown), np.ndarray):
            new_images[fallback] = new_images[shown]
    for i, pixels in new_images.items():
        if not isinstance(i, int) or not 0 <= i < n_images:
            raise InvalidOptions(f"there is no image {i!r} to replace")
        if isinstance(pixels, EncodedImage):
            out[i] = pixels
            continue
        arr = np.asarray(pixels, dtype=np.float32)
        if arr.ndim != 3 or not 1 <= arr.shape[2] <= 4:
            raise ValueError(f"image {i}: pixels must be (H, W, C), C in 1..4; got {arr.shape}")
        src = by_index.get(i)
        probe = ImageData(
            index=i,
            name=src.name if src else f"image{i}",
            pixels=arr,
            bit_depth=src.bit_depth if src else 8,
            mime=src.mime if src else "image/png",
            roles=set(src.roles) if src else set(),
            encoding=src.encoding if src else None,
        )
        requested = image_format
        if i in fallbacks and image_format in TEXTURE_FORMATS:
            requested = "same"
        fmt, bits, mime, ext = output_format(probe, requested)
        encoding: Encoding = jpeg if fmt == "jpeg" and jpeg else output_encoding(probe, fmt)
        if isinstance(encoding, Ktx2Encoding):
            arr = transfer(arr, bool(probe.roles & SRGB_ROLES), encoding.srgb)
        todo[i] = (arr, bits, fmt, mime, ext, encoding)

    def encode(i: int) -> EncodedImage:
        arr, bits, fmt, mime, ext, encoding = todo[i]
        return EncodedImage(encode_image(arr, bits, fmt, encoding), mime, ext, fmt, bits)

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    workers = min(len(todo), cores or 1)
    if workers > 1:
        pool = ThreadPoolExecutor(workers, thread_name_prefix="pbrsr-encode")
        try:
            futures = {i: pool.submit(encode, i) for i in todo}
            pending = set(futures.values())
            while pending:  # short waits: a cancelled job's exception gets in between them
                _, pending = wait(pending, timeout=0.1)
            out.update((i, f.result()) for i, f in futures.items())
        finally:  # on an exception the queued images are dropped, running ones end alone
            pool.shutdown(wait=False, cancel_futures=True)
    else:
        out.update((i, encode(i)) for i in todo)
    return {i: out[i] for i in new_images}  # in the caller's order


def _copy_external(w: _Writer, asset: Asset, doc: dict, replaced: set[int]) -> None:
    """Queue every still-referenced external file (buffers, unreplaced images) for copying."""
    for i, buf in enumerate(doc.get("buffers", [])):
        uri = buf.get("uri")
        if isinstance(uri, str) and not is_data_uri(uri):
            rel = str(relative_path(uri, f"buffer {i}"))
            w.add_file(rel, asset.resources[rel] if rel in asset.resources else asset.buffers[i])
    for i, img in enumerate(doc.get("images", [])):
        uri = img.get("uri")
        if i in replaced or not isinstance(uri, str) or is_data_uri(uri):
            continue
        rel = str(relative_path(uri, f"image {i}"))
        if rel in asset.resources:
            w.add_file(rel, asset.resources[rel])


def _image_file_name(asset: Asset, doc: dict, i: int, ext: str) -> str:
    img = doc["images"][i]
    uri = img.get("uri")
    if isinstance(uri, str) and not is_data_uri(uri):
        rel = relative_path(uri, f"image {i}")
        parent = str(rel.parent) if str(rel.parent) != "." else ""
        stem = safe_stem(rel.name, f"image{i}")
    else:
        parent = ""
        name = img.get("name")
        stem = safe_stem(name if isinstance(name, str) else "", f"image{i}")
    return f"{parent}/{stem}{ext}" if parent else f"{stem}{ext}"


def _save_gltf(asset: Asset, out_path: Path, encoded: dict) -> list[Path]:
    doc = copy.deepcopy(asset.document)
    w = _Writer(asset, out_path)
    replaced = set(encoded)
    # a GLB's embedded buffer becomes a .bin file (meshopt fallback buffers have no bytes)
    placeholders = meshopt_placeholders(asset.document, asset.kind == "glb")
    for i, buf in enumerate(doc.get("buffers", [])):
        if "uri" not in buf and i not in placeholders:
            rel = w.unique(f"{safe_stem(out_path.name, 'asset')}.bin")
            buf["uri"] = encode_uri(rel)
            w.add_file(rel, bytes(asset.buffers[i][: buf["byteLength"]]))
    _copy_external(w, asset, doc, replaced)
    if asset.generated_uvs:
        geometry = bytearray()
        buffers = doc.setdefault("buffers", [])
        buffers.append({"byteLength": 0})
        _write_unwrapped(doc, asset, geometry, len(buffers) - 1)
        rel = w.unique(f"{safe_stem(out_path.name, 'asset')}_unwrapped.bin")
        buffers[-1].update({"uri": encode_uri(rel), "byteLength": len(geometry)})
        w.add_file(rel, bytes(geometry))
    for i in sorted(replaced):
        data, mime, ext = encoded[i].data, encoded[i].mime, encoded[i].ext
        img = doc["images"][i]
        was_data = isinstance(img.get("uri"), str) and is_data_uri(img["uri"])
        img.pop("bufferView", None)
        if was_data:
            img["uri"] = f"data:{mime};base64," + base64.b64encode(data).decode("ascii")
        else:
            rel = w.unique(_image_file_name(asset, doc, i, ext))
            img["uri"] = encode_uri(rel)
            w.add_file(rel, data)
        if mime in GLTF_MIMES and (was_data or "mimeType" in img):
            img["mimeType"] = mime
        elif mime not in GLTF_MIMES:
            img.pop("mimeType", None)
    sync_texture_extensions(doc, _written_mime(asset, encoded))
    main = (json.dumps(doc, indent=2, ensure_ascii=False) + "\n").encode("utf-8")
    return w.flush(main)


def _pad(n: int, align: int = 4) -> int:
    return -n % align


def _written_mime(asset: Asset, encoded: dict[int, EncodedImage]):
    """image index -> the MIME type of the image as it is written."""
    by_index = {im.index: im.mime for im in asset.images}
    return lambda i: encoded[i].mime if i in encoded else by_index.get(i, "")


def _save_glb(asset: Asset, out_path: Path, encoded: dict) -> list[Path]:
    doc = copy.deepcopy(asset.document)
    w = _Writer(asset, out_path)
    replaced = set(encoded)
    sync_texture_extensions(doc, _written_mime(asset, encoded))
    # a GLB embeds only the formats glTF names validly: EXR/TIFF become files beside it
    for i in sorted(replaced):
        data, mime, ext = encoded[i].data, encoded[i].mime, encoded[i].ext
        if mime not in GLTF_MIMES:
            img = doc["images"][i]
            img.pop("bufferView", None)
            img.pop("mimeType", None)
            rel = w.unique(_image_file_name(asset, doc, i, ext))
            img["uri"] = encode_uri(rel)
            w.add_file(rel, data)
    encoded = {i: e for i, e in encoded.items() if e.mime in GLTF_MIMES}
    external = replaced - set(encoded)
    replaced = set(encoded)
    buffers = (
        doc.setdefault("buffers", [])
        if (encoded or asset.generated_uvs or doc.get("buffers"))
        else []
    )
    if buffers and 0 in meshopt_placeholders(asset.document, asset.kind == "glb"):
        # a GLB's buffer 0 without a uri is its BIN chunk: a meshopt fallback buffer goes last
        moved = {old: old - 1 if old else len(buffers) - 1 for old in range(len(buffers))}
        for k, v in doc.items():
            if k != "buffers":
                _walk_refs(
                    v, "buffer", lambda d: d.update(buffer=moved.get(d["buffer"], d["buffer"]))
                )
        buffers.append(buffers.pop(0))
    has_bin = bool(buffers) and "uri" not in buffers[0]
    if has_bin:
        old_bin = bytes(asset.buffers[0][: buffers[0]["byteLength"]])
    else:
        old_bin = b""
        if encoded or asset.generated_uvs:
            # a new GLB-stored buffer must be buffer 0: shift every buffer index

            def shift(d):
                d["buffer"] += 1

            _walk_refs(doc, "buffer", shift)  # bufferViews and their meshopt ranges too
            buffers.insert(0, {"byteLength": 0})
            has_bin = True
    _copy_external(w, asset, doc, replaced | external)

    views = doc.get("bufferViews", [])
    view_refs = _count_refs(doc, "bufferView")
    # bufferViews to refill in place with a replaced image's bytes
    inplace: dict[int, int] = {}
    for i in sorted(replaced):
        bvi = doc["images"][i].get("bufferView")
        if (
            isinstance(bvi, int)
            and 0 <= bvi < len(views)
            and view_refs.get(bvi, 0) == 1
            and views[bvi].get("buffer") == 0
            and has_bin
        ):
            inplace[bvi] = i
    outside_refs = []
    for k, v in doc.items():
        if k not in ("bufferViews", "buffers"):
            _walk_refs(v, "buffer", lambda d: outside_refs.append(d) if d["buffer"] == 0 else None)

    new_bin = bytearray()
    if has_bin:
        if outside_refs:  # keep the old bytes where they are; append new images
            new_bin += old_bin
            for bvi, i in inplace.items():
                new_bin += b"\x00" * _pad(len(new_bin))
                views[bvi]["byteOffset"] = len(new_bin)
                views[bvi]["byteLength"] = len(encoded[i].data)
                new_bin += encoded[i].data
        else:  # repack: ranges in their byte order, dead image bytes dropped
            # (bufferView index or None, the dict holding byteOffset/byteLength)
            ranges: list[tuple[int | None, dict]] = [
                (j, bv) for j, bv in enumerate(views) if bv.get("buffer") == 0
            ]
            ranges += [
                (None, ext)
                for bv in views
                if (ext := meshopt_view(bv)) is not None and ext.get("buffer") == 0
            ]
            ranges.sort(key=lambda r: r[1].get("byteOffset", 0))
            for j, holder in ranges:
                old_off = holder.get("byteOffset", 0)
                if j is not None and j in inplace:
                    data, residue = encoded[inplace[j]].data, 0
                else:
                    data = old_bin[old_off : old_off + holder["byteLength"]]
                    residue = old_off % 4
                new_bin += b"\x00" * ((residue - len(new_bin)) % 4)
                holder["byteOffset"] = len(new_bin)
                holder["byteLength"] = len(data)
                new_bin += data
        placed = set(inplace.values())
        for i in sorted(replaced - placed):
            new_bin += b"\x00" * _pad(len(new_bin))
            views.append(
                {"buffer": 0, "byteOffset": len(new_bin), "byteLength": len(encoded[i].data)}
            )
            doc["bufferViews"] = views
            img = doc["images"][i]
            img.pop("uri", None)
            img["bufferView"] = len(views) - 1
            new_bin += encoded[i].data
        for i in replaced:
            doc["images"][i]["mimeType"] = encoded[i].mime
        if asset.generated_uvs:
            _write_unwrapped(doc, asset, new_bin, 0)
        buffers[0]["byteLength"] = len(new_bin)

    json_bytes = json.dumps(doc, separators=(",", ":"), ensure_ascii=False).encode("utf-8")
    json_bytes += b" " * _pad(len(json_bytes))
    body = struct.pack("<II", len(json_bytes), CHUNK_JSON) + json_bytes
    if has_bin:
        bin_bytes = bytes(new_bin) + b"\x00" * _pad(len(new_bin))
        body += struct.pack("<II", len(bin_bytes), CHUNK_BIN) + bin_bytes
    main = struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body
    return w.flush(main)


def save_asset(
    asset: Asset,
    out_path: Path,
    new_images: Mapping[int, np.ndarray | EncodedImage] | None = None,
    image_format: str = "same",
) -> list[Path]:
    """Write ``asset`` to ``out_path`` (``.glb`` or ``.gltf``, by its suffix) with the images
    in ``new_images`` ({glTF image index: (H, W, C) float32 [0, 1] as stored, or an
    :class:`EncodedImage` from :func:`encode_images`}) replaced.

    ``image_format``: "same", "png", "png16", "exr", "jpeg", "ktx2", "webp" or "avif" (see
    :func:`pbrsr_core.asset.images.output_format`: precision never drops below the input's),
    or "jpeg:Q" / "jpeg:Q:420" (:func:`~pbrsr_core.asset.images.jpeg_request`).
    A ``.glb`` embeds PNG, JPEG, KTX2, WebP and AVIF: a replaced image written as EXR/TIFF goes
    to a file beside the ``.glb`` instead. Textures name their images through the image
    extensions their formats need (``gltf_textures.sync_texture_extensions``). Returns the
    written paths, the main file first.
    """
    out_path = Path(out_path)
    suffix = out_path.suffix.lower()
    if suffix not in (".glb", ".gltf"):
        raise InvalidOptions(f"the output must be a .glb or .gltf file, not '{out_path.name}'")
    out_path.parent.mkdir(parents=True, exist_ok=True)
    encoded = encode_images(asset, dict(new_images or {}), image_format)
    if suffix == ".glb":
        return _save_glb(asset, out_path, encoded)
    return _save_gltf(asset, out_path, encoded)
