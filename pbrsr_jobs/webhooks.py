"""Webhooks: a job's events POSTed to the URL it names, signed, from the worker side.

A job submitted with ``callback_url`` (and ``callback_events``, default the outcome:
succeeded, failed, cancelled) has ``meta['webhook'] = {"url", "events"}``. Whoever publishes
one of those events (:meth:`pbrsr_jobs.events.JobEvents.publish`) also adds a delivery task
to the Redis stream ``<prefix>:webhooks``; the workers' dispatchers (``worker.webhooks``)
take tasks from it as a consumer group, so a delivery never blocks a job and a task a dead
worker held is taken over by another.

Each delivery is ``POST <url>`` with a JSON body ``{"id", "job", "type", "time", "data"}``
and the headers

- ``X-Pbrsr-Event``: the event type; ``X-Pbrsr-Delivery``: the delivery id (the same on
  every retry of it, so a receiver can drop duplicates);
- ``X-Pbrsr-Timestamp``: Unix seconds of this attempt;
- ``X-Pbrsr-Signature``: ``v1=`` + hex HMAC-SHA256 of ``<timestamp>.<body>`` keyed with the
  API key's webhook secret (``GET /v1/webhook-secret``).

A receiver checks it with :func:`verify` (docs/SERVICE.md has the same in a few lines).
Answers other than 2xx and transport errors are retried with exponential backoff; every
attempt is logged in the job's detail (``deliveries``).
"""

from __future__ import annotations

import hashlib
import hmac
import json
import secrets
import time
import uuid
from typing import Any
from urllib.parse import urlsplit

from pbrsr_core.errors import InvalidOptions

from .events import EVENT_TYPES

SIGNATURE_HEADER = "X-Pbrsr-Signature"
TIMESTAMP_HEADER = "X-Pbrsr-Timestamp"
EVENT_HEADER = "X-Pbrsr-Event"
DELIVERY_HEADER = "X-Pbrsr-Delivery"
DEFAULT_EVENTS = ("succeeded", "failed", "cancelled")
MAX_URL = 2048
LOG_ENTRIES = 100


def parse_webhook(url: str | None, events: str | None) -> dict[str, Any] | None:
    """The form fields ``callback_url`` and ``callback_events`` -> ``{"url", "events"}``, or
    None without a URL; InvalidOptions naming what is wrong."""
    if url is None or not url.strip():
        if events and events.strip():
            raise InvalidOptions("callback_events needs a callback_url")
        return None
    url = url.strip()
    parts = urlsplit(url)
    if len(url) > MAX_URL or parts.scheme not in ("http", "https") or not parts.hostname:
        raise InvalidOptions(
            f"callback_url must be an http or https URL of at most {MAX_URL} characters"
        )
    if parts.username or parts.password:
        raise InvalidOptions("callback_url must not carry credentials; the body is signed")
    chosen = [e.strip() for e in (events or "").split(",") if e.strip()] or list(DEFAULT_EVENTS)
    unknown = [e for e in chosen if e not in EVENT_TYPES]
    if unknown:
        raise InvalidOptions(
            f"callback_events: unknown {', '.join(unknown)!s:.80}; "
            f"choose from {', '.join(EVENT_TYPES)}"
        )
    return {"url": url, "events": sorted(set(chosen), key=EVENT_TYPES.index)}


# ----------------------------------------------------------------------------- secrets
def server_secret(redis: Any, prefix: str, configured: str | None) -> bytes:
    """The server's webhook secret: ``configured`` (PBRSR_WEBHOOK_SECRET), else one made once
    and kept in Redis, so that the API and every worker share it."""
    if configured:
        return configured.encode()
    key = f"{prefix}:webhook-secret"
    redis.set(key, secrets.token_hex(32), nx=True)
    value = redis.get(key)
    return value if isinstance(value, bytes) else str(value).encode()


def key_secret(server: bytes, owner: str) -> str:
    """The signing secret of one API key (its owner tag): derived, never stored."""
    return hmac.new(server, f"webhook:{owner}".encode(), hashlib.sha256).hexdigest()


def sign(secret: str, timestamp: str, body: bytes) -> str:
    mac = hmac.new(secret.encode(), timestamp.encode() + b"." + body, hashlib.sha256)
    return "v1=" + mac.hexdigest()


def verify(
    secret: str,
    timestamp: str,
    body: bytes,
    signature: str,
    tolerance_s: float = 300.0,
    now: float | None = None,
) -> bool:
    """Whether ``signature`` signs ``timestamp.body`` with ``secret`` and the timestamp is
    within ``tolerance_s`` of ``now`` (a replayed old delivery is refused)."""
    try:
        age = abs((time.time() if now is None else now) - float(timestamp))
    except ValueError:
        return False
    return age <= tolerance_s and hmac.compare_digest(sign(secret, timestamp, body), signature)


# ----------------------------------------------------------------------------- the queue
class WebhookQueue:
    """Delivery tasks and delivery logs in Redis (``redis``: a sync client)."""

    GROUP = "dispatchers"

    def __init__(self, redis: Any, prefix: str, log_ttl_s: int = 7 * 86400):
        self.redis = redis
        self.prefix = prefix
        self.log_ttl_s = log_ttl_s

    @property
    def stream(self) -> str:
        return f"{self.prefix}:webhooks"

    @property
    def retries(self) -> str:
        return f"{self.prefix}:webhooks:retry"

    def log_key(self, job_id: str) -> str:
        return f"{self.prefix}:webhooks:log:{job_id}"

    @staticmethod
    def task(job_id: str, owner: str, webhook: dict, type_: str, data: dict, at: float) -> dict:
        body = {"id": uuid.uuid4().hex, "job": job_id, "type": type_, "time": at, "data": data}
        return {"url": webhook["url"], "owner": owner, "attempt": 1, "body": body}

    def add(self, pipe: Any, task: dict) -> None:
        """Queue ``task`` on ``pipe`` (a pipeline the event is published on)."""
        pipe.xadd(self.stream, {"task": json.dumps(task)}, maxlen=100_000, approximate=True)

    def log(self, job_id: str, entry: dict) -> None:
        with self.redis.pipeline(transaction=False) as pipe:
            pipe.lpush(self.log_key(job_id), json.dumps(entry))
            pipe.ltrim(self.log_key(job_id), 0, LOG_ENTRIES - 1)
            pipe.expire(self.log_key(job_id), self.log_ttl_s)
            pipe.execute()

    @staticmethod
    def decode_log(raw: list) -> list[dict]:
        """LRANGE of a log (newest first) -> entries, oldest first."""
        out = []
        for item in reversed(raw or []):
            try:
                out.append(json.loads(item))
            except (TypeError, ValueError):
                continue
        return out

    def deliveries(self, job_id: str) -> list[dict]:
        return self.decode_log(self.redis.lrange(self.log_key(job_id), 0, LOG_ENTRIES - 1))
