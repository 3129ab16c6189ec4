"""The object stores behind job storage, against a real S3 server (moto's, over HTTP on
localhost, started here) and a real folder: the store contract for both, clear errors for a
missing bucket, refused credentials and an endpoint that is down, and a whole job and a batch
through the API and a ``pbrsr worker --burst`` process that share nothing but Redis and the
bucket."""

from __future__ import annotations

import io
import json
import subprocess
import uuid
import zipfile
from pathlib import Path

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image
from pydantic import ValidationError
from rq import Queue

from pbrsr_bench.load import free_port
from pbrsr_jobs.objstore import FilesystemStore, S3Store, StoreUnavailable, open_store
from pbrsr_jobs.settings import Settings
from service.app import create_app
from tests.service.test_batches import post_batch
from tests.service_support import (
    PBRSR,
    REPO,
    asset_bytes,
    cleanup_redis,
    gltf_zip_bytes,
    make_settings,
    post_asset,
    redis_client,
    settings_env,
    worker_process,
)

ACCESS, SECRET = "pbrsr-test-access", "pbrsr-test-secret-0123456789"


@pytest.fixture(scope="module")
def s3_endpoint():
    from moto.server import ThreadedMotoServer

    port = free_port()
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.stop()


def _raw_client(endpoint: str):
    from minio import Minio

    return Minio(endpoint.split("://", 1)[1], ACCESS, SECRET, secure=False, region="us-east-1")


@pytest.fixture
def bucket(s3_endpoint):
    name = f"pbrsr-{uuid.uuid4().hex[:12]}"
    _raw_client(s3_endpoint).make_bucket(name)
    return name


def _s3_settings(tmp_path: Path, endpoint: str, bucket: str, **overrides) -> Settings:
    values = {
        "storage_backend": "s3",
        "s3_endpoint_url": endpoint,
        "s3_bucket": bucket,
        "s3_access_key": ACCESS,
        "s3_secret_key": SECRET,
        "s3_key_prefix": "farm-a/",
        **overrides,
    }
    return make_settings(tmp_path, **values)


@pytest.fixture(params=["filesystem", "s3"])
def store(request, tmp_path):
    if request.param == "filesystem":
        return FilesystemStore(tmp_path / "objects")
    endpoint = request.getfixturevalue("s3_endpoint")
    name = request.getfixturevalue("bucket")
    return open_store(_s3_settings(tmp_path, endpoint, name))


def test_store_contract(store, tmp_path):
    store.check()
    src = tmp_path / "src.bin"
    src.write_bytes(b"\x00\x01" * 5000)
    store.put_file("jobs/a/input/model/asset.gltf", src)
    store.put_bytes("jobs/a/job.json", b'{"id": "a"}')
    store.put_bytes("jobs/b/job.json", b"{}")
    assert store.get_bytes("jobs/a/job.json") == b'{"id": "a"}'
    store.get_file("jobs/a/input/model/asset.gltf", tmp_path / "copy" / "asset.gltf")
    assert (tmp_path / "copy" / "asset.gltf").read_bytes() == src.read_bytes()
    assert store.list("jobs/a/") == ["jobs/a/input/model/asset.gltf", "jobs/a/job.json"]
    assert store.list("jobs/none/") == []
    assert store.exists("jobs/a/job.json") and not store.exists("jobs/a/nope")
    store.put_bytes("jobs/a/job.json", b"replaced")  # a put replaces the whole object
    assert store.get_bytes("jobs/a/job.json") == b"replaced"
    with pytest.raises(FileNotFoundError):
        store.get_bytes("jobs/a/missing.json")
    with pytest.raises(FileNotFoundError):
        store.get_file("jobs/a/missing.json", tmp_path / "missing")
    for bad in ("../x", "jobs//x", "/abs", "jobs/.hidden", ""):
        with pytest.raises(ValueError):
            store.put_bytes(bad, b"x")
    with pytest.raises(ValueError):
        store.list("jobs/a")  # a prefix is a folder

    url = store.url("jobs/a/job.json", filename="j.json", media_type="application/json")
    if isinstance(store, FilesystemStore):
        assert url is None and store.local_path("jobs/a/job.json").read_bytes() == b"replaced"
    else:
        assert store.local_path("jobs/a/job.json") is None
        r = httpx.get(url, timeout=10)  # presigned: no credentials needed
        assert r.status_code == 200 and r.content == b"replaced"
        assert r.headers["content-type"] == "application/json"
        # every object sits under the key prefix
        names = {
            o.object_name
            for o in _raw_client(store.endpoint_url).list_objects(store.bucket, recursive=True)
        }
        assert names == {
            "farm-a/jobs/a/input/model/asset.gltf",
            "farm-a/jobs/a/job.json",
            "farm-a/jobs/b/job.json",
        }

    store.delete("jobs/b/job.json")
    store.delete("jobs/b/job.json")  # missing is fine
    store.delete_prefix("jobs/a/")
    store.delete_prefix("jobs/a/")
    assert store.list("jobs/") == []


