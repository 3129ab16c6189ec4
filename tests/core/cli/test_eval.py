"""``pbrsr eval``: map and render PSNR of an upscaled asset against its ground truth, the
render PSNR also per environment map."""

from __future__ import annotations

import json
import math

import numpy as np
import OpenImageIO as oiio

from pbrsr_core.asset.procedural import make_demo_asset
from tests.clirun import run_cli, run_cli_output


def _write_env(path, sun: float) -> None:
    """A small equirect sky: grey, with a bright patch of ``sun`` near the zenith."""
    env = np.full((16, 32, 3), 0.5, np.float32)
    env[2:5, 10:14] = sun
    spec = oiio.ImageSpec(32, 16, 3, oiio.FLOAT)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(env)
    out.close()


def test_eval_scores_an_upscale_per_light(tmp_path, capfd):
    gt = make_demo_asset(tmp_path / "gt.glb", size=32)
    assert (
        run_cli(["degrade", str(gt), "-o", str(tmp_path / "lr.glb"), "--scale", "2"], capfd)[0] == 0
    )
    up = ["upscale", str(tmp_path / "lr.glb"), "-o", str(tmp_path / "up.glb")]
    assert run_cli([*up, "--scale", "2", "--method", "bicubic"], capfd)[0] == 0
    pred = next((tmp_path / "up.glb").glob("*.glb"))
    _write_env(tmp_path / "grey.exr", 0.5)
    _write_env(tmp_path / "sun.exr", 40.0)
    args = ["eval", str(pred), str(gt), "--views", "4", "--resolution", "32"]
    env = ["--envmap", str(tmp_path / "grey.exr"), "--envmap", str(tmp_path / "sun.exr")]
    code, out, _ = run_cli_output([*args, *env, "--json", str(tmp_path / "m.json")], capfd)
    assert code == 0 and "render.sun.psnr" in out
    res = json.loads((tmp_path / "m.json").read_text())
    grey, sun = res["render.grey.psnr"], res["render.sun.psnr"]
    assert all(math.isfinite(v) for v in (grey, sun, res["maps.albedo.psnr"]))
    assert grey != sun and min(grey, sun) < res["render.psnr"] < max(grey, sun)
    # one light: the pooled render PSNR only
    code, out, _ = run_cli_output([*args, "--envmap", str(tmp_path / "sun.exr")], capfd)
    assert code == 0 and "render.psnr" in out and "render.sun.psnr" not in out


def test_eval_refuses_an_environment_map_of_another_format(tmp_path, capfd):
    gt = make_demo_asset(tmp_path / "gt.glb", size=16)
    args = ["eval", str(gt), str(gt), "--envmap", str(tmp_path / "sky.png")]
    code, err = run_cli(args, capfd)
    assert code == 2 and "'sky.png' does not exist" in err
    (tmp_path / "sky.png").write_bytes(b"\x89PNG")
    code, err = run_cli(args, capfd)
    assert code == 2 and "must be a .hdr or .exr file" in err


def test_eval_stores_the_prediction_like_a_jpeg_ground_truth(tmp_path, capfd):
    """--store-like-gt: against a ground truth stored as 4:2:0 JPEG, the lossless maps it was
    made from score higher once stored the same way (what the file holds of them)."""
    from pbrsr_core.asset import load_asset
    from pbrsr_core.asset.gltf_write import save_asset

    source = make_demo_asset(tmp_path / "source.glb", size=32)
    asset = load_asset(source)
    every = {im.index: im.pixels for im in asset.images}
    save_asset(asset, tmp_path / "gt.glb", every, image_format="jpeg:80:420")
    args = ["eval", str(source), str(tmp_path / "gt.glb"), "--views", "2", "--resolution", "32"]
    scores = []
    for extra in ([], ["--store-like-gt"]):
        out = tmp_path / f"m{len(extra)}.json"
        assert run_cli([*args, *extra, "--json", str(out)], capfd)[0] == 0
        scores.append(json.loads(out.read_text()))
    as_is, stored = scores
    for key in ("maps.albedo.psnr", "maps.metallic.psnr", "render.psnr"):
        assert stored[key] > as_is[key] + 1.0, key
