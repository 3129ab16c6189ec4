"""Zip extraction safety (only the files the asset uses, compression ratios) and kind
detection by magic bytes."""

from __future__ import annotations

import re
import stat
import struct
import zipfile

import pytest

from pbrsr_bench.fuzz import pack_glb
from pbrsr_core.asset import detect_kind, extract_zip, load_asset
from pbrsr_core.asset.gltf_read import parse_glb
from pbrsr_core.asset.procedural import make_quad_asset, make_test_asset
from pbrsr_core.errors import InvalidAsset, LimitExceeded, UnprocessableAsset, UnsupportedAsset
from pbrsr_core.limits import Limits
from tests.hostile import gltf_using, zip_with_zeros


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


def _files(folder):
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file())


def test_unpacked_bytes_limit(tmp_path):
    z = _zip(tmp_path / "big.zip", {"a.gltf": gltf_using("big.bin"), "big.bin": bytes(4 * 2**20)})
    with pytest.raises(LimitExceeded, match="unpacks"):
        extract_zip(
            z, tmp_path / "out", Limits(max_unpacked_bytes=2**20, max_compression_ratio=1e4)
        )
    assert not (tmp_path / "out").exists()


def test_only_the_files_the_asset_uses_are_unpacked(tmp_path):
    # 64 MiB of zeros nothing references: skipped, even with a 1 MiB unpacked limit
    z = zip_with_zeros(tmp_path, 64 * 2**20, used=False)
    out = tmp_path / "out"
    found = extract_zip(z, out, Limits(max_unpacked_bytes=2**20))
    assert _files(out) == ["model/base_color.png", "model/quad.bin", "model/quad.gltf"]
    assert load_asset(found).images[0].width == 8
    # a model that cannot be parsed uses nothing (loading it says why)
    z = _zip(tmp_path / "bad.zip", {"a.gltf": b"{}", "b.bin": b"x"})
    assert _files(extract_zip(z, tmp_path / "out2").parent) == ["a.gltf"]


def test_a_glb_unpacks_with_the_files_its_json_names(tmp_path):
    doc, bin_chunk = parse_glb(make_quad_asset(tmp_path / "q.glb", size=8).read_bytes())
    doc["images"].append({"uri": "ext%20a.png"})
    z = _zip(
        tmp_path / "a.zip",
        {"m/q.glb": pack_glb(doc, bin_chunk), "m/ext a.png": b"png", "m/junk.bin": b"j"},
    )
    extract_zip(z, tmp_path / "out")
    assert _files(tmp_path / "out") == ["m/ext a.png", "m/q.glb"]


def test_an_entry_over_the_compression_ratio_is_refused_before_unpacking(tmp_path):
    z = zip_with_zeros(tmp_path, 10 * 2**20, used=True)
    with pytest.raises(LimitExceeded) as info:
        extract_zip(z, tmp_path / "out")
    ratio = re.search(
        r"'model/zeros\.bin' unpacks \d+ bytes to 10485760 \((\d+):1\)", info.value.message
    )
    assert ratio and 500 < int(ratio[1]) < 1100, info.value.message
    assert info.value.message.endswith("the limit is 200:1")
    assert not (tmp_path / "out").exists()
    # under a higher limit it unpacks
    found = extract_zip(z, tmp_path / "out2", Limits(max_compression_ratio=2000))
    assert (found.parent / "zeros.bin").stat().st_size == 10 * 2**20


def test_the_zips_size_bounds_what_it_unpacks_whatever_the_entries_claim(tmp_path):
    z = zip_with_zeros(tmp_path, 10 * 2**20, used=True)
    data = bytearray(z.read_bytes())
    cd = data.rfind(b"PK\x01\x02")  # the central directory record of model/zeros.bin (last)
    assert data[cd + 46 : cd + 46 + 15] == b"model/zeros.bin"
    struct.pack_into("<I", data, cd + 20, 10 * 2**20)  # claims to be stored: 1:1
    z.write_bytes(bytes(data))
    with pytest.raises(LimitExceeded, match=r"from a zip of \d+ bytes \(\d+:1\)"):
        extract_zip(z, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_an_entry_name_too_long_for_the_file_system_is_unprocessable(tmp_path):
    z = _zip(tmp_path / "a.zip", {"a.gltf": gltf_using("b" * 5000), "b" * 5000: b"x"})
    with pytest.raises(
        UnprocessableAsset, match=r"\(5000 characters\)' cannot be unpacked: its name"
    ):
        extract_zip(z, tmp_path / "out")


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
