"""Batches (POST/GET/DELETE /v1/batches, GET /v1/jobs?batch=) against the real Redis: one job
per file, all or nothing, the per-key and queue limits counting every job of a batch, owners,
Idempotency-Key, expiry with the jobs; a real burst worker runs a batch to finished."""

from __future__ import annotations

import json
import time

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
    redis_client,
    settings_scope,
    worker_process,
)

OPTIONS = {"scale": 2, "method": "bicubic"}
A = {"X-API-Key": LONG_KEY_A}
B = {"X-API-Key": LONG_KEY_B}


@pytest.fixture
def settings(tmp_path):
    yield from settings_scope(tmp_path, api_keys=[LONG_KEY_A, LONG_KEY_B])


def post_batch(client, files, options=OPTIONS, headers=A, **fields):
    """``files``: (name, bytes) pairs, each sent as a ``file`` part."""
    parts = [("file", (name, data, "application/octet-stream")) for name, data in files]
    form = {"options": json.dumps(options), **fields}
    return client.post("/v1/batches", files=parts, data=form, headers=headers)


def three(tmp_path) -> list[tuple[str, bytes]]:
    return [(f"asset{i}.glb", asset_bytes(tmp_path, size=32)) for i in range(3)]


def _problem(resp, status: int, code: str) -> dict:
    assert resp.status_code == status, resp.text
    assert resp.headers["content-type"].startswith("application/problem+json")
    body = resp.json()
    assert body["code"] == code and body["status"] == status, body
    return body


def _queued(settings) -> int:
    redis = redis_client()
    return sum(Queue(q, connection=redis).count for q in settings.listen_queues("all"))


def _nothing_kept(settings) -> None:
    layout = JobLayout(settings.storage_dir)
    assert list((settings.storage_dir / "jobs").iterdir()) == []
    assert list(layout.uploads_dir().iterdir()) == []
    assert _queued(settings) == 0
    assert list(redis_client().scan_iter(match=f"{settings.key_prefix}:batch*")) == []
    assert redis_client().hlen(f"{settings.key_prefix}:job-batch") == 0


def test_a_batch_makes_one_job_per_file(client, settings, tmp_path):
    r = post_batch(client, three(tmp_path), priority="high")
    assert r.status_code == 202, r.text
    body = r.json()
    batch_id, ids = body["id"], [j["id"] for j in body["jobs"]]
    assert len(set(ids)) == 3 and all(j["status"] == "queued" for j in body["jobs"])
    assert r.headers["location"] == body["links"]["self"] == f"/v1/batches/{batch_id}"
    assert body["links"]["jobs"] == f"/v1/jobs?batch={batch_id}"
    redis = redis_client()
    for job_id, name in zip(ids, ("asset0.glb", "asset1.glb", "asset2.glb"), strict=True):
        job = Job.fetch(job_id, connection=redis)
        assert job.meta["batch"] == batch_id and job.meta["name"] == name
        assert job.meta["options"]["scale"] == 2 and job.origin == f"{settings.queue}-high"
    assert _queued(settings) == 3

    batch = client.get(f"/v1/batches/{batch_id}", headers=A).json()
    assert batch["status"] == "queued" and batch["total"] == 3 and batch["fraction"] == 0
    assert batch["counts"] == {"queued": 3, "running": 0, "finished": 0, "failed": 0,
                               "canceled": 0}  # fmt: skip
    assert [j["id"] for j in batch["jobs"]] == ids
    listed = client.get(f"/v1/jobs?batch={batch_id}&limit=2", headers=A).json()
    assert [j["id"] for j in listed["items"]] == ids[:2] and listed["total"] == 3
    assert listed["next"] == f"/v1/jobs?offset=2&limit=2&batch={batch_id}"
    assert client.get(f"/v1/jobs/{ids[0]}", headers=A).json()["batch"] == batch_id
    # a job submitted alone is in no batch and not in the batch's list
    single = client.post(
        "/v1/jobs", files={"file": ("x.glb", asset_bytes(tmp_path))}, headers=A
    ).json()
    assert client.get(f"/v1/jobs/{single['id']}", headers=A).json()["batch"] is None
    assert client.get(f"/v1/jobs?batch={batch_id}", headers=A).json()["total"] == 3
    assert client.get("/v1/jobs", headers=A).json()["total"] == 4


