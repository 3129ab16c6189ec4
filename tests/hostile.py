"""A corpus of hostile inputs for the asset loader (and the API's upload checks).

``hostile_cases(folder)`` writes each case into its own sub-folder and returns
:class:`HostileCase` records: the file to load, the typed error it must raise, the limits to
load it with and (optionally) a word the message must contain. Everything is procedural.
"""

from __future__ import annotations

import base64
import json
import struct
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pbrsr_bench.variants import draco_variant, meshopt_variant
from pbrsr_core.asset.procedural import make_quad_asset
from pbrsr_core.errors import (
    InvalidAsset,
    LimitExceeded,
    PbrsrError,
    UnprocessableAsset,
    UnsupportedAsset,
)
from pbrsr_core.limits import Limits


@dataclass
class HostileCase:
    name: str
    path: Path
    error: type[PbrsrError]
    limits: Limits = field(default_factory=Limits)
    says: str = ""  # a word the error message must contain (case-insensitive)
    unwrap: bool = True


def png_header_bomb(width: int = 100_000, height: int = 100_000) -> bytes:
    """A tiny PNG whose header declares width x height RGB pixels."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        crc = zlib.crc32(kind + data) & 0xFFFFFFFF
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(b"\x00" * 64))
        + chunk(b"IEND", b"")
    )


def _quad(folder: Path, kind: str = "gltf") -> Path:
    return make_quad_asset(folder / f"quad.{kind}", size=8, subdiv=2)


def _edit(src: Path, dest: Path, fn) -> Path:
    doc = json.loads(src.read_text())
    fn(doc)
    dest.write_text(json.dumps(doc))
    return dest


def _glb_parts(glb: bytes) -> tuple[bytes, bytes]:
    jlen = struct.unpack("<I", glb[12:16])[0]
    return glb[20 : 20 + jlen], glb[20 + jlen :]


def gltf_using(*uris: str) -> bytes:
    """A bare .gltf whose buffers name ``uris`` (so a zip holding it unpacks those entries)."""
    buffers = [{"uri": uri, "byteLength": 1} for uri in uris]
    return json.dumps({"asset": {"version": "2.0"}, "buffers": buffers}).encode()


def zip_with_zeros(folder: Path, size: int, used: bool) -> Path:
    """``folder/asset.zip``: a quad .gltf with its files under ``model/``, and ``size`` zero
    bytes deflated (about 1000:1) as ``model/zeros.bin``. With ``used`` a buffer of the .gltf
    names that entry (URI-encoded: ``zero%73.bin``); otherwise nothing does."""
    src = _quad(folder / "src")
    if used:
        _edit(
            src,
            src,
            lambda doc: doc["buffers"].append({"uri": "zero%73.bin", "byteLength": size}),
        )
    path = folder / "asset.zip"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for p in sorted(src.parent.iterdir()):
            zf.write(p, f"model/{p.name}")
        with zf.open("model/zeros.bin", "w") as out:
            for _ in range(size // 2**20):
                out.write(bytes(2**20))
            out.write(bytes(size % 2**20))
    return path


def hostile_cases(folder: Path) -> list[HostileCase]:
    folder = Path(folder)
    cases: list[HostileCase] = []

    def case(name: str) -> Path:
        d = folder / name
        d.mkdir(parents=True, exist_ok=True)
        return d

    def add(name, path, error, says="", limits=None, unwrap=True):
        cases.append(HostileCase(name, path, error, limits or Limits(), says, unwrap))

    # --- containers and JSON
    d = case("empty")
    (d / "a.glb").write_bytes(b"")
    add("empty", d / "a.glb", InvalidAsset, "empty")

    d = case("random_bytes")
    (d / "a.glb").write_bytes(np.random.default_rng(0).bytes(4096).replace(b"{", b"x"))
    add("random_bytes", d / "a.glb", UnsupportedAsset)

    glb = _quad(case("glb_src"), "glb").read_bytes()
    d = case("truncated_glb")
    (d / "a.glb").write_bytes(glb[: len(glb) // 2])
    add("truncated_glb", d / "a.glb", InvalidAsset, "truncated")

    d = case("glb_chunk_length_lies")
    bad = bytearray(glb)
    bad[12:16] = struct.pack("<I", len(glb) * 4)
    (d / "a.glb").write_bytes(bytes(bad))
    add("glb_chunk_length_lies", d / "a.glb", InvalidAsset, "chunk")

    d = case("glb_bin_chunk_missing")
    json_chunk, _ = _glb_parts(glb)
    body = struct.pack("<II", len(json_chunk), 0x4E4F534A) + json_chunk
    (d / "a.glb").write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)
    add("glb_bin_chunk_missing", d / "a.glb", InvalidAsset, "BIN")

    d = case("glb_json_not_json")
    junk = b"{not json at all" + b" " * 4
    body = struct.pack("<II", len(junk), 0x4E4F534A) + junk
    (d / "a.glb").write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)
    add("glb_json_not_json", d / "a.glb", InvalidAsset, "JSON")

    d = case("glb_version1")
    (d / "a.glb").write_bytes(struct.pack("<4sII", b"glTF", 1, 20) + b"\x00" * 8)
    add("glb_version1", d / "a.glb", UnsupportedAsset, "1.0")

    d = case("gltf_not_json")
    (d / "a.gltf").write_bytes(b'{"asset": {"version": "2.0"},,,')
    add("gltf_not_json", d / "a.gltf", InvalidAsset, "JSON")

    d = case("gltf_1_0")
    (d / "a.gltf").write_text(json.dumps({"asset": {"version": "1.0"}, "meshes": {}}))
    add("gltf_1_0", d / "a.gltf", UnsupportedAsset, "1.0")

    # --- buffers and uris
    src = _quad(case("src"))

    def buffer_uri(name, uri, error=InvalidAsset, says=""):
        d = case(name)
        p = _edit(src, d / "a.gltf", lambda doc: doc["buffers"][0].__setitem__("uri", uri))
        for f in src.parent.glob("*.png"):
            (d / f.name).write_bytes(f.read_bytes())
        add(name, p, error, says)

    buffer_uri("missing_buffer_file", "nothere.bin", says="missing")
    buffer_uri("uri_dotdot", "../src/quad.bin", says="outside")
    buffer_uri("uri_dotdot_encoded", "%2e%2e/src/quad.bin", says="outside")
    buffer_uri("uri_absolute", str((src.parent / "quad.bin").resolve()))
    buffer_uri("uri_file_scheme", "file:///etc/passwd", says="file:///etc/passwd")
    buffer_uri("uri_http", "http://example.com/a.bin", says="http://example.com/a.bin")
    buffer_uri("uri_https", "https://example.com/a.bin", says="https://example.com/a.bin")
    buffer_uri("uri_too_long", "a" * 5000, UnprocessableAsset, says="name is too long")

    d = case("short_buffer")
    (d / "quad.bin").write_bytes((src.parent / "quad.bin").read_bytes()[:10])
    p = _edit(src, d / "a.gltf", lambda doc: None)
    add("short_buffer", p, InvalidAsset, "shorter")

    d = case("data_uri_over_limit")
    payload = base64.b64encode((src.parent / "quad.bin").read_bytes()).decode()
    p = _edit(
        src,
        d / "a.gltf",
        lambda doc: doc["buffers"][0].__setitem__(
            "uri", "data:application/octet-stream;base64," + payload
        ),
    )
    add("data_uri_over_limit", p, LimitExceeded, "data URI", Limits(max_data_uri_bytes=64))

    # --- accessors and geometry
    def edited(name, fn, error=InvalidAsset, says="", limits=None, unwrap=True):
        d = case(name)
        for f in src.parent.iterdir():
            if f.suffix in (".bin", ".png"):
                (d / f.name).write_bytes(f.read_bytes())
        add(name, _edit(src, d / "a.gltf", fn), error, says, limits, unwrap)

    edited(
        "accessor_out_of_range",
        lambda doc: doc["accessors"][0].__setitem__("count", 10**6),
        says="past the end",
    )
    edited(
        "bufferview_out_of_range",
        lambda doc: doc["bufferViews"][0].__setitem__("byteOffset", 10**7),
        says="past the end",
    )
    edited(
        "accessor_missing",
        lambda doc: doc["meshes"][0]["primitives"][0].__setitem__("indices", 99),
        says="accessor 99",
    )

    def bad_indices(name):
        d = case(name)
        doc = json.loads(src.read_text())
        binary = bytearray((src.parent / "quad.bin").read_bytes())
        acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["indices"]]
        bv = doc["bufferViews"][acc["bufferView"]]
        struct.pack_into("<H", binary, bv["byteOffset"] + acc.get("byteOffset", 0), 60000)
        (d / "quad.bin").write_bytes(bytes(binary))
        for f in src.parent.glob("*.png"):
            (d / f.name).write_bytes(f.read_bytes())
        (d / "a.gltf").write_text(json.dumps(doc))
        add(name, d / "a.gltf", InvalidAsset, "index")

    bad_indices("indices_out_of_range")

    d = case("nan_positions")
    doc = json.loads(src.read_text())
    doc["meshes"][0]["name"] = "Broken Teapot"
    binary = bytearray((src.parent / "quad.bin").read_bytes())
    acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
    struct.pack_into(
        "<f", binary, doc["bufferViews"][acc["bufferView"]]["byteOffset"] + 4, float("nan")
    )
    (d / "quad.bin").write_bytes(bytes(binary))
    for f in src.parent.glob("*.png"):
        (d / f.name).write_bytes(f.read_bytes())
    (d / "a.gltf").write_text(json.dumps(doc))
    add("nan_positions", d / "a.gltf", InvalidAsset, "Broken Teapot")

    edited(
        "node_cycle",
        lambda doc: doc["nodes"].__setitem__(0, {"mesh": 0, "children": [0]}),
        says="cycle",
    )
    edited(
        "too_many_triangles", lambda doc: None, LimitExceeded, "triangles", Limits(max_triangles=4)
    )
    edited("texture_too_big", lambda doc: None, LimitExceeded, "limit", Limits(max_texture_dim=4))

    def drop_uv(doc):
        del doc["meshes"][0]["primitives"][0]["attributes"]["TEXCOORD_0"]

    edited("missing_uvs_no_unwrap", drop_uv, UnprocessableAsset, "TEXCOORD_0", unwrap=False)

    # --- images
    d = case("image_not_an_image")
    for f in src.parent.iterdir():
        if f.suffix == ".bin":
            (d / f.name).write_bytes(f.read_bytes())
    (d / "base_color.png").write_bytes(b"this is not a png at all, only text" * 4)
    add(
        "image_not_an_image",
        _edit(src, d / "a.gltf", lambda doc: None),
        InvalidAsset,
        "base_color.png",
    )

    d = case("png_bomb")
    for f in src.parent.iterdir():
        if f.suffix == ".bin":
            (d / f.name).write_bytes(f.read_bytes())
    (d / "base_color.png").write_bytes(png_header_bomb())
    add("png_bomb", _edit(src, d / "a.gltf", lambda doc: None), LimitExceeded, "100000")

    d = case("image_uri_outside")
    for f in src.parent.iterdir():
        if f.suffix == ".bin":
            (d / f.name).write_bytes(f.read_bytes())
    add(
        "image_uri_outside",
        _edit(
            src,
            d / "a.gltf",
            lambda doc: doc["images"][0].__setitem__("uri", "../src/base_color.png"),
        ),
        InvalidAsset,
        "outside",
    )

    # --- compressed geometry (Draco, meshopt): a GLB whose JSON or compressed bytes lie
    draco = draco_variant(_quad(case("draco_src"), "glb"), folder / "draco_src" / "d.glb")
    meshopt = meshopt_variant(_quad(case("meshopt_src"), "glb"), folder / "meshopt_src" / "m.glb")

    def glb_edited(name: str, glb: Path, fn, error, says: str, bin_fn=None) -> None:
        json_chunk, rest = _glb_parts(glb.read_bytes())
        doc = json.loads(json_chunk)
        fn(doc)
        binary = bytearray(rest[8:])
        if bin_fn:
            bin_fn(doc, binary)
        js = json.dumps(doc).encode()
        js += b" " * (-len(js) % 4)
        body = struct.pack("<II", len(js), 0x4E4F534A) + js
        body += struct.pack("<II", len(binary), 0x004E4942) + bytes(binary)
        path = case(name) / "a.glb"
        path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)
        add(name, path, error, says)

    def draco_view(doc) -> dict:
        ext = doc["meshes"][0]["primitives"][0]["extensions"]["KHR_draco_mesh_compression"]
        return doc["bufferViews"][ext["bufferView"]]

    def halve(doc):
        draco_view(doc)["byteLength"] //= 2

    glb_edited("draco_truncated", draco, halve, InvalidAsset, "Draco data cannot be decoded")

    def scramble(doc, binary):
        bv = draco_view(doc)
        start, end = bv["byteOffset"] + 16, bv["byteOffset"] + bv["byteLength"]
        binary[start:end] = np.random.default_rng(1).bytes(end - start)

    glb_edited("draco_scrambled", draco, lambda doc: None, InvalidAsset, "Draco", scramble)

    def not_draco(doc, binary):
        binary[draco_view(doc)["byteOffset"]] = ord("X")

    glb_edited("draco_magic", draco, lambda doc: None, InvalidAsset, "Draco data", not_draco)

    def huge_counts(doc, binary):  # the header declares 2**31 vertices and triangles
        bv = draco_view(doc)
        start = bv["byteOffset"]
        blob = bytes(binary[start : start + bv["byteLength"]])
        assert blob[8] == 1  # edgebreaker: traversal type, vertices, triangles
        pos = 12
        for _ in range(2):
            while blob[pos] & 0x80:
                pos += 1
            pos += 1
        lie = blob[:12] + b"\x80\x80\x80\x80\x08" * 2 + blob[pos:]
        lie += b"\x00" * (-len(lie) % 4)
        binary[start:] = lie + binary[start + bv["byteLength"] :]
        bv["byteLength"] = len(lie)
        doc["buffers"][0]["byteLength"] = len(binary)

    glb_edited("draco_header_lies", draco, lambda doc: None, InvalidAsset, "declares", huge_counts)

    def point_cloud(doc, binary):
        binary[draco_view(doc)["byteOffset"] + 7] = 0

    glb_edited(
        "draco_point_cloud", draco, lambda doc: None, InvalidAsset, "point cloud", point_cloud
    )

    def wrong_id(doc):
        ext = doc["meshes"][0]["primitives"][0]["extensions"]["KHR_draco_mesh_compression"]
        ext["attributes"]["POSITION"] = 99

    glb_edited("draco_attribute_id", draco, wrong_id, InvalidAsset, "no attribute 99")

    def draco_count(doc):
        prim = doc["meshes"][0]["primitives"][0]
        doc["accessors"][prim["attributes"]["POSITION"]]["count"] += 1
        doc["accessors"][prim["attributes"]["NORMAL"]]["count"] += 1
        doc["accessors"][prim["attributes"]["TANGENT"]]["count"] += 1
        doc["accessors"][prim["attributes"]["TEXCOORD_0"]]["count"] += 1

    glb_edited("draco_vertex_count", draco, draco_count, InvalidAsset, "its accessor")

    def position_ext(doc) -> dict:
        acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
        return doc["bufferViews"][acc["bufferView"]]["extensions"]["EXT_meshopt_compression"]

    def stride(doc):
        position_ext(doc)["byteStride"] = 16

    glb_edited("meshopt_stride", meshopt, stride, InvalidAsset, "byteStride")

    def count(doc):
        position_ext(doc)["count"] += 1

    glb_edited("meshopt_count", meshopt, count, InvalidAsset, "byteStride x count")

    def truncated(doc):
        position_ext(doc)["byteLength"] //= 2

    glb_edited("meshopt_truncated", meshopt, truncated, InvalidAsset, "cannot be decoded")

    def short_fallback(doc):
        doc["buffers"][1]["byteLength"] = 8

    glb_edited("meshopt_fallback_short", meshopt, short_fallback, InvalidAsset, "past the end")

    def bomb(doc):  # 4 GiB declared, nothing behind it
        acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
        bv = doc["bufferViews"][acc["bufferView"]]
        ext = bv["extensions"]["EXT_meshopt_compression"]
        ext["count"] = 2**32 // ext["byteStride"]
        bv["byteLength"] = 2**32
        doc["buffers"][1]["byteLength"] = 2**33

    glb_edited("meshopt_bomb", meshopt, bomb, LimitExceeded, "decodes to")
    return cases
