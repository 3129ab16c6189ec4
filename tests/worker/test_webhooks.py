"""Webhooks: parsing the job's callback fields, signatures, and the workers' dispatcher with a
real HTTP receiver and the real Redis (deliveries, retries with backoff, giving up, taking
over a dead dispatcher's task), then end to end through the API and a real worker."""

from __future__ import annotations

import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest
from fastapi.testclient import TestClient

from pbrsr_bench.load import wait_until
from pbrsr_core.errors import InvalidOptions
from pbrsr_jobs.events import JobEvents
from pbrsr_jobs.webhooks import (
    SIGNATURE_HEADER,
    TIMESTAMP_HEADER,
    WebhookQueue,
    key_secret,
    parse_webhook,
    server_secret,
    sign,
    verify,
)
from service.app import create_app
from tests.service_support import (
    asset_bytes,
    cleanup_redis,
    make_settings,
    post_asset,
    redis_client,
    settings_scope,
    worker_process,
)
from worker.webhooks import WebhookDispatcher


class Receiver:
    """A local HTTP endpoint that records deliveries and answers ``statuses`` in turn."""

    def __init__(self, statuses=(200,)):
        self.statuses = list(statuses)
        self.got: list[dict] = []
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self):  # noqa: N802 - http.server's name
                body = self.rfile.read(int(self.headers["Content-Length"]))
                receiver.got.append({"headers": dict(self.headers), "body": body})
                status = (
                    receiver.statuses.pop(0) if len(receiver.statuses) > 1 else receiver.statuses[0]
                )
                self.send_response(status)
                self.end_headers()

            def log_message(self, *args):
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_port}/hook"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self):
        self.server.shutdown()


@pytest.fixture
def settings(tmp_path):
    yield from settings_scope(tmp_path)


@pytest.fixture
def receiver():
    r = Receiver()
    yield r
    r.close()


def test_callback_fields_are_checked():
    assert parse_webhook(None, None) is None and parse_webhook("  ", "") is None
    hook = parse_webhook("https://ci.example.com/pbrsr", None)
    assert hook == {
        "url": "https://ci.example.com/pbrsr",
        "events": ["succeeded", "failed", "cancelled"],
    }
    assert parse_webhook("http://h/x", "progress, queued,progress")["events"] == [
        "queued",
        "progress",
    ]
    for url, says in [
        ("ftp://h/x", "http or https"),
        ("https://", "http or https"),
        ("https://u:p@h/x", "credentials"),
        ("https://h/" + "a" * 3000, "2048"),
    ]:
        with pytest.raises(InvalidOptions, match=says):
            parse_webhook(url, None)
    with pytest.raises(InvalidOptions, match="unknown exploded"):
        parse_webhook("https://h/x", "succeeded,exploded")
    with pytest.raises(InvalidOptions, match="needs a callback_url"):
        parse_webhook(None, "succeeded")


def test_signatures(settings):
    secret = key_secret(b"server", "owner-a")
    assert secret != key_secret(b"server", "owner-b") and len(secret) == 64
    body, stamp = b'{"job":"j"}', str(int(time.time()))
    signature = sign(secret, stamp, body)
    assert verify(secret, stamp, body, signature)
    assert not verify(secret, stamp, body + b" ", signature)  # the body was changed
    assert not verify(key_secret(b"server", "owner-b"), stamp, body, signature)
    assert not verify(
        secret, str(int(time.time()) - 3600), body, sign(secret, str(int(time.time()) - 3600), body)
    )
    # the server secret: configured, else made once and shared through Redis
    r = redis_client()
    first = server_secret(r, settings.key_prefix, None)
    assert server_secret(r, settings.key_prefix, None) == first and len(first) == 64
    assert server_secret(r, settings.key_prefix, "configured") == b"configured"


def _dispatcher(settings, name="d1", **kw):
    kw = {"backoff_s": 0.2, "max_attempts": 3, **kw}
    d = WebhookDispatcher(redis_client(), settings.key_prefix, name=name, **kw)
    d.start()
    return d


def test_a_delivery_is_signed_and_logged(settings, receiver):
    events = JobEvents(redis_client(), settings.key_prefix)
    hook = {"url": receiver.url, "events": ["succeeded"]}
    events.publish("job1", "owner-a", "progress", {"fraction": 0.5}, hook)  # not asked for
    events.publish("job1", "owner-a", "succeeded", {"summary": {"maps": 3}}, hook)
    d = _dispatcher(settings)
    try:
        wait_until(
            lambda: WebhookQueue(redis_client(), settings.key_prefix).deliveries("job1"),
            20,
            "the delivery",
        )
    finally:
        d.stop()
    assert len(receiver.got) == 1
    got = receiver.got[0]
    body = json.loads(got["body"])
    assert body["job"] == "job1" and body["type"] == "succeeded"
    assert body["data"] == {"summary": {"maps": 3}}
    secret = key_secret(server_secret(redis_client(), settings.key_prefix, None), "owner-a")
    assert verify(
        secret, got["headers"][TIMESTAMP_HEADER], got["body"], got["headers"][SIGNATURE_HEADER]
    )
    log = WebhookQueue(redis_client(), settings.key_prefix).deliveries("job1")
    assert [(e["event"], e["attempt"], e["ok"], e["status"]) for e in log] == [
        ("succeeded", 1, True, 200)
    ]


