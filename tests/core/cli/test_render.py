"""``pbrsr render``: a contact sheet of a procedural asset."""

import numpy as np
import pytest

from pbrsr_core.asset.images import read_image
from pbrsr_core.asset.procedural import make_demo_asset
from pbrsr_core.cli.render import contact_sheet
from pbrsr_core.errors import InvalidOptions


def test_contact_sheet_of_the_demo_asset(tmp_path):
    src = make_demo_asset(tmp_path / "demo.glb", size=32)
    out = contact_sheet(src, tmp_path / "sheet.png", views=4, size=48, background=0.25)
    px, depth, mime = read_image(out, "sheet.png")
    assert depth == 8 and mime == "image/png"
    assert px.shape[:2] == (96, 96)
    # each view shows the object (pixels that differ from the background) in its middle
    for r in range(2):
        for c in range(2):
            tile = px[r * 48 : (r + 1) * 48, c * 48 : (c + 1) * 48, :3]
            assert (np.abs(tile - 0.25) > 0.02).any(axis=2)[16:32, 16:32].mean() > 0.9
            assert np.abs(tile[0, 0] - 0.25).max() < 0.01  # corners are background


def test_contact_sheet_refuses_bad_options(tmp_path):
    src = make_demo_asset(tmp_path / "demo.glb", size=16)
    with pytest.raises(InvalidOptions):
        contact_sheet(src, tmp_path / "x.png", views=0)