def test_a_result_is_stored_whole_or_not_at_all(store, tmp_path):
    from pbrsr_jobs.store import JobFiles

    files = JobFiles(store)
    job_id = uuid.uuid4().hex
    out, thumbs, crops = tmp_path / "out", tmp_path / "thumbs", tmp_path / "crops"
    (out / "previews").mkdir(parents=True)
    (out / "maps").mkdir()
    thumbs.mkdir()
    crops.mkdir()
    for path in (
        out / "preview.png",
        out / "previews" / "after_sky.png",
        out / "maps" / "00_albedo.png",
        thumbs / "a.png",
        crops / "00_albedo_lr.png",
    ):
        path.write_bytes(b"\x89PNG " + path.name.encode())
    (out / "asset.gltf").write_text("{}")
    (out / "previews" / ".partial.png").write_bytes(b"hidden")
    (crops / "crops.json").write_text("[]")  # the index goes to the job's meta, not the store
    bundle = tmp_path / "bundle.zip"
    bundle.write_bytes(b"PK first")
    names = files.publish_result(job_id, out, thumbs, crops, bundle)
    assert names == {"previews": ["preview.png", "after_sky.png"], "thumbs": ["a.png"]}
    assert files.preview_names(job_id) == names["previews"]
    assert files.thumb_names(job_id) == ["a.png"]
    assert files.output_files(job_id) == [
        "asset.gltf",
        "maps/00_albedo.png",
        "preview.png",
        "previews/after_sky.png",
    ]
    assert files.model_name(job_id) == "asset.gltf"
    assert store.list(f"jobs/{job_id}/crops/") == [f"jobs/{job_id}/crops/00_albedo_lr.png"]

    # a second attempt replaces the first: what it no longer makes is gone
    (out / "previews" / "after_sky.png").unlink()
    (thumbs / "a.png").rename(thumbs / "b.png")
    bundle.write_bytes(b"PK second")
    files.publish_result(job_id, out, thumbs, crops, bundle)
    assert files.preview_names(job_id) == ["preview.png"]
    assert files.thumb_names(job_id) == ["b.png"]
    assert store.get_bytes(files.bundle_key(job_id)) == b"PK second"

    # storing the bundle fails: nothing of the result is left
    with pytest.raises(OSError):
        files.publish_result(job_id, out, thumbs, crops, tmp_path / "never-written.zip")
    assert store.list(f"jobs/{job_id}/") == []


def test_presigned_urls_name_the_public_endpoint(s3_endpoint, bucket, tmp_path):
    port = s3_endpoint.rsplit(":", 1)[1]
    public = f"http://localhost:{port}"  # another name of the same server, as clients see it
    store = open_store(_s3_settings(tmp_path, s3_endpoint, bucket, s3_public_url=public))
    store.put_bytes("jobs/p/result.zip", b"PK public")
    url = store.url("jobs/p/result.zip", filename="r.zip", media_type="application/zip")
    assert url.startswith(f"{public}/{bucket}/farm-a/jobs/p/result.zip?")
    got = httpx.get(url, timeout=10)
    assert got.content == b"PK public"
    assert got.headers["content-disposition"] == 'attachment; filename="r.zip"'


