"""End to end with a real ``pbrsr worker`` process and the real Redis: a job finishes and
its bundle is complete; a running job is canceled within 2 s; a failing job keeps a clear
error. One worker serves the module (it takes a while to import torch)."""

from __future__ import annotations

import io
import json
import time
import zipfile
from urllib.parse import urljoin

import numpy as np
import pytest
import torch
from fastapi.testclient import TestClient
from PIL import Image

from pbrsr_bench.load import wait_until
from pbrsr_jobs.store import JobLayout
from service.app import create_app
from tests.bundles import assert_one_bundle
from tests.service_support import (
    asset_bytes,
    cleanup_redis,
    gltf_zip_bytes,
    make_settings,
    post_asset,
    worker_process,
)

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("worker-e2e")
    (tmp / "models").mkdir()
    # a memory budget, not the machine's; the server's own priors in models/
    settings = make_settings(tmp, worker_memory_mb=8192, models_dir=tmp / "models")
    with (
        worker_process(settings, tmp / "worker.log") as proc,
        TestClient(create_app(settings), raise_server_exceptions=False) as client,
    ):
        yield settings, client, proc, tmp
    cleanup_redis(settings)


def _status(client, job_id):
    return client.get(f"/v1/jobs/{job_id}").json()


def _wait_state(client, job_id, states, timeout):
    return wait_until(
        lambda: (j := _status(client, job_id))["status"] in states and j,
        timeout,
        f"job {job_id} to reach {states}",
        0.2,
    )


def test_job_runs_to_finished_with_a_complete_bundle(env):
    settings, client, proc, tmp = env
    job_id = post_asset(client, asset_bytes(tmp), options={"method": "bicubic", "scale": 2}).json()[
        "id"
    ]
    seen = set()

    def done():
        j = _status(client, job_id)
        seen.add(j["status"])
        assert proc.poll() is None, (tmp / "worker.log").read_text()[-3000:]
        return j["status"] in ("finished", "failed", "canceled") and j

    job = wait_until(done, 150, "the job to end", 0.2)
    assert job["status"] == "finished", job
    assert "running" in seen
    assert job["fraction"] == 1.0 and job["attempt"] == 1
    assert job["error"] is None and job["timings"]
    assert job["started_at"] and job["ended_at"] >= job["started_at"]

    r = client.get(f"/v1/jobs/{job_id}/result")
    assert r.status_code == 200 and r.headers["content-type"] == "application/zip"
    assert r.headers["content-disposition"].endswith('-pbrsr-x2.zip"')
    zf = zipfile.ZipFile(io.BytesIO(r.content))
    names = zf.namelist()
    assert "asset.glb" in names and "report.json" in names and "preview.png" in names
    maps = [n for n in names if n.startswith("maps/")]
    assert maps and all(n.endswith((".png", ".exr")) for n in maps)
    assert any(n.startswith("previews/before_") for n in names)
    report = json.loads(zf.read("report.json"))
    assert report["options"]["scale"] == 2
    for img in report["images"]:
        assert img["hr_size"] == [2 * img["lr_size"][0], 2 * img["lr_size"][1]]
    # the job's summary carries the report's table of maps (the dashboard shows it)
    rows = job["summary"]["map_rows"]
    assert [r["name"] for r in rows] == [img["name"] for img in report["images"]]
    assert all(r["scale"] == 2 and r["made_from"] == "bicubic" for r in rows)
    # and the LR model the run inverted (the protocol's, as told by default)
    assert (
        job["summary"]["lr_model"]
        == report["lr_model"]
        == {"kernel": "gaussian", "estimated": False}
    )

    previews = job["links"]["previews"]
    assert "preview.png" in previews
    for url in list(previews.values()) + list(job["links"]["thumbs"].values()):
        img = client.get(url)
        assert img.status_code == 200 and img.content[:4] == b"\x89PNG"
    assert len(job["links"]["thumbs"]) == len(maps)

    # per-map detail crops: the same region of the LR and the HR map
    crops = client.get(job["links"]["crops"]).json()["items"]
    assert sorted(f"maps/{c['map']}.png" for c in crops) == sorted(maps)
    for crop in crops:
        x, y, w, h = crop["lr_region"]
        assert crop["scale"] == 2 and crop["hr_region"] == [2 * x, 2 * y, 2 * w, 2 * h]
        lr, hr = client.get(crop["lr"]), client.get(crop["hr"])
        assert lr.headers["content-type"] == hr.headers["content-type"] == "image/png"
        lr_px = np.asarray(Image.open(io.BytesIO(lr.content)))
        hr_px = np.asarray(Image.open(io.BytesIO(hr.content)))
        assert lr_px.shape[:2] == (h, w) and hr_px.shape[:2] == (2 * h, 2 * w)
    # the upscaled asset for a 3D viewer, and any file of the bundle by its path
    model = client.get(job["links"]["model"])
    assert job["links"]["model"].endswith("/files/asset.glb")
    assert model.headers["content-type"] == "model/gltf-binary"
    assert model.content == zf.read("asset.glb")
    assert client.get(f"/v1/jobs/{job_id}/files/report.json").json() == report
    for bad in ("..%2Fjob.json", "maps", "maps%2F..%2Freport.json", "%2E%2E%2Finput", "nope.glb"):
        assert client.get(f"/v1/jobs/{job_id}/files/{bad}").status_code == 404, bad

    # nothing temporary left, one bundle
    assert_one_bundle(settings.storage_dir, job_id)
    metrics = client.get("/metrics").text
    assert 'pbrsr_jobs_completed_total{state="finished"} 1.0' in metrics
    assert "pbrsr_job_duration_seconds_count 1.0" in metrics
    assert "pbrsr_workers 1.0" in metrics


