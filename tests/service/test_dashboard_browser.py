"""The dashboard end to end in headless Chromium (Debian's /usr/bin/chromium, driven by
Playwright): a real ``pbrsr serve`` and ``pbrsr worker`` on localhost; drop a procedural
asset on the page, watch the progress bar move (pushed by the event stream), see the job
finish, download the bundle.
The screenshot is kept as test-artifacts/dashboard.png."""

from __future__ import annotations

import base64
import io
import time
import zipfile
from pathlib import Path

import pytest

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
]
ARTIFACTS = REPO / "test-artifacts"

DROP_FILE = """([b64, name]) => {
  const bytes = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
  const dt = new DataTransfer();
  dt.items.add(new File([bytes], name, { type: "model/gltf-binary" }));
  return dt;
}"""


@pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian's chromium is not installed")
def test_dashboard_upload_progress_finish_download(tmp_path):
    from playwright.sync_api import sync_playwright

    settings = make_settings(tmp_path)
    ARTIFACTS.mkdir(exist_ok=True)
    data = asset_bytes(tmp_path, size=32)
    try:
        with (
            worker_process(settings, tmp_path / "worker.log"),
            api_server(settings, tmp_path / "api.log") as base,
            sync_playwright() as pw,
        ):
            browser = pw.chromium.launch(
                executable_path=str(CHROMIUM), args=CHROMIUM_ARGS, headless=True
            )
            try:
                page = browser.new_page(
                    viewport={"width": 1360, "height": 1000}, accept_downloads=True
                )
                errors: list[str] = []
                page.on("pageerror", lambda exc: errors.append(str(exc)))
                requests: list[str] = []
                page.on("request", lambda req: requests.append(req.url))
                page.goto(base + "/")
                assert page.title().startswith("pbrsr")
                # the page follows the key's event stream instead of polling
                page.wait_for_function("document.body.dataset.events === 'live'")
                assert page.is_disabled("#submit")

                # drag and drop the asset onto the drop zone, pick options, submit
                dt = page.evaluate_handle(DROP_FILE, [base64.b64encode(data).decode(), "chair.glb"])
                page.dispatch_event("#drop-zone", "drop", {"dataTransfer": dt})
                assert "chair.glb" in page.inner_text("#drop-text")
                # quality's stages (prior, views, 25 steps) report progress for seconds; a
                # bicubic job of this asset can start and end between two polls of the page
                page.select_option("#opt-method", "pbrsr")
                page.select_option("#opt-preset", "quality")
                page.select_option("#opt-scale", "2")
                page.click("#submit")
                page.wait_for_selector("#job-view:not([hidden])")
                page.wait_for_selector(".job-row[data-status]")
                assert page.inner_text("#job-name") == "chair.glb"

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
                page.wait_for_function(
                    "document.getElementById('progress-bar').style.width === '100%'"
                )
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
                assert page.is_hidden("#cancel") and page.is_hidden("#auth")
                page.wait_for_timeout(600)  # let the bar's CSS transition end
                page.screenshot(path=str(ARTIFACTS / "dashboard.png"), full_page=True)

                with page.expect_download() as info:
                    page.click("#download")
                path = info.value.path()
                assert info.value.suggested_filename.endswith("-pbrsr-x2.zip")
                names = zipfile.ZipFile(io.BytesIO(Path(path).read_bytes())).namelist()
                assert "asset.glb" in names and "report.json" in names
                assert errors == []
            finally:
                browser.close()
    finally:
        cleanup_redis(settings)


@pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian's chromium is not installed")
def test_dashboard_with_a_key_and_s3_storage_never_sends_the_key_to_the_bucket(tmp_path):
    """Images and the download come from presigned URLs the page asks for as JSON: the API
    key stays with the API, and the bucket needs no CORS rules."""
    import httpx
    from minio import Minio
    from moto.server import ThreadedMotoServer
    from playwright.sync_api import sync_playwright

    from tests.service_support import LONG_KEY_A, free_port, post_asset, wait_for

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
            wait_for(
                lambda: client.get(f"/v1/jobs/{job_id}").json()["status"] == "finished",
                120,
                0.5,
                "the job to finish",
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
                page.wait_for_function(
                    "[...document.querySelectorAll('#preview-pairs img, #thumbs img')]"
                    ".every(i => i.complete && i.naturalWidth > 0)"
                )
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