def test_cancel_a_batch_then_delete_it(client, settings, tmp_path):
    body = post_batch(client, three(tmp_path)).json()
    batch_id, ids = body["id"], [j["id"] for j in body["jobs"]]
    client.delete(f"/v1/jobs/{ids[0]}", headers=A)  # one canceled on its own first
    r = client.delete(f"/v1/batches/{batch_id}", headers=A)
    assert r.status_code == 202, r.text
    batch = r.json()
    assert batch["status"] == "canceled" and batch["counts"]["canceled"] == 3
    assert batch["fraction"] == 1.0 and _queued(settings) == 0
    assert client.get(f"/v1/jobs?batch={batch_id}&status=canceled", headers=A).json()["total"] == 3
    # every job has ended: a second DELETE removes the batch, its jobs and their files
    assert client.delete(f"/v1/batches/{batch_id}", headers=A).status_code == 204
    _problem(client.get(f"/v1/batches/{batch_id}", headers=A), 404, "not-found")
    for job_id in ids:
        _problem(client.get(f"/v1/jobs/{job_id}", headers=A), 404, "not-found")
    _nothing_kept(settings)


def test_one_bad_file_refuses_the_whole_batch(client, settings, tmp_path):
    good = asset_bytes(tmp_path)
    files = [("a.glb", good), ("b.glb", good), ("../bad chair.glb", good[: len(good) // 2])]
    body = _problem(post_batch(client, files), 400, "invalid-asset")
    assert body["detail"].startswith("file 3 (bad_chair.glb): "), body
    _nothing_kept(settings)
    body = _problem(post_batch(client, [("a.glb", good), ("e.glb", b"")]), 400, "invalid-asset")
    assert body["detail"] == "file 2 (e.glb): the uploaded file is empty"
    _problem(post_batch(client, [("a.glb", good)], options={"scale": 3}), 422, "invalid-options")
    _problem(post_batch(client, [("a.glb", good)], priority="urgent"), 422, "invalid-options")
    _problem(
        client.post("/v1/batches", files={"other": ("x", b"1")}, headers=A), 400, "bad-request"
    )
    _nothing_kept(settings)


def test_too_many_files_or_one_too_large_is_413(tmp_path):
    gen = settings_scope(tmp_path, max_batch_files=2, max_upload_mb=0.05)
    settings = next(gen)
    try:
        with TestClient(create_app(settings), raise_server_exceptions=False) as c:
            body = _problem(post_batch(c, three(tmp_path), headers={}), 413, "limit-exceeded")
            assert "at most 2 files" in body["detail"]
            files = [("small.glb", asset_bytes(tmp_path)), ("big.glb", b"\0" * 100_000)]
            body = _problem(post_batch(c, files, headers={}), 413, "limit-exceeded")
            assert body["detail"].startswith("file 2 (big.glb) is larger than"), body
            _nothing_kept(settings)
    finally:
        next(gen, None)


def test_a_failure_while_queueing_takes_back_the_jobs_already_queued(
    client, settings, tmp_path, monkeypatch
):
    real = Queue.enqueue
    calls = []

    def second_fails(self, *args, **kwargs):
        calls.append(args)
        if len(calls) == 2:
            raise ConnectionError("redis went away")
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Queue, "enqueue", second_fails)
    _problem(post_batch(client, three(tmp_path)), 500, "internal-error")
    assert len(calls) == 2
    _nothing_kept(settings)
    assert client.get("/v1/jobs", headers=A).json()["total"] == 0


def test_a_batch_counts_all_its_jobs_against_the_limits(tmp_path):
    gen = settings_scope(
        tmp_path, api_keys=[LONG_KEY_A, LONG_KEY_B], max_active_jobs_per_key=3, max_queued_jobs=5
    )
    settings = next(gen)
    try:
        with TestClient(create_app(settings), raise_server_exceptions=False) as c:
            data = asset_bytes(tmp_path)
            r = c.post("/v1/jobs", files={"file": ("x.glb", data)}, headers=A)
            assert r.status_code == 202
            over = post_batch(c, three(tmp_path))  # 1 + 3 > 3
            body = _problem(over, 429, "too-many-jobs")
            assert over.headers["Retry-After"] == "30" and "this batch adds 3" in body["detail"]
            assert _queued(settings) == 1
            too_big = _problem(post_batch(c, three(tmp_path) + three(tmp_path)[:1]), 413,
                               "limit-exceeded")  # fmt: skip
            assert "a batch of 4 jobs" in too_big["detail"]
            assert post_batch(c, three(tmp_path)[:2]).status_code == 202  # 1 + 2 fit
            assert post_batch(c, three(tmp_path)[:2], headers=B).status_code == 202  # 5 waiting
            full = post_batch(c, three(tmp_path)[:1], headers=B)
            _problem(full, 503, "queue-full")
            assert full.headers["Retry-After"] == "30"
            assert _queued(settings) == 5
            assert list((settings.storage_dir / "uploads").iterdir()) == []
    finally:
        next(gen, None)


def test_another_key_sees_no_batch(client, settings, tmp_path):
    batch_id = post_batch(client, three(tmp_path)[:1]).json()["id"]
    for method, path in (
        ("GET", f"/v1/batches/{batch_id}"),
        ("DELETE", f"/v1/batches/{batch_id}"),
        ("GET", f"/v1/jobs?batch={batch_id}"),
    ):
        _problem(client.request(method, path, headers=B), 404, "not-found")
    _problem(client.get("/v1/batches/not-a-batch", headers=A), 404, "not-found")
    _problem(client.get(f"/v1/batches/{'0' * 32}", headers=A), 404, "not-found")
    assert client.get(f"/v1/batches/{batch_id}", headers=A).json()["status"] == "queued"
    assert _queued(settings) == 1


def test_idempotency_key_makes_one_batch(client, settings, tmp_path):
    files = three(tmp_path)
    key = {**A, "Idempotency-Key": "nightly-2024-06-01"}
    first = post_batch(client, files, headers=key)
    assert first.status_code == 202
    again = post_batch(client, files, headers=key)
    assert again.status_code == 200 and again.json() == first.json()
    assert again.headers["location"] == first.headers["location"]
    _problem(post_batch(client, files[:2], headers=key), 422, "idempotency-key-reused")
    assert _queued(settings) == 3
    # keys are per endpoint: the same key names another submission on POST /v1/jobs
    one = client.post("/v1/jobs", files={"file": files[0]}, headers=key)
    assert one.status_code == 202 and one.json()["id"] not in {
        j["id"] for j in first.json()["jobs"]
    }


def test_a_batch_expires_with_its_jobs(client, settings, tmp_path):
    body = post_batch(client, three(tmp_path)[:2]).json()
    batch_id, ids = body["id"], [j["id"] for j in body["jobs"]]
    client.delete(f"/v1/batches/{batch_id}", headers=A)
    redis = redis_client()
    index = JobIndex(redis, settings.key_prefix)
    old = Job.fetch(ids[0], connection=redis)
    old.meta["ended_at"] = time.time() - settings.retention_s - 10
    old.save_meta()
    layout = JobLayout(settings.storage_dir)
    files = JobFiles(FilesystemStore(settings.storage_dir))
    assert sweep_expired(redis, index, layout, files, settings.retention_s) == [ids[0]]
    batch = client.get(f"/v1/batches/{batch_id}", headers=A).json()
    assert [j["id"] for j in batch["jobs"]] == [ids[1]] and batch["total"] == 1
    Job.fetch(ids[1], connection=redis).delete()  # its RQ hash gone, as after RQ's own expiry
    later = time.time() + settings.retention_s + 10
    assert sweep_expired(redis, index, layout, files, settings.retention_s, now=later) == [ids[1]]
    _problem(client.get(f"/v1/batches/{batch_id}", headers=A), 404, "not-found")
    _nothing_kept(settings)


@pytest.mark.slow
def test_a_burst_worker_runs_a_batch_to_finished(client, settings, tmp_path):
    body = post_batch(client, three(tmp_path)).json()
    batch_id = body["id"]
    with worker_process(settings, tmp_path / "worker.log", extra=["--burst"]) as proc:
        proc.wait(timeout=240)
    batch = client.get(f"/v1/batches/{batch_id}", headers=A).json()
    assert batch["status"] == "finished", (tmp_path / "worker.log").read_text()[-3000:]
    assert batch["counts"]["finished"] == 3 and batch["fraction"] == 1.0
    for job in batch["jobs"]:
        assert job["links"]["result"] == f"/v1/jobs/{job['id']}/result"
        assert client.get(job["links"]["result"], headers=A).status_code == 200


def test_the_batch_endpoints_are_documented_and_a_job_still_takes_one_file(client, tmp_path):
    spec = client.get("/openapi.json").json()
    assert {"/v1/batches", "/v1/batches/{batch_id}"} <= spec["paths"].keys()
    form = spec["paths"]["/v1/batches"]["post"]["requestBody"]["content"]["multipart/form-data"]
    assert form["schema"]["properties"]["file"]["type"] == "array"
    assert "batch" in [p["name"] for p in spec["paths"]["/v1/jobs"]["get"]["parameters"]]
    data = asset_bytes(tmp_path)
    parts = [("file", ("a.glb", data)), ("file", ("b.glb", data))]
    body = _problem(client.post("/v1/jobs", files=parts, headers=A), 400, "bad-request")
    assert body["detail"] == "send exactly one 'file' part"
    assert list((client.app.state.settings.storage_dir / "uploads").iterdir()) == []
