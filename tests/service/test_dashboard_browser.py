"""The dashboard end to end in headless Chromium (Debian's /usr/bin/chromium, driven by
Playwright): a real ``pbrsr serve`` and ``pbrsr worker`` on localhost; drop a procedural
asset on the page, watch the progress bar move (pushed by the event stream), see the job
finish, download the bundle; a finished job's detail crops with their wipe sliders and its
3D view (WebGL, drawn by SwiftShader on the CPU here), also of Draco and meshopt results;
with a key and S3 storage, nothing the page loads from the bucket carries the key.
The screenshots are kept as test-artifacts/dashboard.png and dashboard-detail.png."""

from __future__ import annotations

import base64
import io
import json
import re
import time
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from PIL import Image

from pbrsr_bench.load import wait_until
from tests.service_support import (
    REPO,
    api_server,
    asset_bytes,
    cleanup_redis,
    make_settings,
    worker_process,
)

pytestmark = [pytest.mark.browser, pytest.mark.slow]

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    # WebGL without a GPU: SwiftShader, which newer Chromium builds use only when allowed
    "--enable-unsafe-swiftshader",
]


@pytest.fixture(autouse=True)
def _needs_chromium() -> None:
    """These tests run in Debian's Chromium, which scripts/test installs: without it they
    fail, saying so, rather than pass unrun."""
    if not CHROMIUM.exists():
        pytest.fail(f"{CHROMIUM} is missing: ./scripts/test installs Debian's chromium")


ARTIFACTS = REPO / "test-artifacts"

DROP_FILE = """([b64, name]) => {
  const bytes = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
  const dt = new DataTransfer();
  dt.items.add(new File([bytes], name, { type: "model/gltf-binary" }));
  return dt;
}"""


