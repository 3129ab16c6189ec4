"""Every hostile input yields its typed error (never a crash, never a read outside)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pbrsr_core.asset import load_asset
from pbrsr_core.asset.procedural import make_quad_asset
from pbrsr_core.errors import UnprocessableAsset
from tests.hostile import hostile_cases


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    return {c.name: c for c in hostile_cases(tmp_path_factory.mktemp("hostile"))}


def test_corpus_is_complete(corpus):
    assert len(corpus) >= 28


def test_every_case_raises_its_typed_error(corpus):
    for case in corpus.values():
        with pytest.raises(case.error) as info:
            load_asset(case.path, case.limits, unwrap_missing_uvs=case.unwrap)
        msg = info.value.message
        assert case.says.lower() in msg.lower(), (case.name, msg)
        assert str(case.path.parent) not in msg, (case.name, msg)  # no server paths


def test_zero_area_triangles_are_kept_finite(tmp_path):
    src = make_quad_asset(tmp_path / "q.gltf", size=8, subdiv=2)
    doc = json.loads(src.read_text())
    binary = bytearray((tmp_path / "q.bin").read_bytes())
    acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
    off = doc["bufferViews"][acc["bufferView"]]["byteOffset"]
    pos = np.frombuffer(binary, np.float32, acc["count"] * 3, off).reshape(-1, 3).copy()
    pos[1] = pos[0]  # collapse an edge: degenerate triangles
    pos[2] = pos[0]
    binary[off : off + pos.nbytes] = pos.tobytes()
    (tmp_path / "q.bin").write_bytes(bytes(binary))
    del doc["meshes"][0]["primitives"][0]["attributes"]["NORMAL"]
    del doc["meshes"][0]["primitives"][0]["attributes"]["TANGENT"]
    src.write_text(json.dumps(doc))
    a = load_asset(src)
    assert a.mesh.num_triangles == 8
    for t in (a.mesh.v_nrm, a.mesh.v_tng):
        assert np.isfinite(t.numpy()).all()
    assert np.allclose(np.linalg.norm(a.mesh.v_nrm.numpy(), axis=1), 1.0, atol=1e-5)


def test_a_uri_that_cannot_be_opened_is_unprocessable(tmp_path):
    src = make_quad_asset(tmp_path / "q.gltf", size=8)
    (tmp_path / "loop.bin").symlink_to("loop.bin")
    doc = json.loads(src.read_text())
    doc["buffers"][0]["uri"] = "loop.bin"
    src.write_text(json.dumps(doc))
    with pytest.raises(UnprocessableAsset, match="'loop.bin', which cannot be opened"):
        load_asset(src)
