"""Every texture a material uses is upscaled: the KHR_materials_* maps (clearcoat, sheen,
specular, transmission, volume, iridescence) by their kind, written back at the HR size and
valid, and the report says which the renderer treats as maps only."""

from __future__ import annotations

import json

import pytest

from pbrsr_core.asset import load_asset, make_test_asset, validate_gltf
from pbrsr_core.asset.model import EXTENSION_ROLES
from pbrsr_core.maps import kind_of, upscalable_images
from pbrsr_core.options import UpscaleOptions
from pbrsr_core.pipeline import upscale_asset

FEATURES = {"orm", "khr_materials"}
EXPECTED = {
    "clearcoat", "clearcoat_roughness", "clearcoat_normal", "sheen_color", "sheen_roughness",
    "specular", "specular_color", "transmission", "thickness", "iridescence",
    "iridescence_thickness",
}  # fmt: skip


def test_the_loader_finds_every_extension_texture_with_its_kind(tmp_path):
    asset = load_asset(make_test_asset(tmp_path / "a.glb", size=32, features=FEATURES))
    roles = {r for img in upscalable_images(asset) for r in img.roles}
    assert roles >= EXPECTED
    by_role = {
        next(iter(img.roles)): img for img in upscalable_images(asset) if len(img.roles) == 1
    }
    for role in EXPECTED:
        assert kind_of(by_role[role].roles) == EXTENSION_ROLES[role][2], role
    assert kind_of({"clearcoat_normal"}) == "normal" and kind_of({"sheen_color"}) == "colour"


@pytest.mark.parametrize(
    ("method", "preset", "iterations"),
    [
        ("bicubic", "fast", None),
        ("direct", "fast", None),
        ("pbrsr", "fast", None),
        ("pbrsr", "quality", 3),  # eight copies of the prior, then optimiser steps
    ],
)
def test_extension_maps_come_back_upscaled_and_valid(tmp_path, method, preset, iterations):
    src = make_test_asset(tmp_path / "a.glb", size=32, features=FEATURES)
    options = UpscaleOptions(
        scale=2, method=method, preset=preset, prior="pbr-upconv7", iterations=iterations
    )
    report = upscale_asset(src, tmp_path / "out", options)
    out = load_asset(tmp_path / "out" / "a.glb")
    assert validate_gltf(tmp_path / "out" / "a.glb")["numErrors"] == 0
    lr = load_asset(src)
    for img in upscalable_images(lr):
        up = out.images[img.index]
        assert (up.width, up.height) == (2 * img.width, 2 * img.height), img.roles
    entries = {e["index"]: e for e in report["images"]}
    for img in upscalable_images(lr):
        assert entries[img.index]["rendered"] == bool(img.roles - EXPECTED)
    maps_only = {r for e in report["images"] if not e["rendered"] for r in e["roles"]}
    assert maps_only == EXPECTED
    doc = json.loads((tmp_path / "out" / "report.json").read_text())
    assert {e["kind"] for e in doc["images"]} == {"colour", "data", "normal"}
    # the extensions keep their factors and point at the same images
    ext = out.document["materials"][0]["extensions"]
    assert ext["KHR_materials_clearcoat"]["clearcoatFactor"] == 1.0
    assert set(out.document["extensionsUsed"]) >= {e for e, _, _ in EXTENSION_ROLES.values()} - {
        "KHR_materials_anisotropy",
        "KHR_materials_diffuse_transmission",
    }


@pytest.mark.parametrize("method", ["direct", "pbrsr"])
def test_extension_data_maps_run_the_prior_on_the_channels_they_read(tmp_path, method):
    """clearcoat reads R, clearcoat roughness G, sheen roughness and specular alpha only
    (KHR_materials_*): the prior runs on those channels, bicubic's upscale fills the rest."""
    from pbrsr_core.prior.direct import bicubic_map

    src = make_test_asset(tmp_path / "a.glb", size=32, features=FEATURES)
    options = UpscaleOptions(scale=2, method=method, preset="fast", prior="pbr-upconv7")
    report = upscale_asset(src, tmp_path / "out", options)
    lr, out = load_asset(src), load_asset(tmp_path / "out" / "a.glb")
    made_by = {e["roles"][0]: e["made_by"] for e in report["images"] if len(e["roles"]) == 1}
    read = {"clearcoat": 0, "clearcoat_roughness": 1, "iridescence": 0}
    for role, c in read.items():
        assert all(m.startswith("bicubic") for k, m in enumerate(made_by[role]) if k != c), role
    assert not made_by["clearcoat"][0].startswith("bicubic")  # the prior wins it here
    for role in ("sheen_roughness", "specular"):
        assert made_by[role] == ["bicubic"] * 3, role
    for img in upscalable_images(lr):
        (role,) = img.roles if len(img.roles) == 1 else (None,)
        if role in read or role in ("sheen_roughness", "specular"):
            bic = bicubic_map(img.pixels, "data", 2)
            unread = [k for k in range(3) if k != read.get(role)]
            got = out.images[img.index].pixels[..., unread]
            assert abs(got - bic[..., unread]).max() <= 1 / 255 + 1e-6, role