def test_a_gltf_result_resolves_its_files_beside_it(env):
    """A zip upload's result is a .gltf: links.model and the URIs inside it, resolved against
    its URL as a browser's 3D viewer does, all answer."""
    settings, client, proc, tmp = env
    r = post_asset(client, gltf_zip_bytes(tmp), "scene.zip", {"method": "bicubic", "scale": 2})
    job = _wait_state(client, r.json()["id"], ("finished", "failed", "canceled"), 150)
    assert job["status"] == "finished", job
    model_url = job["links"]["model"]
    assert model_url.endswith(".gltf")
    doc = client.get(model_url).json()
    uris = [x["uri"] for x in doc["buffers"] + doc["images"]]
    assert len(uris) >= 2
    for uri in uris:
        r = client.get(urljoin(model_url, uri))
        assert r.status_code == 200 and r.content, uri


def test_running_job_cancels_within_two_seconds(env):
    settings, client, proc, tmp = env
    # 512^2 maps at x4: the export (2048^2 PNGs, previews) takes seconds, and calls back rarely
    big = asset_bytes(tmp, size=512)
    job_id = post_asset(client, big, options={"method": "bicubic"}).json()["id"]
    # wait until it is well inside the pipeline
    _wait_state(client, job_id, ("running",), 120)
    wait_until(lambda: _status(client, job_id)["stage"] in ("export",), 60, "export", 0.1)
    time.sleep(0.5)
    t0 = time.monotonic()
    r = client.delete(f"/v1/jobs/{job_id}")
    assert r.status_code == 202 and r.json()["cancel_requested"] is True
    job = _wait_state(client, job_id, ("canceled", "finished", "failed"), 10)
    elapsed = time.monotonic() - t0
    assert job["status"] == "canceled", job
    assert elapsed < 2.0, f"took {elapsed:.2f} s to stop"
    assert proc.poll() is None  # the worker lives on
    job_dir = JobLayout(settings.storage_dir).job_dir(job_id)
    assert not (job_dir / "result.zip").exists() and not (job_dir / "output").exists()
    assert [p.name for p in job_dir.iterdir() if p.name.startswith(".")] == []
    assert client.get(f"/v1/jobs/{job_id}/result").status_code == 409


def test_failing_job_keeps_a_clear_error(env):
    settings, client, proc, tmp = env
    r = post_asset(client, asset_bytes(tmp), options={"method": "direct", "prior": "no-such-prior"})
    job_id = r.json()["id"]
    job = _wait_state(client, job_id, ("finished", "failed", "canceled"), 120)
    assert job["status"] == "failed"
    assert "no-such-prior" in job["error"] and job["code"] == "invalid-options"
    assert "Traceback" not in job["error"] and str(settings.storage_dir) not in job["error"]
    assert client.get(f"/v1/jobs/{job_id}/result").status_code == 409
    assert client.get("/v1/jobs?status=failed").json()["total"] == 1


def test_a_job_larger_than_the_workers_memory_is_refused_not_killed(env):
    """x8 of 2048² maps: an estimate of tens of GiB, over the worker's 8 GiB budget
    (PBRSR_WORKER_MEMORY_MB), refused before it allocates the output (the worker lives on and
    takes the next job)."""
    from pbrsr_core.footprint import MIB, estimate_peak_bytes

    settings, client, proc, tmp = env
    data = asset_bytes(tmp, size=2048)
    assert estimate_peak_bytes([(2048, 2048, 3)] * 3, 8, "direct") > 8192 * MIB
    job_id = post_asset(client, data, options={"method": "direct", "scale": 8}).json()["id"]
    job = _wait_state(client, job_id, ("finished", "failed", "canceled"), 120)
    assert job["status"] == "failed" and job["code"] == "limit-exceeded", job
    assert "GiB of memory" in job["error"] and "x8 of" in job["error"]
    assert job["attempt"] == 1 and proc.poll() is None  # no retry, no dead worker
    small = post_asset(client, asset_bytes(tmp), options={"method": "bicubic", "scale": 2})
    after = _wait_state(client, small.json()["id"], ("finished", "failed", "canceled"), 120)
    assert after["status"] == "finished"