def test_settings_for_s3_are_checked(tmp_path):
    with pytest.raises(ValidationError, match="PBRSR_S3_ENDPOINT_URL and PBRSR_S3_BUCKET"):
        Settings(_env_file=None, storage_backend="s3", s3_endpoint_url="http://h:9000")
    with pytest.raises(ValidationError, match="without a path"):
        Settings(_env_file=None, s3_endpoint_url="http://h:9000/bucket")
    with pytest.raises(ValidationError, match="without a path"):
        Settings(_env_file=None, s3_public_url="https://files.example.test/x?y=1")
    with pytest.raises(ValidationError, match="http"):
        Settings(_env_file=None, s3_endpoint_url="ftp://h")
    with pytest.raises(ValidationError):
        Settings(_env_file=None, storage_backend="nfs")
    s = Settings(
        _env_file=None,
        storage_backend="s3",
        s3_endpoint_url="https://s3.example.test/",
        s3_bucket="b",
        s3_secret_key="very-secret-value",
        s3_key_prefix="/team/a/",
    )
    assert s.s3_endpoint_url == "https://s3.example.test" and s.s3_key_prefix == "team/a/"
    assert "very-secret-value" not in repr(s) and "very-secret-value" not in str(s.model_dump())


def test_unusable_s3_gives_a_clear_error(s3_endpoint, bucket, tmp_path):
    missing = open_store(_s3_settings(tmp_path, s3_endpoint, "no-such-bucket"))
    with pytest.raises(StoreUnavailable, match="PBRSR_S3_BUCKET='no-such-bucket' does not"):
        missing.check()

    down = S3Store(
        f"http://127.0.0.1:{free_port()}",
        bucket,
        region="us-east-1",
        access_key=ACCESS,
        secret_key=SECRET,
        retries=0,
    )
    with pytest.raises(StoreUnavailable, match="cannot reach the S3 endpoint"):
        down.check()

    # moto checks signatures and keys once its authentication is on
    httpx.post(f"{s3_endpoint}/moto-api/reset-auth", content=b"0", timeout=10)
    try:
        wrong = open_store(
            _s3_settings(tmp_path, s3_endpoint, bucket, s3_access_key="AKIAWRONGKEY000000")
        )
        with pytest.raises(StoreUnavailable, match="refused the credentials") as err:
            wrong.check()
        assert "PBRSR_S3_ACCESS_KEY" in str(err.value) and SECRET not in str(err.value)
        with pytest.raises(StoreUnavailable, match="refused the credentials"):
            create_app(_s3_settings(tmp_path, s3_endpoint, bucket, s3_access_key="AKIAWRONG0"))
    finally:
        httpx.post(f"{s3_endpoint}/moto-api/reset-auth", content=b"inf", timeout=10)