@contextmanager
def dashboard_page(base: str, **options: Any) -> Iterator[tuple[Any, list[str], list[str]]]:
    """Headless Chromium on the dashboard at ``base``: the page (1360 x 1000; ``options`` go to
    ``new_page``), its uncaught errors and the URLs it requested (both filled as it runs)."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(
            executable_path=str(CHROMIUM), args=CHROMIUM_ARGS, headless=True
        )
        try:
            page = browser.new_page(viewport={"width": 1360, "height": 1000}, **options)
            errors: list[str] = []
            page.on("pageerror", lambda exc: errors.append(str(exc)))
            requests: list[str] = []
            page.on("request", lambda req: requests.append(req.url))
            page.goto(base + "/")
            yield page, errors, requests
        finally:
            browser.close()


def test_dashboard_upload_progress_finish_download(tmp_path):
    settings = make_settings(tmp_path)
    ARTIFACTS.mkdir(exist_ok=True)
    data = asset_bytes(tmp_path, size=32)
    try:
        with (
            worker_process(settings, tmp_path / "worker.log"),
            api_server(settings, tmp_path / "api.log") as base,
            dashboard_page(base, accept_downloads=True) as (page, errors, requests),
        ):
            assert page.title().startswith("pbrsr")
            # the page follows the key's event stream instead of polling
            page.wait_for_function("document.body.dataset.events === 'live'")
            assert page.is_disabled("#submit")

            # drag and drop the asset onto the drop zone, pick options, submit
            dt = page.evaluate_handle(DROP_FILE, [base64.b64encode(data).decode(), "chair.glb"])
            page.dispatch_event("#drop-zone", "drop", {"dataTransfer": dt})
            assert "chair.glb" in page.inner_text("#drop-text")
            # quality's stages (eight copies of the prior, then views and the steps asked
            # for) report progress for seconds; a bicubic job of this asset can start and end
            # between two polls of the page
            page.select_option("#opt-method", "pbrsr")
            page.select_option("#opt-preset", "quality")
            page.fill("#opt-iterations", "20")
            page.select_option("#opt-scale", "2")
            page.fill("#opt-max-size", "64")  # the 32² maps at x2 all the same
            page.select_option("#opt-lr-kernel", "auto")
            boxes = page.locator("#opt-maps input[type=checkbox]")
            for i in range(boxes.count()):  # nothing checked: nothing sent
                boxes.nth(i).uncheck()
            page.click("#submit")
            assert page.inner_text("#upload-status") == "Check at least one map to upscale."
            page.wait_for_timeout(300)
            assert page.locator(".job-row").count() == 0 and page.is_hidden("#upload-bar")
            for i in range(boxes.count()):
                boxes.nth(i).check()
            page.uncheck("#opt-maps input[value=emissive]")  # its file kept
            page.click("#submit")
            page.wait_for_selector("#job-view:not([hidden])")
            page.wait_for_selector(".job-row[data-status]")
            # the view's status is set when the job's detail has arrived, with its name
            page.wait_for_selector("#job-view[data-status]")
            assert page.inner_text("#job-name") == "chair.glb"
            meta = page.inner_text("#job-meta")
            assert meta.startswith(
                "x2 · at most 64 px · maps: base_color, metallic_roughness, normal, occlusion"
                " · input kernel to estimate · pbrsr · quality"
            )

            # watch the bar until the job ends
            widths, statuses = [], []
            deadline = time.monotonic() + 300
            while time.monotonic() < deadline:
                status = page.get_attribute("#job-view", "data-status")
                statuses.append(status)
                width = page.eval_on_selector("#progress-bar", "el => el.style.width")
                widths.append(float(width.rstrip("%") or 0))
                if status in ("finished", "failed", "canceled"):
                    break
                time.sleep(0.25)
            assert statuses[-1] == "finished", (statuses[-5:], page.inner_text("#job-error"))
            assert page.evaluate("document.body.dataset.events") == "live"
            assert any(u.endswith("/v1/events") for u in requests)
            assert "running" in statuses
            assert any(0 < w < 100 for w in widths), widths  # it moved before the end
            page.wait_for_function("document.getElementById('progress-bar').style.width === '100%'")
            page.wait_for_selector("#download:not([hidden])")
            page.wait_for_selector("#thumbs img")
            page.wait_for_selector("#preview-pairs img")
            page.wait_for_function(  # every image decoded
                "[...document.querySelectorAll('#preview-pairs img, #thumbs img')]"
                ".every(i => i.complete && i.naturalWidth > 0)"
            )
            row = page.locator(".job-row").first
            assert row.get_attribute("data-status") == "finished"
            assert page.inner_text("#timings")  # per-stage timings listed
            # the chair's 32² maps are too small to tell their kernel: the protocol's is run
            meta = page.inner_text("#job-meta")
            assert "input by gaussian (no map to estimate from) · pbrsr" in meta, meta
            # one row per map: its size and factor, what made it, its consistency PSNR
            cells = page.eval_on_selector_all(
                "#map-table tbody tr", "trs => trs.map(tr => [...tr.cells].map(c => c.textContent))"
            )
            upscaled = [c for c in cells if not c[2].endswith("kept")]  # a thumbnail each
            assert len(upscaled) == page.locator("#thumbs img").count() == len(cells) - 1, cells
            assert [c[1:4] for c in cells if c[1] == "emissive"] == [
                ["emissive", "16² kept", "kept (maps)"]
            ], cells
            for _, role, size, made_from, db in (c for c in cells if c[1] != "emissive"):
                lr, hr = re.fullmatch(r"(\d+)² x2 = (\d+)²", size).groups()  # under max_size
                assert role and made_from and int(hr) == 2 * int(lr) <= 64, cells
                assert all(float(v) > 20 for v in db.split()), cells
            # the steps' losses are drawn: one line per loss, no "no losses" text
            assert page.locator("#loss-chart svg path[data-series]").count() > 0
            assert "no losses" not in page.inner_text("#loss-chart")
            assert page.is_hidden("#cancel") and page.is_hidden("#auth")
            page.wait_for_timeout(600)  # let the bar's CSS transition end
            page.screenshot(path=str(ARTIFACTS / "dashboard.png"), full_page=True)

            with page.expect_download() as info:
                page.click("#download")
            path = info.value.path()
            assert info.value.suggested_filename.endswith("-pbrsr-x2.zip")
            names = zipfile.ZipFile(io.BytesIO(Path(path).read_bytes())).namelist()
            assert "asset.glb" in names and "report.json" in names
            report = json.loads(zipfile.ZipFile(path).read("report.json"))
            assert report["options"]["max_size"] == 64
            assert report["options"]["lr_kernel"] == "auto"
            assert report["lr_model"]["kernel"] == "gaussian" and report["lr_model"]["maps"] == 0
            assert report["options"]["maps"] == [
                "base_color", "metallic_roughness", "normal", "occlusion"
            ]  # fmt: skip
            assert {i["scale"] for i in report["images"]} == {2}
            assert [(k["label"], k["reason"]) for k in report["kept"]] == [("emissive", "maps")]

            # the same maps with the rest bicubic: the emissive map upscaled by bicubic
            page.select_option("#opt-method", "direct")
            page.select_option("#opt-other-maps", "bicubic")
            page.click("#submit")
            page.wait_for_function(
                "document.getElementById('job-meta').textContent.includes('(the rest bicubic)')"
            )
            page.wait_for_selector("#job-view[data-status=finished]", timeout=120_000)
            page.wait_for_function(  # the table of this job, not of the one before
                "document.getElementById('map-table').textContent.includes('bicubic (maps)')"
            )
            cells = page.eval_on_selector_all(
                "#map-table tbody tr", "trs => trs.map(tr => [...tr.cells].map(c => c.textContent))"
            )
            assert [c[1:4] for c in cells if c[1] == "emissive"] == [
                ["emissive", "16² x2 = 32²", "bicubic (maps)"]
            ], cells
            assert not any(c[2].endswith("kept") for c in cells), cells
            assert errors == []
    finally:
        cleanup_redis(settings)


# The 3D view's canvas read back in the page: how many pixels differ from the background
# (the top-left pixel) and how many distinct colours there are.
CANVAS_STATS = """() => {
  const src = document.querySelector('#model-view canvas');
  const c = document.createElement('canvas');
  c.width = src.width; c.height = src.height;
  const ctx = c.getContext('2d');
  ctx.drawImage(src, 0, 0);
  const px = ctx.getImageData(0, 0, c.width, c.height).data;
  const colours = new Set();
  let differ = 0;
  for (let i = 0; i < px.length; i += 4) {
    colours.add((px[i] << 16) | (px[i + 1] << 8) | px[i + 2]);
    const d = Math.abs(px[i] - px[0]) + Math.abs(px[i + 1] - px[1]) + Math.abs(px[i + 2] - px[2]);
    if (d > 6) differ++;
  }
  return { differ: differ / (px.length / 4), colours: colours.size, url: src.toDataURL() };
}"""


def _png(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"), dtype=np.int16)


def test_dashboard_detail_crops_wipe_and_3d_view(tmp_path):
    settings = make_settings(tmp_path)
    ARTIFACTS.mkdir(exist_ok=True)
    data = asset_bytes(tmp_path, size=64)
    try:
        # the API's first check of an upload imports torch: seconds on a busy machine
        with (
            api_server(settings, tmp_path / "api.log") as base,
            httpx.Client(base_url=base, timeout=60) as api,
        ):
            options = '{"method": "bicubic", "scale": 4}'
            files = {"file": ("sphere.glb", data, "model/gltf-binary")}
            job_id = api.post("/v1/jobs", files=files, data={"options": options}).json()["id"]
            with worker_process(settings, tmp_path / "worker.log", extra=["--burst"]) as proc:
                wait_until(lambda: proc.poll() is not None, 120, "the burst worker to end", 0.2)
            job = api.get(f"/v1/jobs/{job_id}").json()
            assert job["status"] == "finished", job
            crops = api.get(job["links"]["crops"]).json()["items"]
            assert len(crops) == len(job["links"]["thumbs"]) >= 3

            with dashboard_page(base) as (page, errors, requests):
                page.click(f".job-row[data-id='{job_id}']")

                # one wipe per map, both crops decoded: the LR at its texels, the HR x4
                page.wait_for_selector("#crops-box:not([hidden]) .wipe")
                figures = page.locator("#crops .wipe")
                assert figures.count() == len(crops)
                page.wait_for_function(
                    "[...document.querySelectorAll('#crops img')]"
                    ".every(i => i.complete && i.naturalWidth > 0)"
                )
                sizes = page.eval_on_selector_all(
                    "#crops .wipe",
                    "els => els.map(f => [f.dataset.map,"
                    " f.querySelector('.wipe-lr').naturalWidth,"
                    " f.querySelector('.wipe-hr').naturalWidth,"
                    " getComputedStyle(f.querySelector('.wipe-lr')).imageRendering])",
                )
                assert sorted(m for m, *_ in sizes) == sorted(c["map"] for c in crops)
                for _, lr_w, hr_w, rendering in sizes:
                    assert hr_w == 4 * lr_w and rendering == "pixelated"

                # the wipe: drag across the first crop to 10 %, then its slider to 90 %
                first = figures.first
                box = first.locator(".wipe-box")
                first.scroll_into_view_if_needed()
                rect = box.bounding_box()
                assert rect is not None and rect["width"] >= 256  # at least 2x a 128 crop
                y = rect["y"] + rect["height"] / 2
                page.mouse.move(rect["x"] + rect["width"] / 2, y)
                page.mouse.down()
                page.mouse.move(rect["x"] + rect["width"] * 0.1, y, steps=4)
                page.mouse.up()
                split = box.evaluate("b => b.style.getPropertyValue('--split')")
                assert abs(float(split.rstrip("%")) - 10) < 1, split
                at_10 = _png(box.screenshot())
                first.locator(".wipe-range").fill("90")
                assert box.evaluate("b => b.style.getPropertyValue('--split')") == "90%"
                clip = first.locator(".wipe-lr").evaluate("i => getComputedStyle(i).clipPath")
                assert "10%" in clip, clip  # the input shows on the left 90 %
                at_90 = _png(box.screenshot())
                h, w = at_10.shape[:2]
                rows = slice(4, h - 4)  # inside the rounded border
                left, middle = slice(4, int(0.08 * w)), slice(int(0.15 * w), int(0.85 * w))
                # left of both splits the input both times; between them input vs result
                assert np.array_equal(at_10[rows, left], at_90[rows, left])
                assert np.abs(at_10[rows, middle] - at_90[rows, middle]).mean() > 1.0

                # the 3D view (set up once on screen): the upscaled asset drawn under the
                # room environment
                page.wait_for_selector("#model-box:not([hidden])")
                page.locator("#model-view").scroll_into_view_if_needed()
                page.wait_for_function(
                    "document.getElementById('model-view').dataset.state === 'ready'",
                    timeout=30_000,
                )
                stats = page.evaluate(CANVAS_STATS)
                # the test asset's two small objects: about 2 % of the view, many colours
                assert stats["differ"] > 0.01 and stats["colours"] > 200, stats["colours"]
                # orbiting redraws it from elsewhere
                frames = int(page.get_attribute("#model-view", "data-frames") or 0)
                view = page.locator("#model-view").bounding_box()
                assert view is not None
                cx, cy = view["x"] + view["width"] / 2, view["y"] + view["height"] / 2
                page.mouse.move(cx, cy)
                page.mouse.down()
                page.mouse.move(cx + 120, cy + 30, steps=5)
                page.mouse.up()
                page.wait_for_function(
                    f"+document.getElementById('model-view').dataset.frames > {frames}"
                )
                assert page.evaluate(CANVAS_STATS)["url"] != stats["url"]
                assert page.inner_text("#model-status") == ""

                page.screenshot(path=str(ARTIFACTS / "dashboard-detail.png"), full_page=True)
                assert errors == []
                # nothing from elsewhere (blob: URLs are the GLB's own images)
                assert [u for u in requests if not u.startswith((base, "blob:"))] == []
                assert any("/vendor/three/build/three.module.js" in u for u in requests)
    finally:
        cleanup_redis(settings)


def test_dashboard_3d_view_draws_draco_and_meshopt_results(tmp_path):
    """A result keeps its input's compressed geometry: the 3D view decodes it (Draco's
    decoder and meshopt's from the service's node_modules)."""
    from pbrsr_bench.variants import draco_variant, meshopt_variant
    from pbrsr_core.asset import make_test_asset

    settings = make_settings(tmp_path)
    src = make_test_asset(tmp_path / "src.glb", size=32)
    variants = {
        "draco": draco_variant(src, tmp_path / "draco.glb"),
        "meshopt": meshopt_variant(src, tmp_path / "meshopt.glb"),
    }
    try:
        with (
            api_server(settings, tmp_path / "api.log") as base,
            httpx.Client(base_url=base, timeout=60) as api,
        ):
            ids = {}
            for kind, path in variants.items():
                files = {"file": (f"{kind}.glb", path.read_bytes(), "model/gltf-binary")}
                r = api.post("/v1/jobs", files=files, data={"options": '{"method": "bicubic"}'})
                ids[kind] = r.json()["id"]
            with worker_process(settings, tmp_path / "worker.log", extra=["--burst"]) as proc:
                wait_until(lambda: proc.poll() is not None, 120, "the burst worker to end", 0.2)
            for job_id in ids.values():
                assert api.get(f"/v1/jobs/{job_id}").json()["status"] == "finished"

            with dashboard_page(base) as (page, errors, requests):
                for kind, job_id in ids.items():
                    page.click(f".job-row[data-id='{job_id}']")
                    page.wait_for_selector("#model-box:not([hidden])")
                    page.locator("#model-view").scroll_into_view_if_needed()
                    page.wait_for_function(  # picking a job cleared the previous model
                        "['ready', 'error'].includes(document.getElementById('model-view')"
                        ".dataset.state)",
                        timeout=30_000,
                    )
                    state = page.get_attribute("#model-view", "data-state")
                    assert state == "ready", (kind, page.get_attribute("#model-view", "data-error"))
                    stats = page.evaluate(CANVAS_STATS)
                    assert stats["differ"] > 0.01 and stats["colours"] > 200, (kind, stats)
                    page.locator("#job-list").scroll_into_view_if_needed()
                assert any(u.endswith("/draco/gltf/draco_decoder.wasm") for u in requests)
                assert errors == []
    finally:
        cleanup_redis(settings)


def test_dashboard_with_a_key_and_s3_storage_never_sends_the_key_to_the_bucket(tmp_path):
    """Images, detail crops, the 3D view's model and the download come from presigned URLs
    the page asks for as JSON: the API key stays with the API (moto's server allows every
    origin, as the 3D view's fetch of the model needs)."""
    import httpx
    from minio import Minio
    from moto.server import ThreadedMotoServer
    from playwright.sync_api import sync_playwright

    from pbrsr_bench.load import free_port, wait_until
    from tests.service_support import LONG_KEY_A, post_asset

    port = free_port()
    s3 = ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    s3.start()
    endpoint = f"http://127.0.0.1:{port}"
    raw = Minio(f"127.0.0.1:{port}", "k", "s", secure=False, region="us-east-1")
    raw.make_bucket("dash")
    values = {
        "storage_backend": "s3",
        "s3_endpoint_url": endpoint,
        "s3_bucket": "dash",
        "s3_access_key": "k",
        "s3_secret_key": "s",
        "api_keys": [LONG_KEY_A],
    }
    settings = make_settings(tmp_path / "api", **values)
    worker = settings.model_copy(update={"storage_dir": tmp_path / "worker"})
    try:
        with (
            worker_process(worker, tmp_path / "worker.log"),
            api_server(settings, tmp_path / "api.log") as base,
            httpx.Client(base_url=base, headers={"X-API-Key": LONG_KEY_A}, timeout=30) as client,
            sync_playwright() as pw,
        ):
            data = asset_bytes(tmp_path, size=32)
            job_id = post_asset(client, data, options={"method": "bicubic", "scale": 2}).json()[
                "id"
            ]
            wait_until(
                lambda: client.get(f"/v1/jobs/{job_id}").json()["status"] == "finished",
                120,
                "the job to finish",
                0.5,
            )
            stored = raw.get_object("dash", f"jobs/{job_id}/result.zip").read()
            browser = pw.chromium.launch(
                executable_path=str(CHROMIUM), args=CHROMIUM_ARGS, headless=True
            )
            try:
                page = browser.new_page(accept_downloads=True)
                page.add_init_script(f"localStorage.setItem('pbrsr-api-key', '{LONG_KEY_A}')")
                errors: list[str] = []
                page.on("pageerror", lambda exc: errors.append(str(exc)))
                to_bucket: list = []
                page.on(
                    "request", lambda req: req.url.startswith(endpoint) and to_bucket.append(req)
                )
                page.goto(base + "/")
                page.click(f".job-row[data-id='{job_id}']")
                page.wait_for_selector("#thumbs img")
                page.wait_for_selector("#crops-box:not([hidden]) .wipe")
                # the thumbnails load lazily: under the 3D view and the crops, once on screen
                page.locator("#thumbs").scroll_into_view_if_needed()
                page.wait_for_function(
                    "[...document.querySelectorAll('#thumbs img, #crops img')]"
                    ".every(i => i.complete && i.naturalWidth > 0)"
                )
                page.locator("#preview-pairs").scroll_into_view_if_needed()
                page.wait_for_function(
                    "[...document.querySelectorAll('#preview-pairs img')]"
                    ".every(i => i.complete && i.naturalWidth > 0)"
                )
                page.locator("#model-view").scroll_into_view_if_needed()
                page.wait_for_function(
                    "['ready', 'error'].includes(document.getElementById('model-view')"
                    ".dataset.state)",
                    timeout=30_000,
                )
                assert page.get_attribute("#model-view", "data-state") == "ready", (
                    page.get_attribute("#model-view", "data-error")
                )
                model_key = f"/dash/jobs/{job_id}/output/asset.glb?"
                assert any(model_key in r.url for r in to_bucket)
                with page.expect_download() as info:
                    page.click("#download")
                assert Path(info.value.path()).read_bytes() == stored
                assert to_bucket, "the images and the bundle come from the bucket"
                sent = [r.all_headers() for r in to_bucket]  # what went on the wire
                assert not [h for h in sent if "x-api-key" in h]
                assert errors == []
            finally:
                browser.close()
    finally:
        s3.stop()
        cleanup_redis(settings)
