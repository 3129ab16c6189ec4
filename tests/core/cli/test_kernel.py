"""``pbrsr kernel estimate`` and ``pbrsr kernel fit`` through the real entry point."""

from __future__ import annotations

import json

import numpy as np

from pbrsr_core.asset import load_asset, make_test_asset
from pbrsr_core.degrade import KERNELS, degrade_asset
from pbrsr_core.errors import InvalidOptions
from pbrsr_core.kernel_estimate import CLASSIFIER, estimate_kernel, load_classifier
from pbrsr_core.options import UpscaleOptions
from pbrsr_core.pipeline import upscale_asset
from tests.clirun import run_cli, run_cli_output
from tests.core.prior.test_train import make_texture_folder


def test_estimate_prints_each_map_and_the_pooled_estimate(tmp_path, capfd):
    hr = make_test_asset(tmp_path / "hr.glb", size=256)
    lr = degrade_asset(hr, tmp_path / "lr.glb", 2, image_format="png16", kernel="lanczos")[0]
    images = [img for img in load_asset(lr).images if img.roles]
    want = estimate_kernel([img.pixels for img in images])

    code, out, _ = run_cli_output(["kernel", "estimate", str(lr), "--json"], capfd)
    assert code == 0 and json.loads(out) == json.loads(json.dumps(want.to_json()))

    code, out, _ = run_cli_output(["kernel", "estimate", str(lr)], capfd)
    lines = out.strip().splitlines()
    assert code == 0 and len(lines) == len(images) + 1
    assert lines[-1].startswith(f"estimate: {want.kernel} ({want.maps} maps; gaussian ")
    for line in lines[:-1]:
        assert all(k in line for k in KERNELS) or "not used" in line


def _leaning(tmp_path, kernel: str):
    """The shipped classifier with its bias moved far toward ``kernel``: every map says it."""
    data = json.loads(CLASSIFIER.read_text())
    data["bias"][list(data["kernels"]).index(kernel)] += 100.0
    path = tmp_path / f"leans-{kernel}.json"
    path.write_text(json.dumps(data))
    return path


def test_a_fitted_classifier_is_used_where_named(tmp_path, capfd, set_runtime):
    """``--classifier FILE`` for the command; ``PBRSR_KERNEL_CLASSIFIER`` (the runtime's
    ``kernel_classifier``) for it and for ``lr_kernel="auto"`` runs."""
    hr = make_test_asset(tmp_path / "hr.glb", size=256)
    lr = degrade_asset(hr, tmp_path / "lr.glb", 2, image_format="png16", kernel="lanczos")[0]
    area, bicubic = _leaning(tmp_path, "area"), _leaning(tmp_path, "bicubic")
    args = ["kernel", "estimate", str(lr), "--json"]
    code, out, _ = run_cli_output([*args, "--classifier", str(area)], capfd)
    assert code == 0 and json.loads(out)["kernel"] == "area"
    set_runtime(kernel_classifier=bicubic)
    code, out, _ = run_cli_output(args, capfd)
    assert code == 0 and json.loads(out)["kernel"] == "bicubic"
    code, out, _ = run_cli_output([*args, "--classifier", str(area)], capfd)  # the option wins
    assert code == 0 and json.loads(out)["kernel"] == "area"
    rep = upscale_asset(lr, tmp_path / "run", UpscaleOptions(method="bicubic", lr_kernel="auto"))
    assert rep["lr_model"]["kernel"] == "bicubic" and rep["lr_model"]["posterior"]["bicubic"] > 0.99
    broken = tmp_path / "broken.json"
    broken.write_text("{")
    code, err = run_cli([*args, "--classifier", str(broken)], capfd)
    assert code == InvalidOptions.exit_code and "cannot read the kernel classifier" in err


def test_estimate_refuses_a_missing_or_broken_asset(tmp_path, capfd):
    code, err = run_cli(["kernel", "estimate", str(tmp_path / "none.glb")], capfd)
    assert code != 0 and "none.glb" in err and "Traceback" not in err
    (tmp_path / "bad.glb").write_bytes(b"glTF not really")
    code, err = run_cli(["kernel", "estimate", str(tmp_path / "bad.glb")], capfd)
    assert code != 0 and "error:" in err and "Traceback" not in err


def test_fit_writes_a_classifier_scored_on_held_out_materials(tmp_path, capfd):
    """On a small procedural texture set: the fitted file loads, names its command and data,
    and its held-out scores count every group of the held-out materials (2 scales x 4
    kernels each)."""
    root = make_texture_folder(tmp_path / "textures", n=10, size=256)
    out = tmp_path / "clf" / "classifier.json"
    code, stdout, _ = run_cli_output(
        ["kernel", "fit", "--textures", str(root), "-o", str(out)], capfd
    )
    assert code == 0, stdout
    assert f"wrote {out}" in stdout and "held out:" in stdout
    clf = load_classifier(out)
    held = clf.meta["held_out"]
    assert held["groups"] == len(clf.meta["held_out_materials"]) * 2 * len(KERNELS) > 0
    assert np.asarray(held["group_confusion"]).sum() == held["groups"]
    assert clf.meta["command"].startswith("pbrsr kernel fit --textures")
    assert clf.meta["train_maps"] > 0 and np.isfinite(clf.weights).all()


def test_fit_refuses_a_folder_without_textures(tmp_path, capfd):
    args = ["kernel", "fit", "--textures", str(tmp_path / "nothing"), "-o", str(tmp_path / "c")]
    code, err = run_cli(args, capfd)
    assert code == InvalidOptions.exit_code and "texture folder" in err
    assert not (tmp_path / "c").exists()
