"""Fuzzing the asset reader, writer and zip extraction: only pbrsr's typed errors come out.

A small run of `pbrsr bench fuzz`, a hypothesis-driven run of the same mutators (shrinking
on failure), and regression tests for every escape the fuzzer found.
"""

from __future__ import annotations

import io
import json
import os
import signal
import struct
import tempfile
import zipfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pbrsr_bench.fuzz import (
    FUZZ_LIMITS,
    make_case,
    make_seeds,
    mutate_bytes,
    pack_glb,
    run,
    run_case,
)
from pbrsr_core.asset import extract_zip, load_asset, make_quad_asset
from pbrsr_core.asset.gltf_read import parse_glb
from pbrsr_core.errors import InvalidAsset, UnsupportedAsset
from tests.hostile import gltf_using

_SEEDS: list = []


def seeds():
    if not _SEEDS:
        _SEEDS.extend(make_seeds(Path(tempfile.mkdtemp(prefix="pbrsr-fuzz-seeds-"))))
    return _SEEDS


class HypothesisDraw:
    """The mutators' Draw interface backed by hypothesis' ``st.data()``."""

    def __init__(self, data):
        self.data = data

    def int(self, lo: int, hi: int) -> int:
        return self.data.draw(st.integers(lo, hi)) if hi > lo else lo


def test_bench_fuzz_small_run(tmp_path):
    result = run(cases=160, seed=11, out_dir=tmp_path)
    assert result["escapes"] == [], result["escapes"][:3]
    assert sum(result["outcomes"].values()) == 160
    # the mutations reach both sides: some cases still load (and save), most are refused
    assert result["outcomes"].get("ok-saved", 0) > 0
    assert result["outcomes"].get("InvalidAsset", 0) > 50
    assert len(result["by_seed"]) == len(seeds())
    assert result["cases_per_s"] > 0
    saved = json.loads((tmp_path / "fuzz.json").read_text())
    assert saved["cases"] == 160
    assert (tmp_path / "fuzz.png").stat().st_size > 1000


def _broken_reader(path, limits=None, **kw):
    raise KeyError("boom")


def _memory_bomb(path, limits=None, **kw):
    """A reader that allocates 3 GiB for any asset: past the case process's cap."""
    return bytearray(3 * 2**30)


def _killer(path, limits=None, **kw):
    if path.suffix == ".gltf":
        os.kill(os.getpid(), signal.SIGKILL)
    raise InvalidAsset("refused")


def test_an_escape_is_reported_with_its_reproducer(tmp_path):
    """The bench is able to fail: a reader that raises a non-pbrsr error is caught."""
    result = run(cases=6, seed=0, out_dir=tmp_path, load=_broken_reader)
    glb_or_gltf = [e for e in result["escapes"] if e["error"].startswith("KeyError")]
    assert glb_or_gltf
    d = Path(glb_or_gltf[0]["path"])
    assert (d / "finding.json").is_file()
    assert any(p.suffix in (".glb", ".gltf", ".zip") for p in d.iterdir())


def test_an_allocation_past_the_cap_is_a_finding_not_a_dead_run(tmp_path):
    result = run(cases=3, seed=0, out_dir=tmp_path, memory_cap_mib=2048, load=_memory_bomb)
    assert sum(result["outcomes"].values()) == 3  # every case ran
    bombs = [e for e in result["escapes"] if e["error"].startswith("MemoryError")]
    assert bombs and all(Path(e["path"], "finding.json").is_file() for e in bombs)
    assert result["peak_rss_mib"] < 2048


def test_a_killed_case_process_is_a_finding_and_the_run_goes_on(tmp_path):
    # seeds cycle quad.glb, rich.glb, datauri.gltf, external.gltf, external.zip
    result = run(cases=5, seed=0, out_dir=tmp_path, load=_killer)
    crashed = sorted(e["index"] for e in result["escapes"])
    assert result["outcomes"]["ESCAPE crash"] == len(crashed) >= 2
    assert 0 not in crashed and 1 not in crashed  # GLB cases: refused, the process lives on
    assert {2, 3} <= set(crashed)  # the two .gltf seeds reach the reader and kill it
    assert result["outcomes"].get("InvalidAsset", 0) >= 1
    assert all("signal 9" in e["error"] for e in result["escapes"])


def test_start_replays_one_case(tmp_path):
    """``--start I --cases 1`` runs case I of the seed alone, as the whole run made it: case
    7321 of seed 23 named texture coordinate set 2**53 + 1, which grew the reader's memory
    without bound."""
    result = run(cases=1, seed=23, start=7321, out_dir=tmp_path)
    assert result["escapes"] == []
    assert result["outcomes"] == {"UnsupportedAsset": 1}
    assert result["start"] == 7321


