"""Round trips (read, write, read) of procedural assets with every feature, compared field by
field, and the output checked by the Khronos glTF-Validator."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest

from pbrsr_core.asset import load_asset, make_demo_asset, make_test_asset, save_asset
from pbrsr_core.asset.gltf_materials import texture_transform_matrix
from pbrsr_core.asset.gltf_read import buffer_view_bytes
from pbrsr_core.asset.procedural import TEST_FEATURES, make_quad_asset
from pbrsr_core.asset.validator import validate_gltf, validator_available

ALL_GLTF = set(TEST_FEATURES) - {"jpeg"}
CASES = [
    ("glb", None),
    ("gltf", None),
    ("gltf", ALL_GLTF),
    ("glb", set(TEST_FEATURES) - {"data_uri", "exr"}),
    ("glb", {"jpeg", "no_normals", "hierarchy", "strip"}),
    ("gltf", {"data_uri", "png16", "alpha_blend", "camera"}),
]
TOL = {
    "image/png": {8: 0.5 / 255 + 1e-6, 16: 0.5 / 65535 + 1e-6},
    "image/x-exr": {16: 1e-3, 32: 0.0},
    "image/jpeg": {8: 0.08},
}

needs_validator = pytest.mark.usefixtures("gltf_validator")


def _upscaled(px: np.ndarray) -> np.ndarray:
    h, w, c = px.shape
    y = np.linspace(0, 1, 2 * h, dtype=np.float32)[:, None, None]
    x = np.linspace(0, 1, 2 * w, dtype=np.float32)[None, :, None]
    return np.clip(np.repeat(np.repeat(px, 2, 0), 2, 1) * 0.9 + 0.05 * (x + y), 0, 1)


def _strip_replaced(doc: dict, replaced: set[int], kind: str) -> dict:
    doc = copy.deepcopy(doc)
    views = doc.get("bufferViews", [])
    image_views = {doc["images"][i].get("bufferView") for i in replaced}
    for i in replaced:
        doc["images"][i] = None
    if kind == "glb":
        for j, bv in enumerate(views):
            bv.pop("byteOffset", None)
            if j in image_views:
                views[j] = None
        doc["bufferViews"] = [v for v in views if v is not None]
        if doc.get("buffers"):
            doc["buffers"][0].pop("byteLength", None)
    return doc


@pytest.mark.parametrize("kind,features", CASES)
def test_round_trip(tmp_path, kind, features):
    kw = {} if features is None else {"features": features}
    src = make_test_asset(tmp_path / "in" / f"asset.{kind}", size=32, **kw)
    a = load_asset(src)
    replaced = {im.index for im in a.images if im.roles & {"base_color", "normal"}}
    assert replaced
    new = {i: _upscaled(a.images[i].pixels) for i in replaced}
    out = tmp_path / "out" / f"result.{kind}"
    written = save_asset(a, out, new)
    assert written[0] == out and all(p.is_relative_to(out.parent) for p in written)
    b = load_asset(out)

    # JSON: equal except the replaced images (and, in a GLB, their bufferViews and offsets)
    assert _strip_replaced(b.document, replaced, kind) == _strip_replaced(
        a.document, replaced, kind
    )
    # every accessor-carrying bufferView's bytes are identical
    for acc in a.document.get("accessors", []):
        j = acc["bufferView"]
        assert buffer_view_bytes(b.document, b.buffers, j, "") == buffer_view_bytes(
            a.document, a.buffers, j, ""
        )
    # geometry and materials unchanged
    for name in ("v_pos", "v_nrm", "v_tng", "t_pos_idx", "t_mat"):
        assert getattr(a.mesh, name).equal(getattr(b.mesh, name)), name
    assert a.mesh.v_uv.keys() == b.mesh.v_uv.keys()
    assert a.materials == b.materials
    # images: untouched ones identical, replaced ones new size, >= bit depth, within precision
    for ia, ib in zip(a.images, b.images, strict=True):
        assert ia.roles == ib.roles
        if ia.index in replaced:
            assert ib.pixels.shape == new[ia.index].shape
            assert ib.bit_depth >= ia.bit_depth
            tol = TOL[ib.mime][ib.bit_depth]
            assert np.abs(ib.pixels - new[ia.index]).max() <= tol
        else:
            assert ib.mime == ia.mime and ib.bit_depth == ia.bit_depth
            np.testing.assert_array_equal(ib.pixels, ia.pixels)
    if validator_available():
        for path in (src, out):
            report = validate_gltf(path)
            errors = [m for m in report["messages"] if m["severity"] == 0]
            assert report["numErrors"] == 0, errors


@pytest.mark.parametrize(
    "fmt,mime,depth",
    [("png16", "image/png", 16), ("exr", "image/x-exr", 16), ("jpeg", "image/png", 16)],
)
def test_output_formats_never_lose_precision(tmp_path, fmt, mime, depth):
    src = make_test_asset(tmp_path / "a.gltf", size=16, features={"png16"})
    a = load_asset(src)
    mr = a.materials[0].metallic_roughness.image
    assert a.images[mr].bit_depth == 16
    save_asset(a, tmp_path / "o" / "b.gltf", {mr: _upscaled(a.images[mr].pixels)}, fmt)
    b = load_asset(tmp_path / "o" / "b.gltf")
    assert b.images[mr].mime == mime and b.images[mr].bit_depth >= depth


def test_glb_without_changes_keeps_every_byte_of_meaning(tmp_path):
    src = make_test_asset(tmp_path / "a.glb", size=16)
    a = load_asset(src)
    save_asset(a, tmp_path / "b.glb", {})
    b = load_asset(tmp_path / "b.glb")
    assert a.document == b.document
    assert (
        a.buffers[0][: a.document["buffers"][0]["byteLength"]]
        == b.buffers[0][: b.document["buffers"][0]["byteLength"]]
    )


def test_cross_kind_save(tmp_path):
    a = load_asset(make_test_asset(tmp_path / "a.glb", size=16))
    save_asset(a, tmp_path / "x" / "b.gltf", {0: _upscaled(a.images[0].pixels)})
    b = load_asset(tmp_path / "x" / "b.gltf")
    assert b.images[0].width == 32
    for ia, ib in zip(a.images[1:], b.images[1:], strict=True):
        np.testing.assert_array_equal(ia.pixels, ib.pixels)
    assert a.mesh.v_pos.equal(b.mesh.v_pos)


def test_texture_transform_matrix_matches_spec_formula():
    ext = {"offset": [0.25, -0.5], "rotation": 0.3, "scale": [2.0, 1.5]}
    m = np.array(texture_transform_matrix(ext)).reshape(3, 3)
    u, v = 0.3, 0.7
    c, s = math.cos(0.3), math.sin(0.3)
    expect = (2.0 * c * u - 1.5 * s * v + 0.25, 2.0 * s * u + 1.5 * c * v - 0.5)
    np.testing.assert_allclose((m @ [u, v, 1.0])[:2], expect, atol=1e-12)
    assert texture_transform_matrix({}) == (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


def test_hierarchy_transform_and_flat_normals(tmp_path):
    a0 = load_asset(make_test_asset(tmp_path / "a.glb", size=8, features={"texture_transform"}))
    a1 = load_asset(
        make_test_asset(
            tmp_path / "b.glb", size=8, features={"texture_transform", "hierarchy", "no_normals"}
        )
    )
    # root TRS (t, quaternion about y by 45 deg, s) then mid matrix (scale 0.5, t (1, 2, 3))
    p0 = a0.mesh.v_pos.double().numpy()
    p_mid = p0 * 0.5 + [1.0, 2.0, 3.0]
    p_root = p_mid * [1.0, 1.5, 1.0]
    ang = math.pi / 4
    rot = np.array(
        [[math.cos(ang), 0, math.sin(ang)], [0, 1, 0], [-math.sin(ang), 0, math.cos(ang)]]
    )
    expect = p_root @ rot.T + [0.5, 0.0, -0.25]
    p1 = a1.mesh.v_pos.double().numpy()  # flat normals: one vertex per triangle corner
    idx0 = a0.mesh.t_pos_idx.numpy().reshape(-1)
    np.testing.assert_allclose(p1, expect[idx0], atol=1e-5)
    n = a1.mesh.v_nrm.numpy()
    assert np.isfinite(n).all() and np.allclose(np.linalg.norm(n, axis=1), 1, atol=1e-5)
    t = a1.mesh.t_pos_idx.numpy()
    fn = np.cross(p1[t[:, 1]] - p1[t[:, 0]], p1[t[:, 2]] - p1[t[:, 0]])
    big = np.linalg.norm(fn, axis=1) > 1e-9
    assert (np.sum(fn[big] * n[t[big, 0]], axis=1) > 0).all()


def test_demo_and_quad_assets(tmp_path):
    demo = load_asset(make_demo_asset(tmp_path / "demo.glb", size=64))
    assert 2000 < demo.mesh.num_triangles < 10000
    assert {r for im in demo.images for r in im.roles} == {
        "base_color",
        "metallic_roughness",
        "normal",
        "occlusion",
    }
    orm = demo.images[demo.materials[0].metallic_roughness.image].pixels
    assert orm[..., 2].max() == 1.0 and orm[..., 1].std() > 0.1  # some metal, varied roughness
    tng = demo.mesh.v_tng.numpy()
    assert np.isfinite(tng).all() and set(np.unique(tng[:, 3])) <= {-1.0, 1.0}
    quad = load_asset(make_quad_asset(tmp_path / "q.gltf", size=8))
    np.testing.assert_allclose(quad.mesh.v_pos[:, :2].abs().numpy(), 1.0)
    np.testing.assert_allclose(quad.mesh.v_nrm.numpy(), [[0, 0, 1]] * 4)
    if validator_available():
        assert validate_gltf(tmp_path / "demo.glb")["numErrors"] == 0
