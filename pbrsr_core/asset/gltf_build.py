"""A tiny glTF 2.0 writer for assets made from scratch (procedural demo and test assets).

It accumulates one binary buffer (4-byte aligned bufferViews with targets, accessors with
min/max where the spec requires them) plus images, and writes ``.glb`` or ``.gltf`` (buffer
and images as files or data URIs). Not used for saving loaded assets (see gltf_write).
"""

from __future__ import annotations

import base64
import json
import struct
from pathlib import Path

import numpy as np

from .gltf_read import CHUNK_BIN, CHUNK_JSON
from .gltf_write import atomic_write
from .images import EXT, MIME, ImageFormat, encode_image

ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
_CTYPE = {
    np.dtype("int8"): 5120,
    np.dtype("uint8"): 5121,
    np.dtype("int16"): 5122,
    np.dtype("uint16"): 5123,
    np.dtype("uint32"): 5125,
    np.dtype("float32"): 5126,
}
_TYPE = {1: "SCALAR", 2: "VEC2", 3: "VEC3", 4: "VEC4", 16: "MAT4"}


class GltfBuilder:
    def __init__(self) -> None:
        self.doc: dict = {"asset": {"version": "2.0", "generator": "pbrsr procedural"}}
        self.bin = bytearray()
        self.images: list[tuple[bytes, str, str, str]] = []  # data, mime, ext, file stem

    def _list(self, key: str) -> list:
        return self.doc.setdefault(key, [])

    def add(self, key: str, obj: dict) -> int:
        lst = self._list(key)
        lst.append(obj)
        return len(lst) - 1

    def view(self, data: bytes, target: int | None = None, stride: int | None = None) -> int:
        self.bin += b"\x00" * (-len(self.bin) % 4)
        bv = {"buffer": 0, "byteOffset": len(self.bin), "byteLength": len(data)}
        if stride:
            bv["byteStride"] = stride
        if target:
            bv["target"] = target
        self.bin += data
        return self.add("bufferViews", bv)

    def accessor(
        self,
        arr: np.ndarray,
        *,
        target: int | None = ARRAY_BUFFER,
        normalized: bool = False,
        minmax: bool = False,
    ) -> int:
        """Accessor for ``arr`` (N,) or (N, C); dtype picks the componentType."""
        a = np.ascontiguousarray(arr)
        ncomp = 1 if a.ndim == 1 else a.shape[1]
        acc = {
            "bufferView": self.view(a.tobytes(), target),
            "componentType": _CTYPE[a.dtype],
            "count": int(a.shape[0]),
            "type": _TYPE[ncomp],
        }
        if normalized:
            acc["normalized"] = True
        if minmax:
            flat = a.reshape(a.shape[0], -1)
            cast = float if a.dtype.kind == "f" else int
            acc["min"] = [cast(x) for x in flat.min(axis=0)]
            acc["max"] = [cast(x) for x in flat.max(axis=0)]
        return self.add("accessors", acc)

    def primitive(
        self,
        pos: np.ndarray,
        idx: np.ndarray,
        *,
        nrm: np.ndarray | None = None,
        uvs: dict[int, np.ndarray] | None = None,
        tng: np.ndarray | None = None,
        material: int | None = None,
        extra_attrs: dict[str, int] | None = None,
    ) -> dict:
        attrs = {"POSITION": self.accessor(pos.astype(np.float32), minmax=True)}
        if nrm is not None:
            attrs["NORMAL"] = self.accessor(nrm.astype(np.float32))
        if tng is not None:
            attrs["TANGENT"] = self.accessor(tng.astype(np.float32))
        for n, uv in sorted((uvs or {}).items()):
            attrs[f"TEXCOORD_{n}"] = self.accessor(uv.astype(np.float32))
        attrs.update(extra_attrs or {})
        idx_dtype = np.uint16 if pos.shape[0] < 65536 else np.uint32
        prim = {
            "attributes": attrs,
            "indices": self.accessor(
                idx.reshape(-1).astype(idx_dtype), target=ELEMENT_ARRAY_BUFFER
            ),
        }
        if material is not None:
            prim["material"] = material
        return prim

    def image(
        self, pixels: np.ndarray, *, fmt: ImageFormat = "png", bits: int = 8, name: str
    ) -> int:
        data = encode_image(pixels, bits, fmt)
        self.images.append((data, MIME[fmt], EXT[fmt], name))
        return self.add("images", {"name": name})

    def texture(self, image: int, sampler: int | None = None) -> int:
        t = {"source": image}
        if sampler is not None:
            t["sampler"] = sampler
        return self.add("textures", t)

    def use_extension(self, name: str) -> None:
        used = self._list("extensionsUsed")
        if name not in used:
            used.append(name)

    def write(
        self, path: Path, *, kind: str, data_uris: bool = False, image_dir: str = "textures"
    ) -> Path:
        """Write ``path`` as "glb" or "gltf"; gltf images go to ``image_dir/`` (or data URIs)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        doc = json.loads(json.dumps(self.doc))
        binary = bytearray(self.bin)
        if kind == "glb":
            for i, (data, mime, _ext, _stem) in enumerate(self.images):
                binary += b"\x00" * (-len(binary) % 4)
                doc.setdefault("bufferViews", []).append(
                    {"buffer": 0, "byteOffset": len(binary), "byteLength": len(data)}
                )
                binary += data
                doc["images"][i].update(
                    {"bufferView": len(doc["bufferViews"]) - 1, "mimeType": mime}
                )
            if binary:
                doc["buffers"] = [{"byteLength": len(binary)}]
            js = json.dumps(doc, separators=(",", ":")).encode()
            js += b" " * (-len(js) % 4)
            body = struct.pack("<II", len(js), CHUNK_JSON) + js
            if binary:
                binary += b"\x00" * (-len(binary) % 4)
                body += struct.pack("<II", len(binary), CHUNK_BIN) + bytes(binary)
            return atomic_write(path, struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)
        if kind != "gltf":
            raise ValueError(f"kind must be 'glb' or 'gltf', not {kind!r}")
        if binary:
            if data_uris:
                uri = "data:application/octet-stream;base64," + base64.b64encode(binary).decode()
            else:
                uri = f"{path.stem}.bin"
                atomic_write(path.parent / uri, bytes(binary))
            doc["buffers"] = [{"byteLength": len(binary), "uri": uri}]
        for i, (data, mime, ext, stem) in enumerate(self.images):
            if data_uris and mime in ("image/png", "image/jpeg"):
                doc["images"][i]["uri"] = f"data:{mime};base64," + base64.b64encode(data).decode()
                doc["images"][i]["mimeType"] = mime
            else:
                rel = f"{image_dir}/{stem}{ext}" if image_dir else f"{stem}{ext}"
                atomic_write(path.parent / rel, data)
                doc["images"][i]["uri"] = rel.replace(" ", "%20")
        return atomic_write(path, (json.dumps(doc, indent=2) + "\n").encode())