def test_pbrsr_job_reports_losses_and_returns_valid_hr_maps(env):
    """PBR-SR with optimiser steps (``iterations``; bicubic prior on a small asset: seconds):
    losses and consistency PSNR reach the status while it runs, and the bundle holds a valid
    asset at x2."""
    from pbrsr_core.asset import load_asset, validate_gltf

    settings, client, proc, tmp = env
    opts = {
        "method": "pbrsr",
        "preset": "quality",
        "iterations": 20,
        "prior": "bicubic",
        "scale": 2,
    }
    job_id = post_asset(client, asset_bytes(tmp), options=opts).json()["id"]
    job = _wait_state(client, job_id, ("finished", "failed", "canceled"), 240)
    assert job["status"] == "finished", job
    history = job["history"]  # the status keeps the optimiser's losses over time
    assert any(h.get("losses") for h in history), history[-3:]
    r = client.get(f"/v1/jobs/{job_id}/result")
    zf = zipfile.ZipFile(io.BytesIO(r.content))
    out = tmp / f"bundle-{job_id}"
    zf.extractall(out)
    assert validate_gltf(out / "asset.glb")["numErrors"] == 0
    report = json.loads((out / "report.json").read_text())
    assert report["num_views"] >= 1 and report["history"]
    res = load_asset(out / "asset.glb")
    for img in report["images"]:
        assert [res.images[img["index"]].width, res.images[img["index"]].height] == [
            2 * img["lr_size"][0],
            2 * img["lr_size"][1],
        ]


def test_a_worker_takes_high_priority_jobs_first(tmp_path):
    """Jobs queued low, normal, high while no worker runs: one worker (burst) runs them
    high first, then normal, then low."""
    settings = make_settings(tmp_path)
    try:
        with TestClient(create_app(settings), raise_server_exceptions=False) as client:
            ids = {}
            for priority in ("low", "normal", "high"):
                r = client.post(
                    "/v1/jobs",
                    files={"file": ("a.glb", asset_bytes(tmp_path), "application/octet-stream")},
                    data={"priority": priority, "options": json.dumps({"method": "bicubic"})},
                )
                ids[priority] = r.json()["id"]
            with worker_process(settings, tmp_path / "worker.log", extra=["--burst"]) as proc:
                proc.wait(timeout=180)
            started = {p: _status(client, i)["started_at"] for p, i in ids.items()}
            assert all(_status(client, i)["status"] == "finished" for i in ids.values())
            assert started["high"] < started["normal"] < started["low"], started
    finally:
        cleanup_redis(settings)


def test_a_job_names_a_texture_set_from_the_servers_models_folder(env):
    """A set ``pbrsr priors train|finetune`` wrote, put in PBRSR_MODELS_DIR, is a job's
    ``texture:<name>`` prior; a name the folder does not hold is refused before queueing."""
    from pbrsr_core.prior.train.loop import TrainConfig
    from pbrsr_core.prior.train.weights import new_network, save_network

    settings, client, proc, tmp = env
    cfg = TrainConfig(kinds=("colour",), widths=(4, 8), init="random")
    torch.manual_seed(0)
    net = new_network(cfg.arch, cfg.widths, cfg.stride)
    (tmp / "models" / "farm-set" / "farm-colour").mkdir(parents=True)
    save_network(net, tmp / "models" / "farm-set" / "farm-colour" / "farm-colour.safetensors",
                 cfg, {})  # fmt: skip
    options = {"method": "direct", "prior": "texture:farm-set", "scale": 2}
    r = post_asset(client, asset_bytes(tmp), options=options)
    assert r.status_code == 202, r.text
    job = _wait_state(client, r.json()["id"], ("finished", "failed", "canceled"), 150)
    assert job["status"] == "finished", job
    report = client.get(f"/v1/jobs/{job['id']}/files/report.json").json()
    assert report["options"]["prior"] == f"texture:{tmp / 'models' / 'farm-set'}"
    r = post_asset(client, asset_bytes(tmp), options={**options, "prior": "texture:other-set"})
    assert r.status_code == 422 and "not available on this server" in r.text