@settings(
    max_examples=150,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(data=st.data())
def test_mutated_assets_raise_only_typed_errors(data):
    seed = seeds()[data.draw(st.integers(0, len(seeds()) - 1))]
    case = make_case(seed, HypothesisDraw(data))
    with tempfile.TemporaryDirectory(prefix="pbrsr-fuzz-case-") as tmp:
        outcome = run_case(case, Path(tmp) / "case")
        assert sorted(p.name for p in Path(tmp).iterdir()) == ["case"]  # nothing outside
    assert outcome == "ok-saved" or outcome in {
        "InvalidAsset",
        "UnsupportedAsset",
        "LimitExceeded",
        "UnprocessableAsset",
    }


@pytest.mark.parametrize("offset", [8, 12, 16, "bin_len", "bin_type"])
@pytest.mark.parametrize("value", [0, 1, 0x7FFFFFFF, 0xFFFFFFFF, 13])
def test_glb_length_lies(tmp_path, offset, value):
    src = make_quad_asset(tmp_path / "q.glb", size=8)
    b = bytearray(src.read_bytes())
    jlen = struct.unpack_from("<I", b, 12)[0]
    off = {"bin_len": 20 + jlen, "bin_type": 24 + jlen}.get(offset, offset)
    struct.pack_into("<I", b, off, value)
    src.write_bytes(bytes(b))
    with pytest.raises(InvalidAsset):
        load_asset(src, FUZZ_LIMITS)


def test_mutate_bytes_is_reproducible():
    import numpy as np

    from pbrsr_bench.fuzz import RngDraw

    data = bytes(range(256)) * 4
    a = mutate_bytes(data, RngDraw(np.random.default_rng(5)))
    b = mutate_bytes(data, RngDraw(np.random.default_rng(5)))
    assert a == b and a[0] != data


# ----------------------------------------------------------------------------- regressions
def _glb_with(tmp_path: Path, fn) -> Path:
    src = make_quad_asset(tmp_path / "q.glb", size=8)
    doc, bin_chunk = parse_glb(src.read_bytes())
    fn(doc)
    src.write_bytes(pack_glb(doc, bin_chunk))
    return src


def _set_ktt(doc, ext):
    bct = doc["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]
    bct["extensions"] = {"KHR_texture_transform": ext}


@pytest.mark.parametrize(
    "edit, says",
    [
        (lambda d: d["materials"][0].__setitem__("pbrMetallicRoughness", "x"), "object"),
        (lambda d: d["meshes"][0]["primitives"].__setitem__(0, [1]), "object"),
        (lambda d: d["accessors"][0].__setitem__("sparse", 7), "sparse"),
        (lambda d: _set_ktt(d, {"offset": [0.5]}), "offset"),
        (lambda d: _set_ktt(d, {"scale": [1, "a"]}), "scale"),
        (lambda d: d["nodes"][0].__setitem__("translation", [0, 0]), "translation"),
        (lambda d: d["accessors"][0].__setitem__("count", -3), "count"),
        (lambda d: d["accessors"][0].__setitem__("count", 2.5), "count"),
        (lambda d: d["bufferViews"][0].__setitem__("byteLength", None), "byteLength"),
        (lambda d: d["materials"][0].__setitem__("emissiveFactor", [1, 1, float("nan")]), "emis"),
        (lambda d: d["meshes"][0]["primitives"][0].__setitem__("attributes", []), "attributes"),
        (lambda d: d["meshes"][0]["primitives"][0]["attributes"].__setitem__("NORMAL", "0"), "NOR"),
    ],
)
def test_wrong_json_types_are_invalid_asset(tmp_path, edit, says):
    src = _glb_with(tmp_path, edit)
    with pytest.raises(InvalidAsset, match=f"(?i){says}"):
        load_asset(src)


def _zip(entries: list[tuple[str, bytes]]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in entries:
            zf.writestr(name, data)
    return buf.getvalue()


def test_zip_file_and_folder_of_the_same_name(tmp_path):
    z = tmp_path / "a.zip"
    z.write_bytes(_zip([("m/a.gltf", gltf_using("a.gltf/b.bin")), ("m/a.gltf/b.bin", b"")]))
    with pytest.raises(InvalidAsset, match="clashes|twice"):
        extract_zip(z, tmp_path / "out")
    z.write_bytes(
        _zip([("m/a.gltf", gltf_using("x", "x/y.bin")), ("m/x", b"1"), ("m/x/y.bin", b"2")])
    )
    with pytest.raises(InvalidAsset, match="clashes"):
        extract_zip(z, tmp_path / "out2")


def test_zip_with_lying_offsets_is_invalid(tmp_path):
    data = bytearray(_zip([("m/a.gltf", gltf_using("b.bin")), ("m/b.bin", b"x" * 100)]))
    # the central directory's "offset of local header" of the second entry: far past the end
    cd = data.rfind(b"PK\x01\x02")
    struct.pack_into("<I", data, cd + 42, 0x7FFFFFF0)
    z = tmp_path / "a.zip"
    z.write_bytes(bytes(data))
    with pytest.raises(InvalidAsset, match="zip"):
        extract_zip(z, tmp_path / "out")
    # a cut inside the compressed data
    good = _zip([("m/a.gltf", bytes(range(256)) * 50)])
    cut = bytearray(good)
    del cut[60:90]
    z.write_bytes(bytes(cut))
    with pytest.raises(InvalidAsset):
        extract_zip(z, tmp_path / "out3")


@pytest.mark.parametrize(
    ("value", "error", "says"),
    [(2**53 + 1, UnsupportedAsset, "set 9007199254740993"), ("a" * 5000, InvalidAsset, "texCoord")],
)
def test_texcoord_sets_are_checked_before_anything_is_made_for_them(tmp_path, value, error, says):
    def edit(doc):
        doc["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]["texCoord"] = value

    with pytest.raises(error, match=says) as info:
        load_asset(_glb_with(tmp_path, edit))
    assert len(str(info.value)) < 200
