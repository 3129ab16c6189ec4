"""The REST API against the real Redis (no worker): submit, validate, list, cancel, keys,
problem bodies, health, metrics, expiry."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from rq import Queue
from rq.job import Job

from pbrsr_jobs.objstore import FilesystemStore
from pbrsr_jobs.store import JobFiles, JobIndex, JobLayout, sweep_expired
from service.app import create_app
from tests.service_support import (
    LONG_KEY_A,
    LONG_KEY_B,
    asset_bytes,
    cleanup_redis,
    gltf_zip_bytes,
    make_settings,
    post_asset,
    redis_client,
    settings_scope,
)


@pytest.fixture
def settings(tmp_path):
    yield from settings_scope(tmp_path)


def _problem_ok(resp, status: int, code: str | None = None) -> dict:
    assert resp.status_code == status, resp.text
    assert resp.headers["content-type"].startswith("application/problem+json")
    body = resp.json()
    assert {"type", "title", "status", "detail", "code"} <= body.keys()
    assert body["status"] == status
    if code is not None:
        assert body["code"] == code, body
    text = resp.text
    assert "Traceback" not in text and "/tmp" not in text and "/work" not in text
    assert str(Path.home()) not in text
    return body


def test_health_ready_and_openapi(client):
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz")
    assert ready.status_code == 200 and ready.json() == {
        "status": "ready",
        "redis": True,
        "storage": True,
    }
    spec = client.get("/openapi.json").json()
    for path in (
        "/v1/jobs",
        "/v1/jobs/{job_id}",
        "/v1/jobs/{job_id}/result",
        "/v1/jobs/{job_id}/previews/{name}",
        "/v1/jobs/{job_id}/crops",
        "/v1/jobs/{job_id}/crops/{name}",
        "/v1/jobs/{job_id}/files/{path}",
        "/healthz",
        "/readyz",
        "/metrics",
    ):
        assert path in spec["paths"], path
    body = spec["paths"]["/v1/jobs"]["post"]["requestBody"]["content"]["multipart/form-data"]
    assert body["schema"]["properties"]["file"]["format"] == "binary"
    assert client.get("/docs").status_code == 200


def test_readyz_503_when_redis_unreachable(tmp_path):
    bad = make_settings(tmp_path, redis_url="redis://127.0.0.1:1/0")
    with TestClient(create_app(bad), raise_server_exceptions=False) as c:
        r = c.get("/readyz")
        assert r.status_code == 503
        assert r.json() == {"status": "unavailable", "redis": False, "storage": True}
        _problem_ok(c.get("/v1/jobs"), 503, "queue-unavailable")


def test_submit_glb_is_validated_stored_and_queued(client, settings, tmp_path):
    r = post_asset(
        client,
        asset_bytes(tmp_path),
        filename="../../etc/My Chair.glb",
        options={"scale": 2, "method": "bicubic"},
    )
    assert r.status_code == 202, r.text
    body = r.json()
    job_id = body["id"]
    assert body["status"] == "queued"
    assert body["links"]["self"] == f"/v1/jobs/{job_id}"
    assert r.headers["location"] == f"/v1/jobs/{job_id}"

    layout = JobLayout(settings.storage_dir)
    stored = sorted(
        p.relative_to(layout.job_dir(job_id)).as_posix() for p in layout.job_dir(job_id).rglob("*")
    )
    assert stored == ["input", "input/asset.glb", "job.json"]  # generated names only
    assert list(layout.uploads_dir().iterdir()) == []  # the streamed upload was moved
    manifest = JobFiles(FilesystemStore(settings.storage_dir)).read_manifest(job_id)
    assert manifest.options["scale"] == 2 and manifest.options["method"] == "bicubic"
    assert manifest.name == "My_Chair.glb"  # display only, sanitised

    job = Job.fetch(job_id, connection=redis_client())
    assert job.func_name == "worker.tasks.run_job" and job.args == (job_id,)
    assert job.retries_left == settings.job_retries
    assert Queue(settings.queue, connection=redis_client()).count == 1

    detail = client.get(f"/v1/jobs/{job_id}").json()
    assert detail["status"] == "queued" and detail["name"] == "My_Chair.glb"
    assert detail["options"]["scale"] == 2
    _problem_ok(client.get(f"/v1/jobs/{job_id}/result"), 409, "not-finished")


def test_submit_zip_of_gltf(client, settings, tmp_path):
    r = post_asset(
        client, gltf_zip_bytes(tmp_path), filename="bundle.zip", options={"method": "bicubic"}
    )
    assert r.status_code == 202, r.text
    manifest = JobFiles(FilesystemStore(settings.storage_dir)).read_manifest(r.json()["id"])
    assert manifest.kind == "zip"
    assert manifest.input == "model/asset.gltf"
    job_dir = JobLayout(settings.storage_dir).job_dir(manifest.id)
    assert (job_dir / "input" / manifest.input).is_file()


def _bad_cases(tmp_path: Path) -> list[tuple[str, bytes, str | dict | None, int, str]]:
    from pbrsr_core.asset import make_quad_asset

    glb = asset_bytes(tmp_path)
    bare = make_quad_asset(tmp_path / "bare.glb", maps={}).read_bytes()
    return [
        ("empty", b"", None, 400, "invalid-asset"),
        # a NUL first: random bytes that happen to start with "{" would be sniffed as glTF JSON
        ("random bytes", b"\x00" + os.urandom(4095), None, 415, "unsupported-asset"),
        ("truncated glb", glb[: len(glb) // 2], None, 400, "invalid-asset"),
        ("json that is not gltf", b'{"hello": 1}', None, 400, None),
        ("options not json", glb, "{scale: 4", 422, "invalid-options"),
        ("unknown option", glb, {"scael": 4}, 422, "invalid-options"),
        ("bad scale", glb, {"scale": 3}, 422, "invalid-options"),
        ("device per job", glb, {"device": "cuda:0"}, 422, "invalid-options"),
        ("envmap path", glb, {"envmap": "/etc/passwd"}, 422, "invalid-options"),
        ("prior path", glb, {"prior": "spandrel:../../x.pth"}, 422, "invalid-options"),
        ("nothing to upscale", bare, None, 422, "unprocessable-asset"),
        ("max_size 1", glb, {"max_size": 1}, 422, "invalid-options"),
        ("unknown LR kernel", glb, {"lr_kernel": "box"}, 422, "invalid-options"),
        ("max_size under every x2", glb, {"max_size": 3}, 422, "unprocessable-asset"),
        ("unknown map role", glb, {"maps": ["albedo"]}, 422, "invalid-options"),
        ("maps the asset lacks", glb, {"maps": ["clearcoat"]}, 422, "unprocessable-asset"),
        (
            "unknown other_maps",
            glb,
            {"maps": ["normal"], "other_maps": "smear"},
            422,
            "invalid-options",
        ),
    ]


def test_bad_uploads_get_problem_bodies_and_leave_nothing(client, settings, tmp_path):
    layout = JobLayout(settings.storage_dir)
    for label, data, options, status, code in _bad_cases(tmp_path):
        r = post_asset(client, data, options=options)
        body = _problem_ok(r, status, code)
        assert len(body["detail"]) > 10, label
    assert list((settings.storage_dir / "jobs").iterdir()) == []
    assert list(layout.uploads_dir().iterdir()) == []
    assert Queue(settings.queue, connection=redis_client()).count == 0


def test_request_shape_errors(client):
    _problem_ok(
        client.post(
            "/v1/jobs", content=b"abc", headers={"content-type": "application/octet-stream"}
        ),
        415,
    )
    r = client.post("/v1/jobs", data={"options": "{}"}, files={"other": ("x", b"1")})
    _problem_ok(r, 400, "bad-request")
    _problem_ok(client.get("/v1/jobs?limit=0"), 422, "invalid-request")
    _problem_ok(client.get("/v1/jobs?status=sleeping"), 422, "invalid-request")
    _problem_ok(client.get("/v1/jobs/not-a-job"), 404, "not-found")
    _problem_ok(client.get("/v1/jobs/" + "0" * 32), 404, "not-found")
    _problem_ok(client.get("/nowhere"), 404)


def test_upload_over_limit_is_413(tmp_path):
    small = make_settings(tmp_path, max_upload_mb=0.05)
    try:
        with TestClient(create_app(small), raise_server_exceptions=False) as c:
            r = post_asset(c, os.urandom(200_000))
            body = _problem_ok(r, 413, "limit-exceeded")
            assert "0.05 MB" in body["detail"]
            assert list(JobLayout(small.storage_dir).uploads_dir().iterdir()) == []
    finally:
        cleanup_redis(small)


def test_api_keys_isolate_jobs(tmp_path):
    keyed = make_settings(tmp_path, api_keys=[LONG_KEY_A, LONG_KEY_B])
    a, b = {"X-API-Key": LONG_KEY_A}, {"X-API-Key": LONG_KEY_B}
    try:
        with TestClient(create_app(keyed), raise_server_exceptions=False) as c:
            data = asset_bytes(tmp_path)
            _problem_ok(post_asset(c, data), 401, "unauthorized")
            _problem_ok(post_asset(c, data, headers={"X-API-Key": "wrong-key-0123456789"}), 401)
            _problem_ok(c.get("/v1/jobs"), 401)
            job_id = post_asset(c, data, headers=a).json()["id"]
            assert c.get(f"/v1/jobs/{job_id}", headers=a).status_code == 200
            for method, path in (
                ("GET", ""),
                ("GET", "/result"),
                ("DELETE", ""),
                ("GET", "/previews/preview.png"),
                ("GET", "/thumbs/x.png"),
                ("GET", "/crops"),
                ("GET", "/crops/x.png"),
                ("GET", "/files/asset.glb"),
            ):
                r = c.request(method, f"/v1/jobs/{job_id}{path}", headers=b)
                _problem_ok(r, 404, "not-found")
            assert c.get("/v1/jobs", headers=b).json()["total"] == 0
            assert [j["id"] for j in c.get("/v1/jobs", headers=a).json()["items"]] == [job_id]
            # the health and metrics endpoints stay open
            assert c.get("/healthz").status_code == 200
            assert c.get("/metrics").status_code == 200
    finally:
        cleanup_redis(keyed)


def test_list_paginates_and_filters(client, tmp_path):
    data = asset_bytes(tmp_path)
    ids = [post_asset(client, data, options={"method": "bicubic"}).json()["id"] for _ in range(3)]
    page = client.get("/v1/jobs?limit=2").json()
    assert page["total"] == 3 and len(page["items"]) == 2
    assert [j["id"] for j in page["items"]] == ids[::-1][:2]  # newest first
    assert page["next"] == "/v1/jobs?offset=2&limit=2"
    rest = client.get(page["next"]).json()
    assert [j["id"] for j in rest["items"]] == [ids[0]] and rest["next"] is None

    assert client.delete(f"/v1/jobs/{ids[1]}").json()["status"] == "canceled"
    canceled = client.get("/v1/jobs?status=canceled").json()
    assert canceled["total"] == 1 and canceled["items"][0]["id"] == ids[1]
    queued = client.get("/v1/jobs?status=queued&limit=1").json()
    assert queued["total"] == 2 and queued["next"] == "/v1/jobs?offset=1&limit=1&status=queued"


def test_cancel_queued_then_delete(client, settings, tmp_path):
    job_id = post_asset(client, asset_bytes(tmp_path)).json()["id"]
    r = client.delete(f"/v1/jobs/{job_id}")
    assert r.status_code == 202 and r.json()["status"] == "canceled"
    assert Queue(settings.queue, connection=redis_client()).count == 0
    _problem_ok(client.get(f"/v1/jobs/{job_id}/result"), 409)
    # a second DELETE on an ended job removes it and its files
    assert client.delete(f"/v1/jobs/{job_id}").status_code == 204
    _problem_ok(client.get(f"/v1/jobs/{job_id}"), 404)
    assert not JobLayout(settings.storage_dir).job_dir(job_id).exists()


def test_preview_names_never_become_paths(client, settings, tmp_path):
    job_id = post_asset(client, asset_bytes(tmp_path)).json()["id"]
    out = JobLayout(settings.storage_dir).job_dir(job_id) / "output"
    (out / "previews").mkdir(parents=True)
    (out / "previews" / "after_studio.png").write_bytes(b"\x89PNG fake")
    for name in ("..%2Fjob.json", "%2E%2E%2F%2E%2E%2Fjob.json", "job.json", ".hidden.png"):
        r = client.get(f"/v1/jobs/{job_id}/previews/{name}")
        assert r.status_code == 404, name
    # listed files are served only once the job has finished
    _problem_ok(client.get(f"/v1/jobs/{job_id}/previews/nope.png"), 404)


def test_crops_and_files_wait_for_the_end_and_serve_only_recorded_names(client, settings, tmp_path):
    job_id = post_asset(client, asset_bytes(tmp_path)).json()["id"]
    base = f"/v1/jobs/{job_id}"
    _problem_ok(client.get(f"{base}/crops"), 409, "not-finished")
    _problem_ok(client.get(f"{base}/files/asset.glb"), 409, "not-finished")
    job_dir = JobLayout(settings.storage_dir).job_dir(job_id)  # the filesystem store's objects
    crops, out = job_dir / "crops", job_dir / "output"
    crops.mkdir(parents=True)
    out.mkdir(parents=True)
    for name in ("00_normal_n_lr.png", "00_normal_n_hr.png", "stray.png"):
        (crops / name).write_bytes(b"\x89PNG fake")
    (out / "asset.glb").write_bytes(b"glTF fake")
    (out / ".hidden.glb").write_bytes(b"glTF fake")
    entry = {
        "map": "00_normal_n",
        "label": "normal",
        "scale": 2,
        "lr_region": [4, 4, 8, 8],
        "hr_region": [8, 8, 16, 16],
        "lr_size": [16, 16],
        "hr_size": [32, 32],
        "lr": "00_normal_n_lr.png",
        "hr": "00_normal_n_hr.png",
    }
    job = Job.fetch(job_id, connection=redis_client())
    job.meta.update(
        state="finished",
        files={"previews": [], "thumbs": [], "crops": [entry, {"map": 3}], "model": "asset.glb"},
    )
    job.save_meta()
    job.set_status("finished")
    links = client.get(base).json()["links"]
    assert links["crops"] == f"{base}/crops" and links["model"] == f"{base}/files/asset.glb"
    items = client.get(links["crops"]).json()["items"]  # the malformed entry left out
    assert items == [{**entry, "lr": f"{base}/crops/00_normal_n_lr.png",
                      "hr": f"{base}/crops/00_normal_n_hr.png"}]  # fmt: skip
    assert client.get(items[0]["hr"]).content == b"\x89PNG fake"
    assert client.get(links["model"]).headers["content-type"] == "model/gltf-binary"
    for name in ("stray.png", "..%2Fjob.json", "%2E%2E%2Fcrops%2Fstray.png"):
        _problem_ok(client.get(f"{base}/crops/{name}"), 404)
    for path in (".hidden.glb", "..%2Fjob.json", "%2E%2E%2Finput", "input%2Fasset.glb"):
        _problem_ok(client.get(f"{base}/files/{path}"), 404)


def test_the_3d_viewer_library_comes_from_the_npm_packages(client, tmp_path):
    r = client.get("/vendor/three/build/three.module.js")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/javascript")
    assert b"./three.core.js" in r.content
    assert client.get("/vendor/three/examples/jsm/loaders/GLTFLoader.js").status_code == 200
    wasm = client.get("/vendor/three/examples/jsm/libs/draco/gltf/draco_decoder.wasm")
    assert wasm.headers["content-type"] == "application/wasm" and wasm.content[:4] == b"\0asm"
    for path in ("package.json", "..%2F..%2Fpackage.json", "src/Three.js"):
        _problem_ok(client.get(f"/vendor/three/{path}"), 404)
    bare = make_settings(tmp_path, npm_dir=tmp_path / "no-node-modules")
    with TestClient(create_app(bare), raise_server_exceptions=False) as c:
        body = _problem_ok(c.get("/vendor/three/build/three.module.js"), 404)
        assert "scripts/setup" in body["detail"]


def test_cors_off_by_default_and_on_when_configured(client, tmp_path):
    origin = {"Origin": "http://example.test"}
    assert "access-control-allow-origin" not in client.get("/v1/jobs", headers=origin).headers
    cors = make_settings(tmp_path, cors_origins=["http://example.test"])
    try:
        with TestClient(create_app(cors)) as c:
            r = c.get("/v1/jobs", headers=origin)
            assert r.headers["access-control-allow-origin"] == "http://example.test"
            other = c.get("/v1/jobs", headers={"Origin": "http://evil.test"})
            assert "access-control-allow-origin" not in other.headers
    finally:
        cleanup_redis(cors)


def test_metrics_report_queue_depth(client, tmp_path):
    data = asset_bytes(tmp_path)
    for _ in range(2):
        post_asset(client, data)
    text = client.get("/metrics").text
    assert 'pbrsr_jobs{state="queued"} 2.0' in text
    assert f'pbrsr_queue_depth{{queue="{client.app.state.settings.queue}"}} 2.0' in text
    assert "pbrsr_redis_up 1.0" in text
    assert 'pbrsr_http_requests_total{method="POST",status="2xx"} 2.0' in text


def test_large_jobs_go_to_the_large_queue(tmp_path):
    gen = settings_scope(tmp_path, large_job_mpix=0.001)
    settings = next(gen)
    try:
        with TestClient(create_app(settings), raise_server_exceptions=False) as c:
            job_id = post_asset(c, asset_bytes(tmp_path)).json()["id"]
        redis = redis_client()
        assert Job.fetch(job_id, connection=redis).origin == settings.large_queue
        assert Queue(settings.large_queue, connection=redis).count == 1
        assert Queue(settings.queue, connection=redis).count == 0
        q, big = settings.queue, settings.large_queue
        assert settings.listen_queues("small") == [f"{q}-high", q, f"{q}-low"]
        assert settings.listen_queues("all") == [
            f"{q}-high", f"{big}-high", q, big, f"{q}-low", f"{big}-low"
        ]  # fmt: skip
        assert settings.queue_for(0.0001, "high") == f"{q}-high"
        assert settings.queue_for(1.0, "low") == f"{big}-low"
    finally:
        next(gen, None)


def test_max_size_is_stored_and_sizes_the_job_for_its_queue(tmp_path):
    """A job's size (output megapixels, which picks the queue) counts each map at the factor
    max_size leaves it."""
    from pbrsr_core.asset import load_asset

    data = asset_bytes(tmp_path)
    (tmp_path / "a.glb").write_bytes(data)
    sides = [max(i.width, i.height) for i in load_asset(tmp_path / "a.glb").images if i.roles]
    cap = 2 * max(sides)  # the largest maps at x2, none kept
    gen = settings_scope(tmp_path, large_job_mpix=sum(s * s for s in sides) * 8 / 1e6)
    settings = next(gen)
    try:
        with TestClient(create_app(settings), raise_server_exceptions=False) as c:
            full = post_asset(c, data, options={"scale": 4, "method": "bicubic"}).json()["id"]
            capped = post_asset(
                c, data, options={"scale": 4, "method": "bicubic", "max_size": cap}
            ).json()["id"]
        redis = redis_client()
        assert Job.fetch(full, connection=redis).origin == settings.large_queue
        assert Job.fetch(capped, connection=redis).origin == settings.queue
        manifest = JobFiles(FilesystemStore(settings.storage_dir)).read_manifest(capped)
        assert manifest.options["max_size"] == cap
    finally:
        next(gen, None)


def test_maps_is_stored_and_sizes_the_job_by_the_maps_it_upscales(tmp_path):
    """A job's size (output megapixels) counts the maps ``maps`` does not list at their own
    size: with every map at x4 the job goes to the large queue, with the base colour alone to
    the default one."""
    from pbrsr_core.asset import load_asset

    data = asset_bytes(tmp_path)
    (tmp_path / "a.glb").write_bytes(data)
    images = [i for i in load_asset(tmp_path / "a.glb").images if i.roles]
    some_mpix = sum(i.width * i.height * (16 if "base_color" in i.roles else 1) for i in images)
    assert len(images) > 1 and some_mpix < sum(i.width * i.height * 16 for i in images)
    gen = settings_scope(tmp_path, large_job_mpix=some_mpix * 1.01 / 1e6)
    settings = next(gen)
    try:
        with TestClient(create_app(settings), raise_server_exceptions=False) as c:
            full = post_asset(c, data, options={"method": "bicubic"}).json()["id"]
            some = post_asset(
                c, data, options={"method": "bicubic", "maps": ["base_color"]}
            ).json()["id"]
            rest = {"method": "bicubic", "maps": ["base_color"], "other_maps": "bicubic"}
            rest_bicubic = post_asset(c, data, options=rest).json()["id"]
        redis = redis_client()
        assert Job.fetch(full, connection=redis).origin == settings.large_queue
        assert Job.fetch(some, connection=redis).origin == settings.queue
        # the maps bicubic upscales count at their output size
        assert Job.fetch(rest_bicubic, connection=redis).origin == settings.large_queue
        files = JobFiles(FilesystemStore(settings.storage_dir))
        assert files.read_manifest(some).options["maps"] == ["base_color"]
        assert files.read_manifest(some).options["other_maps"] == "keep"
        assert files.read_manifest(rest_bicubic).options["other_maps"] == "bicubic"
    finally:
        next(gen, None)


def test_priority_picks_the_queue_and_a_bad_one_is_refused(client, settings, tmp_path):
    redis = redis_client()
    ids = {}
    for priority in ("high", "normal", "low"):
        r = client.post(
            "/v1/jobs",
            files={"file": ("a.glb", asset_bytes(tmp_path), "application/octet-stream")},
            data={"priority": priority},
        )
        assert r.status_code == 202, r.text
        ids[priority] = r.json()["id"]
    q = settings.queue
    want = {"high": f"{q}-high", "normal": q, "low": f"{q}-low"}
    for priority, job_id in ids.items():
        job = Job.fetch(job_id, connection=redis)
        assert job.origin == want[priority] and job.meta["priority"] == priority
    default = post_asset(client, asset_bytes(tmp_path)).json()["id"]
    assert Job.fetch(default, connection=redis).origin == q
    bad = client.post(
        "/v1/jobs",
        files={"file": ("a.glb", asset_bytes(tmp_path), "application/octet-stream")},
        data={"priority": "urgent"},
    )
    body = _problem_ok(bad, 422)
    assert "priority must be one of high, normal, low" in body["detail"]


def test_sweep_expires_old_jobs_only(client, settings, tmp_path):
    data = asset_bytes(tmp_path)
    old, fresh = (post_asset(client, data).json()["id"] for _ in range(2))
    for job_id in (old, fresh):
        client.delete(f"/v1/jobs/{job_id}")  # canceled: terminal
    redis = redis_client()
    job = Job.fetch(old, connection=redis)
    job.meta["ended_at"] = time.time() - settings.retention_s - 10
    job.save_meta()
    layout = JobLayout(settings.storage_dir)
    index = JobIndex(redis, settings.key_prefix)
    files = JobFiles(FilesystemStore(settings.storage_dir))
    removed = sweep_expired(redis, index, layout, files, settings.retention_s)
    assert removed == [old]
    assert not layout.job_dir(old).exists() and layout.job_dir(fresh).exists()
    assert client.get(f"/v1/jobs/{old}").status_code == 404
    assert client.get(f"/v1/jobs/{fresh}").json()["status"] == "canceled"
    assert [i for i, _ in index.all_ids()] == [fresh]


def test_problem_body_for_internal_errors_hides_details(client, monkeypatch, tmp_path):
    import service.intake as intake

    def boom(*_a, **_k):
        raise RuntimeError(f"secret at {tmp_path}/x")

    monkeypatch.setattr(intake, "check_asset", boom)
    r = post_asset(client, asset_bytes(tmp_path))
    body = _problem_ok(r, 500, "internal-error")
    assert "secret" not in json.dumps(body) and "reference" in body["detail"]


def test_status_of_a_finished_job_lists_no_folder_and_drops_bad_history_points(
    client, settings, tmp_path, monkeypatch
):
    job_id = post_asset(client, asset_bytes(tmp_path)).json()["id"]
    job = Job.fetch(job_id, connection=redis_client())
    good = {"t": 1.0, "stage": "optimize", "step": 3, "losses": {"total": 0.5}, "metrics": {}}
    job.meta.update(
        state="finished",
        files={"previews": ["preview.png"], "thumbs": ["00_albedo.png"]},
        history=[good, {"t": "soon", "stage": "x"}, {**good, "step": 4}],
    )
    job.save_meta()
    job.set_status("finished")

    def no_listing(*args, **kwargs):
        raise AssertionError("a status read listed a folder")

    monkeypatch.setattr(FilesystemStore, "list", no_listing)
    body = client.get(f"/v1/jobs/{job_id}").json()
    assert body["status"] == "finished"
    base = f"/v1/jobs/{job_id}"
    assert body["links"]["thumbs"] == {"00_albedo.png": f"{base}/thumbs/00_albedo.png"}
    assert body["links"]["previews"] == {"preview.png": f"{base}/previews/preview.png"}
    assert [p["step"] for p in body["history"]] == [3, 4]  # the malformed point left out
    listed = client.get("/v1/jobs").json()["items"]
    assert listed[0]["links"]["thumbs"] == body["links"]["thumbs"]


def test_a_key_over_its_active_jobs_gets_429_and_a_full_queue_503(tmp_path):
    gen = settings_scope(
        tmp_path, api_keys=[LONG_KEY_A, LONG_KEY_B], max_active_jobs_per_key=2, max_queued_jobs=3
    )
    settings = next(gen)
    a, b = {"X-API-Key": LONG_KEY_A}, {"X-API-Key": LONG_KEY_B}
    try:
        with TestClient(create_app(settings), raise_server_exceptions=False) as c:
            for _ in range(2):
                assert post_asset(c, asset_bytes(tmp_path), headers=a).status_code == 202
            over = post_asset(c, asset_bytes(tmp_path), headers=a)
            body = _problem_ok(over, 429, "too-many-jobs")
            assert (
                over.headers["Retry-After"] == "30" and "2 jobs queued or running" in body["detail"]
            )
            assert post_asset(c, asset_bytes(tmp_path), headers=b).status_code == 202  # its own
            full = post_asset(c, asset_bytes(tmp_path), headers=b)  # 3 waiting in all
            _problem_ok(full, 503, "queue-full")
            assert full.headers["Retry-After"] == "30"
            # a canceled job frees its place
            first = c.get("/v1/jobs", headers=a).json()["items"][0]["id"]
            assert c.delete(f"/v1/jobs/{first}", headers=a).status_code == 202
            assert post_asset(c, asset_bytes(tmp_path), headers=a).status_code == 202
            assert len(list((settings.storage_dir / "uploads").iterdir())) == 0  # nothing kept
    finally:
        next(gen, None)
