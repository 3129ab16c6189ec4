"""Zip extraction safety and kind detection by magic bytes."""

from __future__ import annotations

import stat
import zipfile

import pytest

from pbrsr_core.asset import detect_kind, extract_zip, load_asset
from pbrsr_core.asset.procedural import make_quad_asset, make_test_asset
from pbrsr_core.errors import InvalidAsset, LimitExceeded, UnsupportedAsset
from pbrsr_core.limits import Limits


def _zip(path, entries):
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in entries.items():
            if isinstance(data, zipfile.ZipInfo):
                zf.writestr(data, b"target")
            else:
                zf.writestr(name, data)
    return path


def test_extract_good_zip_and_load(tmp_path):
    src = make_quad_asset(tmp_path / "src" / "q.gltf", size=8)
    entries = {f"model/{p.name}": p.read_bytes() for p in src.parent.iterdir()}
    z = _zip(tmp_path / "a.zip", entries)
    assert detect_kind(z) == "zip"
    found = extract_zip(z, tmp_path / "out", Limits())
    assert found.name == "q.gltf" and found.is_relative_to((tmp_path / "out").resolve())
    assert load_asset(found).images[0].width == 8


@pytest.mark.parametrize(
    "bad",
    ["../evil.gltf", "/abs/evil.gltf", "a/../../evil.gltf", "C:/evil.gltf", "a\\..\\evil.gltf"],
)
def test_unsafe_names(tmp_path, bad):
    z = _zip(tmp_path / "a.zip", {bad: b"{}", "ok.gltf": b"{}"})
    with pytest.raises(InvalidAsset):
        extract_zip(z, tmp_path / "out")
    assert not (tmp_path / "evil.gltf").exists()


def test_symlink_entry_refused(tmp_path):
    info = zipfile.ZipInfo("link.bin")
    info.create_system = 3
    info.external_attr = (stat.S_IFLNK | 0o777) << 16
    z = _zip(tmp_path / "a.zip", {"a.gltf": b"{}", "link.bin": info})
    with pytest.raises(InvalidAsset, match="symlink"):
        extract_zip(z, tmp_path / "out")


def test_zip_bomb_counts_real_bytes(tmp_path):
    z = tmp_path / "bomb.zip"
    with zipfile.ZipFile(z, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("a.gltf", b"{}")
        zf.writestr("big.bin", b"\x00" * (4 * 2**20))
    with pytest.raises(LimitExceeded, match="unpacks"):
        extract_zip(z, tmp_path / "out", Limits(max_unpacked_bytes=2**20))


def test_entry_count_and_model_count(tmp_path):
    z = _zip(tmp_path / "many.zip", {f"f{i}.txt": b"x" for i in range(12)} | {"a.glb": b"g"})
    with pytest.raises(LimitExceeded, match="entries"):
        extract_zip(z, tmp_path / "o1", Limits(max_zip_entries=10))
    z = _zip(tmp_path / "none.zip", {"readme.txt": b"x"})
    with pytest.raises(InvalidAsset, match="no .gltf"):
        extract_zip(z, tmp_path / "o2")
    z = _zip(tmp_path / "two.zip", {"a.gltf": b"{}", "b.glb": b"glTF"})
    with pytest.raises(InvalidAsset, match="several"):
        extract_zip(z, tmp_path / "o3")
    (tmp_path / "notzip.zip").write_bytes(b"PK\x03\x04garbage")
    with pytest.raises(InvalidAsset):
        extract_zip(tmp_path / "notzip.zip", tmp_path / "o4")


def test_detect_kind(tmp_path):
    glb = make_test_asset(tmp_path / "a.glb", size=8, features={"camera"})
    renamed = tmp_path / "looks_like.gltf"
    renamed.write_bytes(glb.read_bytes())
    assert detect_kind(renamed) == "glb"
    (tmp_path / "b.glb").write_text('  {"asset": {"version": "2.0"}}')
    assert detect_kind(tmp_path / "b.glb") == "gltf"
    (tmp_path / "c.glb").write_bytes(b"\x89PNG\r\n\x1a\n")
    with pytest.raises(UnsupportedAsset):
        detect_kind(tmp_path / "c.glb")
    (tmp_path / "d.glb").write_bytes(b"")
    with pytest.raises(InvalidAsset):
        detect_kind(tmp_path / "d.glb")
