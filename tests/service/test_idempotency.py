"""Idempotency-Key on POST /v1/jobs against the real Redis (no worker): replay, reuse with
another body, scoping per API key, key format, release after a failed attempt, concurrency."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest
from fastapi.testclient import TestClient
from rq import Queue

import service.idempotency
import service.intake
from pbrsr_jobs.idempotency import IdempotencyKeys, Reservation, fingerprint
from pbrsr_jobs.store import JobLayout, owner_of
from service.app import create_app
from tests.service_support import (
    LONG_KEY_A,
    LONG_KEY_B,
    asset_bytes,
    post_asset,
    redis_client,
    settings_scope,
)

OPTIONS = {"scale": 2, "method": "bicubic"}


@pytest.fixture
def settings(tmp_path):
    yield from settings_scope(tmp_path, api_keys=[LONG_KEY_A, LONG_KEY_B])


@pytest.fixture
def client(settings):
    """Answers as the server would (problem bodies), as the owner of LONG_KEY_A by default."""
    app = create_app(settings)
    with TestClient(app, raise_server_exceptions=False, headers={"X-API-Key": LONG_KEY_A}) as c:
        yield c


def _post(client, data, key, api_key=LONG_KEY_A, options=OPTIONS):
    headers = {"X-API-Key": api_key}
    if key is not None:
        headers["Idempotency-Key"] = key
    return post_asset(client, data, options=options, headers=headers)


def _queued(settings) -> int:
    return Queue(settings.queue, connection=redis_client()).count


def _problem(resp, status: int, code: str) -> dict:
    assert resp.status_code == status, resp.text
    assert resp.headers["content-type"].startswith("application/problem+json")
    body = resp.json()
    assert body["code"] == code and body["status"] == status
    return body


def _slow_check(monkeypatch, seconds: float) -> None:
    """Make the asset check of every submission take ``seconds`` longer."""
    real = service.intake.check_asset

    def slow(*args, **kwargs):
        time.sleep(seconds)
        return real(*args, **kwargs)

    monkeypatch.setattr(service.intake, "check_asset", slow)


def test_replay_returns_the_first_job(client, settings, tmp_path):
    data = asset_bytes(tmp_path)
    first = _post(client, data, "order-17 retry/1")
    assert first.status_code == 202, first.text
    job_id = first.json()["id"]
    again = _post(client, data, "order-17 retry/1")
    assert again.status_code == 200, again.text
    assert again.json() == first.json()
    assert again.headers["location"] == first.headers["location"] == f"/v1/jobs/{job_id}"
    page = client.get("/v1/jobs").json()
    assert [j["id"] for j in page["items"]] == [job_id]
    assert _queued(settings) == 1
    assert list(JobLayout(settings.storage_dir).uploads_dir().iterdir()) == []
    # without the header every submission is a new job
    assert _post(client, data, None).status_code == 202
    assert _queued(settings) == 2


def test_same_key_with_another_body_is_refused(client, settings, tmp_path):
    data = asset_bytes(tmp_path)
    job_id = _post(client, data, "k1").json()["id"]
    other_options = _post(client, data, "k1", options={"scale": 4, "method": "bicubic"})
    body = _problem(other_options, 422, "idempotency-key-reused")
    assert "another file or other options" in body["detail"]
    other_file = _post(client, asset_bytes(tmp_path, size=16), "k1")
    _problem(other_file, 422, "idempotency-key-reused")
    assert _queued(settings) == 1
    assert list(JobLayout(settings.storage_dir).uploads_dir().iterdir()) == []
    assert _post(client, data, "k1").json()["id"] == job_id  # the record is untouched


def test_keys_are_scoped_per_api_key(client, settings, tmp_path):
    data = asset_bytes(tmp_path)
    a = _post(client, data, "shared-key", api_key=LONG_KEY_A)
    b = _post(client, data, "shared-key", api_key=LONG_KEY_B)
    assert a.status_code == b.status_code == 202
    assert a.json()["id"] != b.json()["id"]
    assert _queued(settings) == 2
    # a different body under the other API key is no reuse either
    c = _post(client, data, "shared-key", api_key=LONG_KEY_B, options={"method": "bicubic"})
    _problem(c, 422, "idempotency-key-reused")


@pytest.mark.parametrize(
    "key",
    ["", "x" * 256, "clé".encode(), b"tab\there", b"nul\x7fdel"],
    ids=["empty", "too-long", "non-ascii", "tab", "del"],
)
def test_invalid_keys_are_400(client, settings, tmp_path, key):
    r = _post(client, asset_bytes(tmp_path), key)
    body = _problem(r, 400, "invalid-idempotency-key")
    assert "255 printable ASCII" in body["detail"]
    assert _queued(settings) == 0


def test_longest_and_widest_valid_key(client, tmp_path):
    data = asset_bytes(tmp_path)
    for key in ("k" * 255, "".join(chr(c) for c in range(0x21, 0x7F))):
        assert _post(client, data, key).status_code == 202
        assert _post(client, data, key).status_code == 200


def test_failed_attempt_frees_the_key(client, settings, tmp_path):
    data = asset_bytes(tmp_path)
    bad = _post(client, data[: len(data) // 2], "retry-me")
    _problem(bad, 400, "invalid-asset")
    bad_options = _post(client, data, "retry-me", options={"scale": 3})
    _problem(bad_options, 422, "invalid-options")
    keys = IdempotencyKeys(redis_client(), settings.key_prefix, settings.idempotency_ttl_s)
    assert keys.get(owner_of(LONG_KEY_A), "retry-me") is None
    good = _post(client, data, "retry-me")
    assert good.status_code == 202, good.text
    assert _post(client, data, "retry-me").json()["id"] == good.json()["id"]
    assert _queued(settings) == 1
    record = keys.get(owner_of(LONG_KEY_A), "retry-me")
    assert record is not None and record.done and record.ref == good.json()["id"]
    ttl = redis_client().ttl(keys.redis_key(owner_of(LONG_KEY_A), "retry-me"))
    assert settings.idempotency_ttl_s == 86400 and 86400 - 60 < ttl <= 86400


def _race(client, data, key) -> list:
    barrier = threading.Barrier(2)

    def one(_):
        barrier.wait()
        return _post(client, data, key)

    with ThreadPoolExecutor(2) as pool:
        return list(pool.map(one, range(2)))


def test_concurrent_requests_make_one_job(client, settings, tmp_path, monkeypatch):
    _slow_check(monkeypatch, 0.5)  # the second arrives while the first is being checked
    results = _race(client, asset_bytes(tmp_path), "concurrent")
    assert sorted(r.status_code for r in results) == [200, 202], [r.text for r in results]
    assert results[0].json()["id"] == results[1].json()["id"]
    assert _queued(settings) == 1
    assert len(list((settings.storage_dir / "jobs").iterdir())) == 1
    assert list(JobLayout(settings.storage_dir).uploads_dir().iterdir()) == []


def test_still_running_first_request_is_409(client, settings, tmp_path, monkeypatch):
    _slow_check(monkeypatch, 1.5)
    monkeypatch.setattr(service.idempotency, "WAIT_S", 0.3)
    results = _race(client, asset_bytes(tmp_path), "slow")
    codes = sorted(r.status_code for r in results)
    assert codes == [202, 409], [r.text for r in results]
    busy = next(r for r in results if r.status_code == 409)
    _problem(busy, 409, "idempotency-key-in-progress")
    assert busy.headers["retry-after"] == "2"
    assert _queued(settings) == 1


def test_fingerprint():
    base = fingerprint("a" * 64, {"options": '{"scale": 2}'})
    assert fingerprint("a" * 64, {"options": '{"scale": 2}'}) == base
    assert fingerprint("b" * 64, {"options": '{"scale": 2}'}) != base
    assert fingerprint("a" * 64, {"options": '{"scale": 4}'}) != base
    assert fingerprint("a" * 64, {}) == fingerprint("a" * 64, {"options": ""})
    assert fingerprint(None, {}) != fingerprint("a" * 64, {})


def test_completion_keeps_a_newer_reservation(settings):
    """A reservation that expired and was taken by another request does not overwrite it."""
    redis = redis_client()
    keys = IdempotencyKeys(redis, settings.key_prefix, 3600, pending_ttl_s=1)
    fp = fingerprint("0" * 64, {"options": "{}"})
    first = keys.reserve("owner", "k", fp)
    assert isinstance(first, Reservation)
    assert keys.reserve("owner", "k", fp) == first.record  # held: the record, not the key
    redis.delete(first.redis_key)  # as if its reservation had expired
    second = keys.reserve("owner", "k", fp)
    assert isinstance(second, Reservation)
    assert first.complete("a" * 32) is False
    first.release()  # not its record any more: nothing happens
    assert keys.get("owner", "k") == second.record
    assert second.complete("b" * 32) is True
    record = keys.get("owner", "k")
    assert record is not None and record.done and record.ref == "b" * 32