@pytest.mark.parametrize("command", [["serve", "--port", "8765"], ["worker", "--burst"]])
def test_serve_and_worker_refuse_to_start_on_a_missing_bucket(s3_endpoint, tmp_path, command):
    settings = _s3_settings(tmp_path, s3_endpoint, "no-such-bucket")
    done = subprocess.run(
        [PBRSR, *command],
        env=settings_env(settings),
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2, done.stderr
    assert "job storage: the bucket PBRSR_S3_BUCKET='no-such-bucket' does not exist" in (
        done.stderr
    )
    assert SECRET not in done.stderr + done.stdout


def test_store_going_away_answers_503_and_leaves_nothing(s3_endpoint, bucket, tmp_path):
    settings = _s3_settings(tmp_path, s3_endpoint, bucket)
    try:
        with TestClient(create_app(settings), raise_server_exceptions=False) as client:
            assert client.get("/readyz").json()["storage"] is True
            _raw_client(s3_endpoint).remove_bucket(bucket)  # empty: the probes cleaned up
            r = post_asset(client, asset_bytes(tmp_path), options={"method": "bicubic"})
            assert r.status_code == 503, r.text
            body = r.json()
            assert body["code"] == "storage-unavailable" and r.headers["retry-after"] == "30"
            assert s3_endpoint not in body["detail"]  # no server details
            ready = client.get("/readyz")
            assert ready.status_code == 503 and ready.json()["storage"] is False
        local = settings.storage_dir
        assert list((local / "jobs").iterdir()) == [] and list((local / "uploads").iterdir()) == []
        assert Queue(settings.queue, connection=redis_client()).count == 0
    finally:
        cleanup_redis(settings)


@pytest.mark.slow
def test_a_job_through_s3_with_nothing_shared_but_the_bucket(s3_endpoint, bucket, tmp_path):
    api = _s3_settings(tmp_path / "api", s3_endpoint, bucket)
    worker = api.model_copy(update={"storage_dir": tmp_path / "worker" / "storage"})
    raw = _raw_client(s3_endpoint)
    try:
        with TestClient(create_app(api), raise_server_exceptions=False) as client:
            r = post_asset(client, asset_bytes(tmp_path), options={"method": "bicubic", "scale": 2})
            assert r.status_code == 202, r.text
            job_id = r.json()["id"]
            prefix = f"farm-a/jobs/{job_id}/"
            keys = sorted(o.object_name for o in raw.list_objects(bucket, prefix, recursive=True))
            assert keys == [prefix + "input/asset.glb", prefix + "job.json"]
            assert list((api.storage_dir / "jobs").iterdir()) == []  # nothing kept locally

            done = subprocess.run(
                [PBRSR, "worker", "--burst"],
                env=settings_env(worker),
                cwd=REPO,
                capture_output=True,
                text=True,
                timeout=300,
            )
            assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
            job = client.get(f"/v1/jobs/{job_id}").json()
            assert job["status"] == "finished", (job, done.stderr[-3000:])
            assert list((worker.storage_dir / "jobs").iterdir()) == []  # released

            r = client.get(f"/v1/jobs/{job_id}/result", follow_redirects=False)
            assert r.status_code == 307
            got = httpx.get(r.headers["location"], timeout=30)
            assert got.status_code == 200
            stored = raw.get_object(bucket, prefix + "result.zip").read()
            assert got.content == stored
            link = client.get(f"/v1/jobs/{job_id}/result?redirect=false")  # for keyed fetches
            assert link.status_code == 200 and link.json()["expires_in_s"] == 900
            assert httpx.get(link.json()["url"], timeout=30).content == stored
            names = zipfile.ZipFile(io.BytesIO(got.content)).namelist()
            assert "asset.glb" in names and "report.json" in names
            links = job["links"]
            assert "preview.png" in links["previews"] and links["thumbs"]
            for url in [*links["previews"].values(), *links["thumbs"].values()]:
                redirect = client.get(url, follow_redirects=False)
                assert redirect.status_code == 307, url
                png = httpx.get(redirect.headers["location"], timeout=30)
                assert png.status_code == 200 and png.content[:4] == b"\x89PNG"
            assert client.get(f"/v1/jobs/{job_id}/thumbs/job.json").status_code == 404

            assert client.delete(f"/v1/jobs/{job_id}").status_code == 204
            assert list(raw.list_objects(bucket, prefix, recursive=True)) == []
            assert client.get(f"/v1/jobs/{job_id}").status_code == 404
    finally:
        cleanup_redis(api)


@pytest.mark.slow
def test_a_batch_through_s3_and_its_deletion(s3_endpoint, bucket, tmp_path):
    api = _s3_settings(tmp_path / "api", s3_endpoint, bucket)
    worker = api.model_copy(update={"storage_dir": tmp_path / "worker" / "storage"})
    raw = _raw_client(s3_endpoint)

    def keys(prefix: str) -> list[str]:
        return sorted(o.object_name for o in raw.list_objects(bucket, prefix, recursive=True))

    try:
        with TestClient(create_app(api), raise_server_exceptions=False) as client:
            assets = [(f"asset{size}.glb", asset_bytes(tmp_path, size=size)) for size in (32, 48)]
            r = post_batch(client, assets, headers={})
            assert r.status_code == 202, r.text
            batch_id, ids = r.json()["id"], [job["id"] for job in r.json()["jobs"]]
            for job_id in ids:
                prefix = f"farm-a/jobs/{job_id}/"
                assert keys(prefix) == [prefix + "input/asset.glb", prefix + "job.json"]
            assert list((api.storage_dir / "jobs").iterdir()) == []  # nothing kept locally

            log = tmp_path / "worker.log"
            with worker_process(worker, log, extra=["--burst"]) as proc:
                proc.wait(timeout=240)
            batch = client.get(f"/v1/batches/{batch_id}").json()
            assert batch["status"] == "finished", log.read_text()[-3000:]
            assert [job["id"] for job in batch["jobs"]] == ids
            assert list((worker.storage_dir / "jobs").iterdir()) == []  # released
            for job in batch["jobs"]:
                r = client.get(job["links"]["result"], follow_redirects=False)
                assert r.status_code == 307
                got = httpx.get(r.headers["location"], timeout=30)
                stored = raw.get_object(bucket, f"farm-a/jobs/{job['id']}/result.zip").read()
                assert got.status_code == 200 and got.content == stored
                assert "asset.glb" in zipfile.ZipFile(io.BytesIO(got.content)).namelist()

            # the store turns the API's key down: the batch is kept whole, 503
            httpx.post(f"{s3_endpoint}/moto-api/reset-auth", content=b"0", timeout=10)
            try:
                r = client.delete(f"/v1/batches/{batch_id}")
            finally:
                httpx.post(f"{s3_endpoint}/moto-api/reset-auth", content=b"inf", timeout=10)
            assert r.status_code == 503 and r.json()["code"] == "storage-unavailable", r.text
            assert client.get(f"/v1/batches/{batch_id}").json()["total"] == 2
            assert all(f"farm-a/jobs/{job_id}/result.zip" in keys("farm-a/") for job_id in ids)

            assert client.delete(f"/v1/batches/{batch_id}").status_code == 204
            assert keys("farm-a/") == []
            assert client.get(f"/v1/batches/{batch_id}").status_code == 404
            assert all(client.get(f"/v1/jobs/{job_id}").status_code == 404 for job_id in ids)
    finally:
        cleanup_redis(api)


def _in_process_worker(settings: Settings, monkeypatch):
    """An RQ SimpleWorker on ``settings``' queue that runs jobs in this process with the
    worker context of ``settings`` (its storage folder and store, on the CPU)."""
    from redis import Redis
    from rq import SimpleWorker

    from pbrsr_jobs.store import JobFiles, JobIndex, JobLayout
    from worker import tasks

    redis = Redis.from_url(settings.redis_url)
    context = tasks.WorkerContext(
        settings=settings,
        layout=JobLayout(settings.prepare_storage()),
        files=JobFiles(open_store(settings)),
        index=JobIndex(redis, settings.key_prefix),
        device="cpu",
    )
    monkeypatch.setattr(tasks, "_CONTEXT", context)
    return SimpleWorker([Queue(settings.queue, connection=redis)], connection=redis)


def test_a_worker_refused_by_the_store_fails_the_job_clearly(
    s3_endpoint, bucket, tmp_path, monkeypatch
):
    api = _s3_settings(tmp_path / "api", s3_endpoint, bucket)
    worker = api.model_copy(update={"storage_dir": tmp_path / "worker" / "storage"})
    try:
        with TestClient(create_app(api), raise_server_exceptions=False) as client:
            r = post_asset(client, asset_bytes(tmp_path), options={"method": "bicubic"})
            job_id = r.json()["id"]
            rq_worker = _in_process_worker(worker, monkeypatch)
            # the store turns the worker's key down between start-up and the job
            httpx.post(f"{s3_endpoint}/moto-api/reset-auth", content=b"0", timeout=10)
            try:
                rq_worker.work(burst=True)
            finally:
                httpx.post(f"{s3_endpoint}/moto-api/reset-auth", content=b"inf", timeout=10)
            job = client.get(f"/v1/jobs/{job_id}").json()
            assert job["status"] == "failed" and job["code"] == "storage-error", job
            assert "job storage was unavailable" in job["error"]
            assert s3_endpoint not in job["error"] and SECRET not in job["error"]
            assert list((worker.storage_dir / "jobs").iterdir()) == []  # nothing left
            assert client.get(f"/v1/jobs/{job_id}/result").status_code == 409
    finally:
        cleanup_redis(api)


def test_crops_and_model_files_through_s3(s3_endpoint, bucket, tmp_path, monkeypatch):
    """A .gltf job run by a worker that shares only the bucket: its detail crops and every
    file of its bundle (the model and what it refers to) come from presigned URLs."""
    from urllib.parse import urljoin

    api = _s3_settings(tmp_path / "api", s3_endpoint, bucket)
    worker = api.model_copy(update={"storage_dir": tmp_path / "worker" / "storage"})
    raw = _raw_client(s3_endpoint)
    try:
        with TestClient(create_app(api), raise_server_exceptions=False) as client:
            upload = gltf_zip_bytes(tmp_path)
            r = post_asset(client, upload, "scene.zip", {"method": "bicubic", "scale": 2})
            job_id = r.json()["id"]
            _in_process_worker(worker, monkeypatch).work(burst=True)
            job = client.get(f"/v1/jobs/{job_id}").json()
            assert job["status"] == "finished", job
            assert list((worker.storage_dir / "jobs").iterdir()) == []  # released

            def presigned(url: str) -> httpx.Response:
                answer = client.get(url, follow_redirects=False)
                assert answer.status_code == 307, (url, answer.text)
                assert answer.headers["location"].startswith(f"{s3_endpoint}/{bucket}/farm-a/")
                got = httpx.get(answer.headers["location"], timeout=30)
                assert got.status_code == 200, url
                return got

            crops = client.get(job["links"]["crops"]).json()["items"]
            assert len(crops) == len(job["links"]["thumbs"]) >= 3
            for crop in crops:
                side = crop["lr_region"][2]
                lr, hr = presigned(crop["lr"]), presigned(crop["hr"])
                assert lr.headers["content-type"] == hr.headers["content-type"] == "image/png"
                assert np.asarray(Image.open(io.BytesIO(lr.content))).shape[:2] == (side, side)
                hr_px = np.asarray(Image.open(io.BytesIO(hr.content)))
                assert hr_px.shape[:2] == (2 * side, 2 * side)
            # a keyed fetch asks for the URL as JSON
            link = client.get(crops[-1]["hr"] + "?redirect=false").json()
            assert link["expires_in_s"] == 900
            assert httpx.get(link["url"], timeout=30).content == hr.content

            bundle = zipfile.ZipFile(io.BytesIO(presigned(job["links"]["result"]).content))
            model_url = job["links"]["model"]
            assert model_url.endswith(".gltf")
            model = presigned(model_url)
            assert model.headers["content-type"] == "model/gltf+json"
            name = model_url.rsplit("/", 1)[1]
            assert model.content == bundle.read(name)
            doc = json.loads(model.content)
            uris = [x["uri"] for x in doc["buffers"] + doc["images"]]
            assert len(uris) >= 2
            for uri in uris:  # resolved beside the model, as a 3D viewer does
                assert presigned(urljoin(model_url, uri)).content == bundle.read(uri)
            base = f"/v1/jobs/{job_id}"
            for bad in ("..%2Fjob.json", "maps", "%2E%2E%2Finput%2Fasset.gltf", "nope.glb"):
                assert client.get(f"{base}/files/{bad}").status_code == 404, bad
            assert client.get(f"{base}/crops/job.json").status_code == 404

            prefix = f"farm-a/jobs/{job_id}/"
            assert client.delete(base).status_code == 204
            assert list(raw.list_objects(bucket, prefix, recursive=True)) == []
    finally:
        cleanup_redis(api)