def test_failures_are_retried_with_backoff_then_given_up(settings):
    flaky, dead = Receiver([500, 200]), Receiver([503])
    events = JobEvents(redis_client(), settings.key_prefix)
    events.publish("flaky", "o", "failed", {"error": "x"}, {"url": flaky.url, "events": ["failed"]})
    events.publish("dead", "o", "failed", {}, {"url": dead.url, "events": ["failed"]})
    queue = WebhookQueue(redis_client(), settings.key_prefix)
    d = _dispatcher(settings)
    try:
        wait_until(
            lambda: len(queue.deliveries("flaky")) == 2 and len(queue.deliveries("dead")) == 3,
            30,
            "2 deliveries to the flaky receiver and 3 to the dead one",
        )
    finally:
        d.stop()
        flaky.close()
        dead.close()
    log = queue.deliveries("flaky")
    assert [(e["attempt"], e["ok"], e["status"]) for e in log] == [(1, False, 500), (2, True, 200)]
    assert log[1]["at"] - log[0]["at"] >= 0.2  # waited for the backoff
    assert log[0]["delivery"] == log[1]["delivery"]  # a retry of the same delivery
    gave_up = queue.deliveries("dead")
    assert [e["attempt"] for e in gave_up] == [1, 2, 3] and gave_up[-1]["retry_in_s"] is None
    r = redis_client()
    assert r.zcard(queue.retries) == 0 and r.xlen(queue.stream) == 0  # nothing left behind


def test_a_task_a_dead_dispatcher_held_is_taken_over(settings, receiver):
    r = redis_client()
    queue = WebhookQueue(r, settings.key_prefix)
    events = JobEvents(r, settings.key_prefix)
    events.publish("j", "o", "succeeded", {}, {"url": receiver.url, "events": ["succeeded"]})
    r.xgroup_create(queue.stream, WebhookQueue.GROUP, id="0", mkstream=True)
    taken = r.xreadgroup(WebhookQueue.GROUP, "died", {queue.stream: ">"}, count=10)
    assert taken and len(taken[0][1]) == 1  # held by a consumer that never answers
    d = _dispatcher(settings, name="alive", claim_after_s=0.5)
    try:
        wait_until(lambda: queue.deliveries("j"), 20, "the delivery")
    finally:
        d.stop()
    assert len(receiver.got) == 1 and queue.deliveries("j")[0]["ok"]


@pytest.mark.slow
def test_a_jobs_webhooks_end_to_end(tmp_path, receiver):
    settings = make_settings(tmp_path, webhook_backoff_s=0.2)
    try:
        with (
            worker_process(settings, tmp_path / "worker.log"),
            TestClient(create_app(settings), raise_server_exceptions=False) as client,
        ):
            bad = client.post(
                "/v1/jobs",
                files={"file": ("a.glb", asset_bytes(tmp_path), "application/octet-stream")},
                data={"callback_url": "ftp://x/y"},
            )
            assert bad.status_code == 422 and "callback_url" in bad.json()["detail"]
            resp = client.post(
                "/v1/jobs",
                files={"file": ("a.glb", asset_bytes(tmp_path), "application/octet-stream")},
                data={
                    "options": json.dumps({"method": "bicubic", "scale": 2}),
                    "callback_url": receiver.url,
                    "callback_events": "queued,started,succeeded",
                },
            )
            assert resp.status_code == 202, resp.text
            job_id = resp.json()["id"]

            def delivered():
                j = client.get(f"/v1/jobs/{job_id}").json()
                return len([d for d in j["deliveries"] if d["ok"]]) == 3 and j

            job = wait_until(delivered, 150, "three deliveries", 0.2)
            assert job["status"] == "finished"
            assert job["webhook"] == {
                "url": receiver.url,
                "events": ["queued", "started", "succeeded"],
            }
            assert [d["event"] for d in job["deliveries"]] == ["queued", "started", "succeeded"]
            secret = client.get("/v1/webhook-secret").json()["secret"]
            for got in receiver.got:
                h = got["headers"]
                assert verify(secret, h[TIMESTAMP_HEADER], got["body"], h[SIGNATURE_HEADER])
            assert json.loads(receiver.got[-1]["body"])["data"]["summary"]
            # no webhook: no deliveries, none logged
            plain = post_asset(client, asset_bytes(tmp_path), options={"method": "bicubic"})
            assert client.get(f"/v1/jobs/{plain.json()['id']}").json()["deliveries"] == []
    finally:
        cleanup_redis(settings)


def test_the_documented_check_accepts_what_the_dispatcher_signs():
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[2] / "docs" / "SERVICE.md").read_text()
    code = doc.split("Checking a delivery (Python):\n\n```python\n", 1)[1].split("```", 1)[0]
    scope: dict = {}
    exec(code, scope)  # noqa: S102 - the snippet the docs give users
    secret, body, stamp = key_secret(b"s", "o"), b'{"job":"j"}', str(int(time.time()))
    headers = {TIMESTAMP_HEADER: stamp, SIGNATURE_HEADER: sign(secret, stamp, body)}
    assert scope["verified"](secret, headers, body)
    assert not scope["verified"](secret, headers, body + b"x")
