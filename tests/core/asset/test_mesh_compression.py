"""Compressed geometry: Draco (KHR_draco_mesh_compression) and meshopt (EXT_meshopt_compression)
assets made from procedural ones with DracoPy and meshopt, read within each codec's
quantisation, rendered like the plain asset, and upscaled into assets that keep the compressed
bytes and the required extensions; KHR_mesh_quantization's normalized integers read right.
(Payloads that lie are in the hostile corpus, tests/hostile.py.)"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from pbrsr_bench.variants import DRACO_BITS, draco_variant, meshopt_variant
from pbrsr_core.asset import load_asset, make_test_asset, save_asset
from pbrsr_core.asset.gltf_build import ELEMENT_ARRAY_BUFFER, GltfBuilder
from pbrsr_core.asset.gltf_read import buffer_view_bytes, read_accessor
from pbrsr_core.asset.mesh_codecs import DRACO, MESHOPT, draco_primitives, meshopt_view
from pbrsr_core.asset.model import Asset
from pbrsr_core.asset.procedural import _pattern, grid_quad
from pbrsr_core.asset.validator import validate_gltf, validator_available
from pbrsr_core.metrics import eval_cameras, psnr
from pbrsr_core.options import UpscaleOptions
from pbrsr_core.pipeline import upscale_asset
from pbrsr_core.scene import asset_textures, make_scene, procedural_light, render_views

needs_validator = pytest.mark.usefixtures("gltf_validator")


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("compressed")
    src = make_test_asset(d / "src.glb", size=32)
    return {
        "src": src,
        "draco": draco_variant(src, d / "draco.glb"),
        "meshopt": meshopt_variant(src, d / "meshopt.glb"),
        "exact": meshopt_variant(src, d / "exact.glb", filters=False),
    }


def _accessor(asset: Asset, index: int) -> np.ndarray:
    g = asset.geometry
    bufs = g.buffers if g else asset.buffers
    return read_accessor(asset.document, bufs, index, decoded=g.accessors if g else None)


def _prim(asset: Asset, mesh: int = 0, prim: int = 0) -> dict[str, np.ndarray]:
    p = asset.document["meshes"][mesh]["primitives"][prim]
    out = {k: _accessor(asset, a) for k, a in p["attributes"].items()}
    out["indices"] = _accessor(asset, p["indices"])[:, 0]
    return out


def _renders(asset: Asset) -> list[np.ndarray]:
    scene = make_scene(asset, torch.device("cpu"))
    images, _ = render_views(
        scene, asset_textures(asset, scene.device), eval_cameras(96, 6), procedural_light()
    )
    return [im.numpy() for im in images]


def test_meshopt_without_filters_reads_the_geometry_bit_exact(files):
    a, b = load_asset(files["src"]), load_asset(files["exact"])
    assert b.document["extensionsRequired"] == [MESHOPT]
    fallback = b.document["buffers"][1]
    assert "uri" not in fallback and fallback["extensions"][MESHOPT] == {"fallback": True}
    assert b.geometry is not None and not b.geometry.accessors
    for name in ("v_pos", "v_nrm", "v_tng", "t_pos_idx", "t_mat"):
        assert torch.equal(getattr(a.mesh, name), getattr(b.mesh, name)), name
    assert a.mesh.v_uv.keys() == b.mesh.v_uv.keys()
    assert all(torch.equal(a.mesh.v_uv[k], b.mesh.v_uv[k]) for k in a.mesh.v_uv)


def test_meshopt_filters_read_within_their_quantisation(files):
    a, b = load_asset(files["src"]), load_asset(files["meshopt"])
    assert b.document["extensionsRequired"] == [MESHOPT, "KHR_mesh_quantization"]
    filters = {
        meshopt_view(bv).get("filter", "NONE")
        for bv in b.document["bufferViews"]
        if meshopt_view(bv)
    }
    modes = {meshopt_view(bv)["mode"] for bv in b.document["bufferViews"] if meshopt_view(bv)}
    assert filters == {"NONE", "OCTAHEDRAL", "EXPONENTIAL", "QUATERNION"}
    assert modes == {"ATTRIBUTES", "TRIANGLES"}
    pa, pb = _prim(a), _prim(b)
    # normals and tangents: 8-bit octahedral, stored as normalized bytes (KHR_mesh_quantization)
    acc = b.document["accessors"][b.document["meshes"][0]["primitives"][0]["attributes"]["NORMAL"]]
    assert acc["componentType"] == 5120 and acc["normalized"]
    assert np.array_equal(pa["indices"], pb["indices"])
    pos_tol = np.abs(pa["POSITION"]).max() * 2.0**-15
    assert np.abs(pa["POSITION"] - pb["POSITION"]).max() <= pos_tol
    assert np.abs(pa["TEXCOORD_0"] - pb["TEXCOORD_0"]).max() <= 2.0**-15
    assert np.abs(pa["NORMAL"] - pb["NORMAL"]).max() < 0.03
    assert np.abs(pa["TANGENT"][:, :3] - pb["TANGENT"][:, :3]).max() < 0.03
    assert np.array_equal(np.sign(pa["TANGENT"][:, 3]), np.sign(pb["TANGENT"][:, 3]))
    # the animation's rotations: 16-bit QUATERNION filter
    out = b.document["animations"][0]["samplers"][0]["output"]
    assert b.document["accessors"][out]["componentType"] == 5122
    assert np.abs(_accessor(a, out) - _accessor(b, out)).max() < 1e-4
    # the merged mesh the renderer gets
    assert torch.equal(a.mesh.t_pos_idx, b.mesh.t_pos_idx)
    assert (a.mesh.v_pos - b.mesh.v_pos).abs().max() < 1e-3


def test_draco_reads_the_geometry_within_its_quantisation(files):
    a, b = load_asset(files["src"]), load_asset(files["draco"])
    assert b.document["extensionsRequired"] == [DRACO]
    assert [(mi, pi) for mi, pi, _, _ in draco_primitives(b.document)] == [(0, 0)]
    pa, pb = _prim(a), _prim(b)
    assert pb["indices"].shape == pa["indices"].shape
    span = np.ptp(pa["POSITION"], axis=0).max()
    uv_span = max(np.ptp(pa["TEXCOORD_0"], axis=0).max(), 1.0)
    pos_tol = span / (2 ** DRACO_BITS["POSITION"] - 1)
    uv_tol = uv_span / (2 ** DRACO_BITS["TEXCOORD"] - 1)
    # Draco reorders (and merges equal) vertices: match each to its source by position and UVs
    keys = ("POSITION", "TEXCOORD_0", "TEXCOORD_1")
    feats_a = np.concatenate([pa[k] for k in keys], axis=1)
    feats_b = np.concatenate([pb[k] for k in keys], axis=1)
    _, nearest = cKDTree(feats_a).query(feats_b)
    assert np.abs(pb["POSITION"] - pa["POSITION"][nearest]).max() <= pos_tol
    assert np.abs(pb["TEXCOORD_0"] - pa["TEXCOORD_0"][nearest]).max() <= uv_tol
    assert np.abs(pb["TEXCOORD_1"] - pa["TEXCOORD_1"][nearest]).max() <= 1e-6  # float generic
    assert np.abs(pb["NORMAL"] - pa["NORMAL"][nearest]).max() < 0.01
    assert np.abs(pb["TANGENT"] - pa["TANGENT"][nearest]).max() < 1e-6
    # the same triangles, winding kept (vertices equal in every attribute count as one)
    _, canon = np.unique(np.round(feats_a, 5), axis=0, return_inverse=True)

    def triangles(idx: np.ndarray, to_src: np.ndarray) -> list[tuple]:
        tri = canon.reshape(-1)[to_src[idx.reshape(-1, 3)]]
        rolled = [tuple(np.roll(t, -int(np.argmin(t)))) for t in tri]
        return sorted(rolled)

    assert triangles(pb["indices"], nearest) == triangles(pa["indices"], np.arange(len(feats_a)))


@pytest.mark.parametrize("kind", ["draco", "meshopt"])
def test_compressed_assets_render_like_the_plain_asset(files, kind):
    plain, compressed = _renders(load_asset(files["src"])), _renders(load_asset(files[kind]))
    for p, c in zip(plain, compressed, strict=True):
        assert psnr(c, p) > 35.0, kind


@pytest.mark.parametrize("kind", ["draco", "meshopt"])
def test_upscaled_asset_keeps_the_compressed_bytes(files, kind, tmp_path):
    src = files[kind]
    upscale_asset(src, tmp_path / "out", UpscaleOptions(scale=2, method="bicubic"))
    out_path = tmp_path / "out" / src.name
    a, b = load_asset(src), load_asset(out_path)
    assert b.document["extensionsRequired"] == a.document["extensionsRequired"]
    assert b.document["extensionsUsed"] == a.document["extensionsUsed"]
    for im in a.images:  # textures upscaled
        assert (b.images[im.index].width, b.images[im.index].height) == (
            2 * im.width,
            2 * im.height,
        )
    # the images moved in the BIN chunk; the compressed bytes came along unchanged
    if kind == "draco":
        for (_, _, _, ea), (_, _, _, eb) in zip(
            draco_primitives(a.document), draco_primitives(b.document), strict=True
        ):
            assert ea["attributes"] == eb["attributes"]
            da = buffer_view_bytes(a.document, a.buffers, ea["bufferView"], "")
            db = buffer_view_bytes(b.document, b.buffers, eb["bufferView"], "")
            assert db == da and db.startswith(b"DRACO")
    else:
        pairs = [
            (meshopt_view(va), meshopt_view(vb), vb)
            for va, vb in zip(a.document["bufferViews"], b.document["bufferViews"], strict=False)
            if meshopt_view(va)
        ]
        assert len(pairs) == sum(bool(meshopt_view(v)) for v in b.document["bufferViews"])
        for ea, eb, vb in pairs:
            assert eb["byteOffset"] % 4 == 0 and vb["buffer"] == 1
            assert {k: v for k, v in ea.items() if k != "byteOffset"} == {
                k: v for k, v in eb.items() if k != "byteOffset"
            }
            old = a.buffers[0][ea["byteOffset"] : ea["byteOffset"] + ea["byteLength"]]
            assert b.buffers[0][eb["byteOffset"] : eb["byteOffset"] + eb["byteLength"]] == old
        assert "uri" not in b.document["buffers"][1]
    # so the geometry decodes to the very same values
    for name in ("v_pos", "v_nrm", "v_tng", "t_pos_idx"):
        assert torch.equal(getattr(a.mesh, name), getattr(b.mesh, name)), name
    assert all(torch.equal(a.mesh.v_uv[k], b.mesh.v_uv[k]) for k in a.mesh.v_uv)
    if validator_available():
        report = validate_gltf(out_path)
        assert report["numErrors"] == 0, report["messages"][:5]


def test_meshopt_glb_saved_as_gltf_keeps_its_fallback_buffer_without_a_uri(files, tmp_path):
    a = load_asset(files["meshopt"])
    new = {im.index: np.repeat(np.repeat(im.pixels, 2, 0), 2, 1) for im in a.images}
    written = save_asset(a, tmp_path / "m.gltf", new)
    doc = json.loads(written[0].read_text())
    assert "uri" not in doc["buffers"][1] and "uri" in doc["buffers"][0]
    assert sorted(p.name for p in tmp_path.glob("*.bin")) == ["m.bin"]
    b = load_asset(written[0])
    assert torch.equal(a.mesh.v_pos, b.mesh.v_pos) and torch.equal(a.mesh.v_nrm, b.mesh.v_nrm)
    # and back to a GLB: a BIN buffer goes first, the meshopt ranges' buffer indices shift too
    glb = save_asset(b, tmp_path / "again" / "m.glb", new)[0]
    c = load_asset(glb)
    assert [("uri" in buf) for buf in c.document["buffers"]] == [False, True, False]
    assert all(
        e["buffer"] == 1 for v in c.document["bufferViews"] if (e := meshopt_view(v)) is not None
    )
    assert torch.equal(a.mesh.v_pos, c.mesh.v_pos) and torch.equal(a.mesh.v_tng, c.mesh.v_tng)
    if validator_available():
        assert validate_gltf(written[0])["numErrors"] == 0
        assert validate_gltf(glb)["numErrors"] == 0


def test_draco_primitive_without_uvs_is_unwrapped_and_stored_uncompressed(files, tmp_path):
    src = make_test_asset(tmp_path / "s.gltf", size=16, features={"no_normals"})
    doc = json.loads(src.read_text())
    del doc["meshes"][0]["primitives"][0]["attributes"]["TEXCOORD_0"]
    src.write_text(json.dumps(doc))
    draco = draco_variant(src, tmp_path / "d.glb")
    a = load_asset(draco)
    assert a.generated_uvs and draco_primitives(a.document)
    pixels = {im.index: im.pixels for im in a.images}
    out = save_asset(a, tmp_path / "out.glb", pixels)[0]
    b = load_asset(out)
    assert not draco_primitives(b.document)
    assert DRACO not in b.document.get("extensionsRequired", [])
    assert not b.generated_uvs and 0 in b.mesh.v_uv
    assert torch.allclose(torch.sort(a.mesh.v_pos, 0)[0], torch.sort(b.mesh.v_pos, 0)[0])
    if validator_available():
        assert validate_gltf(out)["numErrors"] == 0


@needs_validator
def test_mesh_quantization_reads_normalized_integers(tmp_path):
    pos, nrm, uv, tri = grid_quad(2, 1.0)
    b = GltfBuilder()
    img = b.texture(b.image(_pattern(16, 1), name="base"))
    m = b.add("materials", {"pbrMetallicRoughness": {"baseColorTexture": {"index": img}}})
    q_pos = np.round(pos * 1000).astype(np.int16)  # node scale 1/1000
    q_nrm = np.round(nrm * 127).astype(np.int8)
    q_uv = np.round(uv * 65535).astype(np.uint16)
    tng = np.tile(np.array([1.0, 0.0, 0.0, -1.0]), (len(pos), 1))
    q_tng = np.round(tng * 127).astype(np.int8)
    # 4-byte aligned rows, as the extension requires: VEC3 bytes/shorts padded to 4/8 bytes
    pos_rows = np.zeros((len(pos), 4), np.int16)
    pos_rows[:, :3] = q_pos
    nrm_rows = np.zeros((len(pos), 4), np.int8)
    nrm_rows[:, :3] = q_nrm

    def acc(rows: np.ndarray, ctype: int, atype: str, stride=None, normalized=False, **kw):
        view = b.view(rows.tobytes(), 34962, stride)
        a = {"bufferView": view, "componentType": ctype, "count": len(pos), "type": atype, **kw}
        if normalized:
            a["normalized"] = True
        return b.add("accessors", a)

    attrs = {
        "POSITION": acc(
            pos_rows, 5122, "VEC3", 8, min=q_pos.min(0).tolist(), max=q_pos.max(0).tolist()
        ),
        "NORMAL": acc(nrm_rows, 5120, "VEC3", 4, normalized=True),
        "TEXCOORD_0": acc(q_uv, 5123, "VEC2", normalized=True),
        "TANGENT": acc(q_tng, 5120, "VEC4", normalized=True),
    }
    indices = b.accessor(tri.reshape(-1).astype(np.uint16), target=ELEMENT_ARRAY_BUFFER)
    mesh = b.add(
        "meshes", {"primitives": [{"attributes": attrs, "indices": indices, "material": m}]}
    )
    b.doc["nodes"] = [{"mesh": mesh, "scale": [1e-3, 1e-3, 1e-3]}]
    b.doc["scenes"] = [{"nodes": [0]}]
    b.use_extension("KHR_mesh_quantization")
    b.doc["extensionsRequired"] = ["KHR_mesh_quantization"]
    path = b.write(tmp_path / "q.glb", kind="glb")
    assert validate_gltf(path)["numErrors"] == 0
    a = load_asset(path)
    assert np.allclose(a.mesh.v_pos.numpy(), pos, atol=1e-6)
    assert np.allclose(a.mesh.v_nrm.numpy(), nrm, atol=1e-6)
    assert np.allclose(a.mesh.v_uv[0].numpy(), uv, atol=0.5 / 65535)
    assert np.allclose(a.mesh.v_tng.numpy(), tng, atol=1e-6)
    upscale_asset(path, tmp_path / "out", UpscaleOptions(scale=2, method="bicubic"))
    out = load_asset(tmp_path / "out" / "q.glb")
    assert out.document["extensionsRequired"] == ["KHR_mesh_quantization"]
    assert out.document["accessors"][:4] == a.document["accessors"][:4]
    assert torch.equal(out.mesh.v_pos, a.mesh.v_pos) and torch.equal(
        out.mesh.v_uv[0], a.mesh.v_uv[0]
    )
    assert validate_gltf(tmp_path / "out" / "q.glb")["numErrors"] == 0


def test_an_image_in_a_meshopt_view_is_decoded(files, tmp_path):
    import meshopt

    glb = files["exact"].read_bytes()
    jlen = int.from_bytes(glb[12:16], "little")
    doc = json.loads(glb[20 : 20 + jlen])
    binary = bytearray(glb[28 + jlen :])
    view = doc["bufferViews"][doc["images"][0]["bufferView"]]
    data = bytes(binary[view["byteOffset"] : view["byteOffset"] + view["byteLength"]])
    data += b"\x00" * (-len(data) % 4)  # PNG readers stop at IEND
    blob = meshopt.encode_gltf_buffer(np.frombuffer(data, np.uint8).reshape(-1, 4), "ATTRIBUTES")
    binary += b"\x00" * (-len(binary) % 4)
    fallback = doc["buffers"][1]
    view.update(buffer=1, byteOffset=fallback["byteLength"], byteLength=len(data))
    fallback["byteLength"] += len(data)
    ext = {"buffer": 0, "byteOffset": len(binary), "byteLength": len(blob), "byteStride": 4}
    view["extensions"] = {MESHOPT: {**ext, "count": len(data) // 4, "mode": "ATTRIBUTES"}}
    binary += blob + b"\x00" * (-len(blob) % 4)
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    body = len(js).to_bytes(4, "little") + b"JSON" + js
    body += len(binary).to_bytes(4, "little") + b"BIN\x00" + bytes(binary)
    path = tmp_path / "img.glb"
    path.write_bytes(
        b"glTF" + (2).to_bytes(4, "little") + (12 + len(body)).to_bytes(4, "little") + body
    )
    a, b = load_asset(files["exact"]), load_asset(path)
    assert np.array_equal(a.images[0].pixels, b.images[0].pixels)


def test_a_fallback_buffer_first_in_a_gltf_goes_last_in_a_glb(files, tmp_path):
    a = load_asset(files["meshopt"])
    gltf = save_asset(a, tmp_path / "g" / "m.gltf")[0]
    doc = json.loads(gltf.read_text())
    doc["buffers"].reverse()  # the fallback buffer (no uri) first
    for bv in doc["bufferViews"]:
        for holder in (bv, meshopt_view(bv) or {}):
            if "buffer" in holder:
                holder["buffer"] = 1 - holder["buffer"]
    gltf.write_text(json.dumps(doc))
    glb = save_asset(load_asset(gltf), tmp_path / "o" / "m.glb")[0]  # no image replaced
    b = load_asset(glb)
    assert [("uri" in buf) for buf in b.document["buffers"]] == [True, False]
    assert torch.equal(a.mesh.v_pos, b.mesh.v_pos) and torch.equal(a.mesh.v_nrm, b.mesh.v_nrm)
    if validator_available():
        assert validate_gltf(glb)["numErrors"] == 0


def test_draco_integer_attributes_read_through_their_normalized_accessors(tmp_path):
    import DracoPy

    pos, _, uv, tri = grid_quad(2, 1.0)
    q_uv = np.round(uv * 65535).astype(np.uint16)  # KHR_mesh_quantization texture coordinates
    blob = DracoPy.encode(
        pos.astype(np.float32),
        tri.astype(np.uint32),
        preserve_order=True,
        generic_attributes={7: q_uv},
    )
    points = DracoPy.decode(blob)
    pid = next(a["unique_id"] for a in points.attributes if a["attribute_type"] == 0)
    b = GltfBuilder()
    img = b.texture(b.image(_pattern(16, 1), name="base"))
    m = b.add("materials", {"pbrMetallicRoughness": {"baseColorTexture": {"index": img}}})
    n = len(points.points)
    bounds = {"min": pos.min(0).tolist(), "max": pos.max(0).tolist()}
    attrs = {
        "POSITION": b.add(
            "accessors", {"componentType": 5126, "count": n, "type": "VEC3", **bounds}
        ),
        "TEXCOORD_0": b.add(
            "accessors", {"componentType": 5123, "normalized": True, "count": n, "type": "VEC2"}
        ),
    }
    indices = b.add("accessors", {"componentType": 5123, "count": tri.size, "type": "SCALAR"})
    ext = {"bufferView": b.view(bytes(blob)), "attributes": {"POSITION": pid, "TEXCOORD_0": 7}}
    prim = {"attributes": attrs, "indices": indices, "material": m, "extensions": {DRACO: ext}}
    b.doc["nodes"] = [{"mesh": b.add("meshes", {"primitives": [prim]})}]
    b.doc["scenes"] = [{"nodes": [0]}]
    for name in (DRACO, "KHR_mesh_quantization"):
        b.use_extension(name)
    b.doc["extensionsRequired"] = [DRACO, "KHR_mesh_quantization"]
    path = b.write(tmp_path / "q.glb", kind="glb")
    a = load_asset(path)
    assert a.geometry.accessors[attrs["TEXCOORD_0"]].dtype == np.uint16
    corners = tri.reshape(-1)  # no NORMAL: flat normals, one vertex per triangle corner
    assert np.allclose(a.mesh.v_uv[0].numpy(), uv[corners], atol=0.5 / 65535 + 1e-7)
    assert np.abs(a.mesh.v_pos.numpy() - pos[corners]).max() <= 2.0 / (2**14 - 1)
    if validator_available():
        assert validate_gltf(path)["numErrors"] == 0
