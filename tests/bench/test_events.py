"""The service benchmarks' event clients: SSE parsing, the webhook receiver's signature check
over real HTTP, and how the delivery report counts a lost event."""

from __future__ import annotations

import json
import time

import httpx

from pbrsr_bench.events import EventWatch, Received, WebhookReceiver, delivery_report, parse_sse
from pbrsr_jobs.webhooks import (
    DELIVERY_HEADER,
    SIGNATURE_HEADER,
    TIMESTAMP_HEADER,
    sign,
)


def test_sse_messages_are_split_at_blank_lines_without_comments():
    text = (
        "retry: 2000\n\n: keepalive\n\n"
        'id: 1-0\nevent: queued\ndata: {"job": "a"}\n\n'
        "event: progress\ndata: line one\ndata: line two\n\n"
        "id: 3-0\n"  # no data yet: not a message
    )
    messages = parse_sse(text.split("\n"))
    assert messages == [
        {"id": "1-0", "event": "queued", "data": '{"job": "a"}'},
        {"event": "progress", "data": "line one\nline two"},
    ]


def _post(receiver: WebhookReceiver, secret: str, body: dict, delivery: str) -> int:
    raw = json.dumps(body).encode()
    stamp = str(int(time.time()))
    headers = {
        TIMESTAMP_HEADER: stamp,
        SIGNATURE_HEADER: sign(secret, stamp, raw),
        DELIVERY_HEADER: delivery,
    }
    return httpx.post(receiver.url, content=raw, headers=headers, timeout=10).status_code


def test_the_receiver_keeps_signed_deliveries_once_and_refuses_bad_signatures():
    body = {"id": "d1", "job": "j1", "type": "succeeded", "time": time.time() - 0.05, "data": {}}
    with WebhookReceiver("right-secret") as receiver:
        assert _post(receiver, "right-secret", body, "d1") == 200
        assert _post(receiver, "right-secret", body, "d1") == 200  # a retry of the same one
        assert _post(receiver, "wrong-secret", {**body, "id": "d2"}, "d2") == 401
    assert receiver.bad_signatures == 1 and receiver.duplicates == 1
    [got] = receiver.events()
    assert (got.job, got.type, got.channel) == ("j1", "succeeded", "webhook")
    assert got.at - got.time >= 0.05
    assert receiver.outcomes() == {"j1"}


def _event(channel: str, job: str, type_: str, at: float, live: bool = True) -> Received:
    return Received(channel, job, type_, at, at + 0.01, live)


def test_an_event_missing_from_the_key_stream_or_the_webhooks_is_lost():
    watch = EventWatch("http://127.0.0.1:9")  # never started: its events are given here
    receiver = WebhookReceiver("s")
    for job, t in (("a", 100.0), ("b", 200.0)):
        for i, type_ in enumerate(("queued", "started", "progress", "succeeded")):
            watch.received.append(_event("job", job, type_, t + i, live=i > 0))
            if (job, type_) != ("b", "started"):
                watch.received.append(_event("key", job, type_, t + i))
            if type_ != "progress" and (job, type_) != ("a", "succeeded"):
                receiver.received.append(_event("webhook", job, type_, t + i))
    report = delivery_report(["a", "b"], watch, receiver)
    receiver.close()
    watch.close()
    channels = report["channels"]
    assert channels["sse_job"]["lost"] == 0 and channels["sse_job"]["timed"] == 6
    assert (
        channels["sse_key"]["lost"] == 1 and "b: started" in channels["sse_key"]["lost_samples"][0]
    )
    assert channels["webhook"]["lost"] == 1  # progress is not asked for; a's outcome is lost
    assert "a: succeeded" in channels["webhook"]["lost_samples"][0]
    assert report["lost"] == 2
    assert channels["sse_key"]["p50_ms"] == channels["sse_key"]["max_ms"]
    assert abs(channels["sse_key"]["p50_ms"] - 10.0) < 1e-6
