"""Job events (pbrsr_jobs.events) and their Server-Sent Events endpoints, against the real
Redis: without a worker through the app (queued, cancelled, replay, Last-Event-ID, 404),
and end to end with a real ``pbrsr serve`` and ``pbrsr worker`` (a job's stream from queued
to succeeded; the key's stream sees a new job)."""

from __future__ import annotations

import json
import threading

import httpx
import pytest

from pbrsr_jobs.events import JobEvent, JobEvents
from tests.service_support import (
    LONG_KEY_A,
    LONG_KEY_B,
    api_server,
    asset_bytes,
    cleanup_redis,
    make_settings,
    post_asset,
    redis_client,
    settings_scope,
    worker_process,
)


def parse_sse(text: str) -> list[dict]:
    """SSE messages -> [{"id", "event", "data"}] (comments and retry lines skipped)."""
    out = []
    for block in text.split("\n\n"):
        msg: dict = {}
        for line in block.splitlines():
            if line.startswith(":") or ":" not in line:
                continue
            field, value = line.split(":", 1)
            msg[field] = value[1:] if value.startswith(" ") else value
        if "event" in msg:
            msg["data"] = json.loads(msg["data"])
            out.append(msg)
    return out


@pytest.fixture
def settings(tmp_path):
    yield from settings_scope(tmp_path, api_keys=[LONG_KEY_A, LONG_KEY_B])


KEY_A = {"X-API-Key": LONG_KEY_A}


def test_publish_and_read_back_in_order(settings):
    events = JobEvents(redis_client(), settings.key_prefix)
    first = events.publish("j1", "o1", "queued")
    events.publish("j1", "o1", "progress", {"stage": "init", "fraction": 0.5})
    events.publish("j2", "o1", "queued")
    events.publish("j1", "o1", "succeeded", {"summary": {"maps": 3}})
    got = events.history("j1")
    assert [e.type for e in got] == ["queued", "progress", "succeeded"]
    assert got[0].id == first and got[1].data == {"stage": "init", "fraction": 0.5}
    assert [e.type for e in events.history("j1", after=first)] == ["progress", "succeeded"]
    owner = JobEvents.decode(redis_client().xrange(events.owner_key("o1")))
    assert [(e.job, e.type) for e in owner] == [
        ("j1", "queued"), ("j1", "progress"), ("j2", "queued"), ("j1", "succeeded")
    ]  # fmt: skip
    with pytest.raises(ValueError, match="unknown job event type"):
        events.publish("j1", "o1", "exploded")
    assert "id: " not in JobEvent("", "failed", "j", 0.0, {}).sse()  # made-up events: no id


def test_queued_then_cancelled_replayed_with_last_event_id(client, tmp_path):
    job_id = post_asset(client, asset_bytes(tmp_path), headers=KEY_A).json()["id"]
    assert client.delete(f"/v1/jobs/{job_id}", headers=KEY_A).status_code == 202
    resp = client.get(f"/v1/jobs/{job_id}/events", headers=KEY_A)
    assert resp.status_code == 200
    assert resp.headers["content-type"].startswith("text/event-stream")
    msgs = parse_sse(resp.text)
    assert [m["event"] for m in msgs] == ["queued", "cancelled"]
    assert all(m["data"]["job"] == job_id and m["data"]["type"] == m["event"] for m in msgs)
    again = client.get(
        f"/v1/jobs/{job_id}/events", headers={**KEY_A, "Last-Event-ID": msgs[0]["id"]}
    )
    assert [m["event"] for m in parse_sse(again.text)] == ["cancelled"]
    # a malformed Last-Event-ID is ignored: the whole history
    bad = client.get(f"/v1/jobs/{job_id}/events", headers={**KEY_A, "Last-Event-ID": "x\ny"})
    assert [m["event"] for m in parse_sse(bad.text)] == ["queued", "cancelled"]


def test_another_keys_job_is_404_and_a_finished_job_without_events_still_ends(
    client, settings, tmp_path
):
    job_id = post_asset(client, asset_bytes(tmp_path), headers=KEY_A).json()["id"]
    other = client.get(f"/v1/jobs/{job_id}/events", headers={"X-API-Key": LONG_KEY_B})
    assert other.status_code == 404
    assert client.get("/v1/jobs/nope/events", headers=KEY_A).status_code == 404
    assert client.delete(f"/v1/jobs/{job_id}", headers=KEY_A).status_code == 202
    redis_client().delete(JobEvents(None, settings.key_prefix).job_key(job_id))  # expired
    msgs = parse_sse(client.get(f"/v1/jobs/{job_id}/events", headers=KEY_A).text)
    assert [m["event"] for m in msgs] == ["cancelled"] and "id" not in msgs[0]
    # deleting the finished job drops its stream
    JobEvents(redis_client(), settings.key_prefix).publish(job_id, "x", "queued")
    assert client.delete(f"/v1/jobs/{job_id}", headers=KEY_A).status_code == 204
    assert not redis_client().exists(JobEvents(None, settings.key_prefix).job_key(job_id))


@pytest.mark.slow
def test_a_jobs_stream_and_the_keys_stream_with_a_real_server_and_worker(tmp_path):
    settings = make_settings(tmp_path)
    try:
        with (
            worker_process(settings, tmp_path / "worker.log"),
            api_server(settings, tmp_path / "api.log") as base,
            httpx.Client(base_url=base, timeout=60) as http,
        ):
            seen: list[dict] = []
            opened = threading.Event()

            def follow_key() -> None:  # the key's stream, open before the job exists
                with http.stream("GET", "/v1/events") as resp:
                    opened.set()
                    buf = ""
                    for chunk in resp.iter_text():
                        buf += chunk
                        *done, buf = buf.split("\n\n")
                        seen.extend(parse_sse("\n\n".join(done) + "\n\n"))
                        if any(m["event"] == "succeeded" for m in seen):
                            return

            follower = threading.Thread(target=follow_key, daemon=True)
            follower.start()
            assert opened.wait(30)
            options = {"method": "bicubic", "scale": 2}
            job_id = post_asset(http, asset_bytes(tmp_path), options=options).json()["id"]
            resp = http.get(f"/v1/jobs/{job_id}/events", timeout=180)  # ends with the job
            msgs = parse_sse(resp.text)
            types = [m["event"] for m in msgs]
            assert types[:2] == ["queued", "started"] and types[-1] == "succeeded", types
            assert "progress" in types and all(t != "failed" for t in types)
            ids = [tuple(map(int, m["id"].split("-"))) for m in msgs]
            assert ids == sorted(ids) and len(set(ids)) == len(ids)
            progress = [m["data"] for m in msgs if m["event"] == "progress"]
            assert all({"stage", "fraction", "eta_s"} <= p.keys() for p in progress)
            assert msgs[-1]["data"]["summary"]
            follower.join(60)
            mine = [m["event"] for m in seen if m["data"]["job"] == job_id]
            assert mine[0] == "queued" and mine[-1] == "succeeded", mine
    finally:
        cleanup_redis(settings)
