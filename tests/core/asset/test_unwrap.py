"""Meshes without the UVs their material needs: unwrapped with xatlas (and saved valid), or
refused when unwrapping is off."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from pbrsr_core.asset import load_asset, make_quad_asset, make_test_asset, save_asset, validate_gltf
from pbrsr_core.asset.gltf_read import parse_glb
from pbrsr_core.asset.procedural import uv_sphere
from pbrsr_core.asset.unwrap import unwrap_triangles
from pbrsr_core.asset.validator import validator_available
from pbrsr_core.errors import UnprocessableAsset

needs_validator = pytest.mark.usefixtures("gltf_validator")


def _drop_texcoords(doc: dict) -> None:
    for mesh in doc["meshes"]:
        for prim in mesh["primitives"]:
            for key in [k for k in prim["attributes"] if k.startswith("TEXCOORD_")]:
                del prim["attributes"][key]


def _rewrite_glb(path, fn) -> None:
    doc, bin_chunk = parse_glb(path.read_bytes())
    fn(doc)
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    body = struct.pack("<II", len(js), 0x4E4F534A) + js
    if bin_chunk is not None:
        body += struct.pack("<II", len(bin_chunk), 0x004E4942) + bin_chunk
    path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)


def _tri_area_uv(uv: np.ndarray, tri: np.ndarray) -> np.ndarray:
    a, b, c = uv[tri[:, 0]], uv[tri[:, 1]], uv[tri[:, 2]]
    e1, e2 = b - a, c - a
    return 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


def test_unwrap_triangles_is_a_valid_atlas():
    pos, _, _, tri = uv_sphere(8, 16)
    un = unwrap_triangles(pos, tri)
    uv = un.uvs[0]
    # same triangles, same order, through the vertex mapping
    assert np.array_equal(un.vmapping[un.indices], tri)
    assert np.array_equal(un.vmapping.shape[0], uv.shape[0])
    assert np.isfinite(uv).all() and uv.min() >= 0 and uv.max() <= 1
    # every non-degenerate 3D triangle gets a non-degenerate UV triangle
    p = pos[tri]
    area3 = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    area_uv = _tri_area_uv(uv, un.indices)
    assert (area_uv[area3 > 1e-6] > 0).all()
    # charts do not overlap: rasterised triangle coverage adds up to at most one per cell
    n = 256
    cover = np.zeros((n, n), np.int32)
    ys, xs = np.mgrid[0:n, 0:n]
    q = np.stack([(xs + 0.5) / n, (ys + 0.5) / n], -1).reshape(-1, 2)
    for t in un.indices:
        a, b, c = uv[t]
        d = (b[1] - c[1]) * (a[0] - c[0]) + (c[0] - b[0]) * (a[1] - c[1])
        if abs(d) < 1e-12:
            continue
        w0 = ((b[1] - c[1]) * (q[:, 0] - c[0]) + (c[0] - b[0]) * (q[:, 1] - c[1])) / d
        w1 = ((c[1] - a[1]) * (q[:, 0] - c[0]) + (a[0] - c[0]) * (q[:, 1] - c[1])) / d
        inside = (w0 > 1e-4) & (w1 > 1e-4) & (1 - w0 - w1 > 1e-4)
        cover.reshape(-1)[inside] += 1
    assert cover.max() == 1
    assert (cover > 0).mean() > 0.3  # a packed atlas, not a few specks


def test_unwrap_is_scale_invariant_and_keeps_degenerate_triangles():
    pos, _, _, tri = uv_sphere(6, 12)
    tri = np.concatenate([tri, [[0, 0, 0], [1, 2, 2]]])
    small = unwrap_triangles(pos * 1e-4, tri)
    big = unwrap_triangles(pos * 1e4, tri)
    for un in (small, big):
        assert un.indices.shape == tri.shape
        assert np.array_equal(un.vmapping[un.indices], tri)
        assert np.isfinite(un.uvs[0]).all()
    assert np.allclose(small.uvs[0], big.uvs[0], atol=1e-4)


def test_refused_when_unwrapping_is_off(tmp_path):
    src = make_quad_asset(tmp_path / "q.gltf", size=8, subdiv=2)
    doc = json.loads(src.read_text())
    _drop_texcoords(doc)
    src.write_text(json.dumps(doc))
    with pytest.raises(UnprocessableAsset, match="TEXCOORD_0"):
        load_asset(src, unwrap_missing_uvs=False)


@pytest.mark.parametrize("out_kind", ["glb", "gltf"])
def test_quad_without_uvs_is_unwrapped_and_saved_valid(tmp_path, out_kind):
    src = make_quad_asset(tmp_path / "q.gltf", size=8, subdiv=3)
    doc = json.loads(src.read_text())
    _drop_texcoords(doc)
    src.write_text(json.dumps(doc))
    a = load_asset(src, unwrap_missing_uvs=True)
    assert list(a.generated_uvs) == [(0, 0)]
    uv = a.mesh.v_uv[0].numpy()
    tri = a.mesh.t_pos_idx.numpy()
    assert uv.shape[0] == a.mesh.v_pos.shape[0]
    assert (_tri_area_uv(uv, tri) > 0).all()
    assert a.mesh.num_triangles == 18
    for t in (a.mesh.v_nrm, a.mesh.v_tng):
        assert np.isfinite(t.numpy()).all()
    # the quad is flat: tangents generated from the atlas lie in its plane (z = 0)
    assert np.allclose(a.mesh.v_tng.numpy()[:, 2], 0.0, atol=1e-5)

    out = tmp_path / "out" / f"q.{out_kind}"
    new = {0: np.full((16, 16, 3), 0.5, np.float32)}
    save_asset(a, out, new)
    b = load_asset(out, unwrap_missing_uvs=False)  # the output has its UVs now
    assert b.generated_uvs == {}
    assert np.allclose(b.mesh.v_uv[0].numpy(), uv, atol=1e-6)
    assert np.allclose(b.mesh.v_pos.numpy(), a.mesh.v_pos.numpy())
    assert np.array_equal(b.mesh.t_pos_idx.numpy(), tri)
    assert b.images[0].width == 16
    if validator_available():
        report = validate_gltf(out)
        assert report["numErrors"] == 0, report["messages"][:5]


@needs_validator
def test_rich_asset_without_uvs_round_trips_valid(tmp_path):
    """Every primitive of the feature-rich test asset (strip, skin, texcoord1 material,
    tangents, morph-free animation) loses its UVs; a GLB source, saved as GLB."""
    src = make_test_asset(tmp_path / "t.glb", size=16)
    _rewrite_glb(src, _drop_texcoords)
    with pytest.raises(UnprocessableAsset):
        load_asset(src, unwrap_missing_uvs=False)
    a = load_asset(src)
    assert a.generated_uvs
    for key, un in a.generated_uvs.items():
        assert 0 in un.uvs, key  # sets stay contiguous from TEXCOORD_0
    out = tmp_path / "out" / "t.glb"
    save_asset(a, out)
    report = validate_gltf(out)
    assert report["numErrors"] == 0, [m for m in report["messages"] if m["severity"] == 0][:5]
    b = load_asset(out, unwrap_missing_uvs=False)
    assert b.mesh.num_triangles == a.mesh.num_triangles
    for n, uv in a.mesh.v_uv.items():
        assert np.allclose(b.mesh.v_uv[n].numpy(), uv.numpy(), atol=1e-6)
    assert np.allclose(b.mesh.v_pos.numpy(), a.mesh.v_pos.numpy(), atol=1e-5)
