"""Job events: what happened to a job, in order, for Server-Sent Events and webhooks.

Every event goes into two Redis streams: the job's own (``<prefix>:events:job:<id>``, the
whole life of one job) and its owner's (``<prefix>:events:owner:<owner>``, every job of one
API key). A stream entry's id is the event's id, so a client that reconnects with the last id
it saw (``Last-Event-ID``) gets exactly what it missed. Streams are capped (approximately)
and expire with the jobs.

Types: ``queued`` (intake), ``started`` (a worker took it; again on a retry), ``progress``
(at most one a second while it runs), and one terminal event: ``succeeded``, ``failed`` or
``cancelled``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from typing import Any

from .store import JobState

EVENT_TYPES = ("queued", "started", "progress", "succeeded", "failed", "cancelled")
TERMINAL_EVENTS = frozenset({"succeeded", "failed", "cancelled"})
STATE_EVENTS = {
    JobState.QUEUED: "queued",
    JobState.RUNNING: "started",
    JobState.FINISHED: "succeeded",
    JobState.FAILED: "failed",
    JobState.CANCELED: "cancelled",
}


@dataclass(frozen=True)
class JobEvent:
    id: str
    type: str
    job: str
    time: float
    data: dict[str, Any]

    def sse(self) -> str:
        """The event as one Server-Sent Events message."""
        body = json.dumps({"job": self.job, "type": self.type, "time": self.time, **self.data})
        head = f"id: {self.id}\n" if self.id else ""  # an event made up from the job's state
        return f"{head}event: {self.type}\ndata: {body}\n\n"


def _text(value: Any) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


class JobEvents:
    """Publish and read job events (``redis``: a sync or asyncio client for reading; the
    publishing side is sync)."""

    def __init__(
        self,
        redis: Any,
        prefix: str,
        *,
        job_maxlen: int = 2000,
        owner_maxlen: int = 20000,
        ttl_s: int = 7 * 86400,
    ):
        self.redis = redis
        self.prefix = prefix
        self.job_maxlen = job_maxlen
        self.owner_maxlen = owner_maxlen
        self.ttl_s = ttl_s

    def job_key(self, job_id: str) -> str:
        return f"{self.prefix}:events:job:{job_id}"

    def owner_key(self, owner: str) -> str:
        return f"{self.prefix}:events:owner:{owner}"

    def publish(
        self,
        job_id: str,
        owner: str,
        type_: str,
        data: dict[str, Any] | None = None,
        webhook: dict[str, Any] | None = None,
    ) -> str:
        """Append one event to the job's and the owner's streams, and a delivery task when the
        job's ``webhook`` (``meta['webhook']``) asks for this type; returns the job stream's
        id."""
        from .webhooks import WebhookQueue

        if type_ not in EVENT_TYPES:
            raise ValueError(f"unknown job event type {type_!r}")
        at = round(time.time(), 3)
        fields = {
            "type": type_,
            "job": job_id,
            "time": f"{at:.3f}",
            "data": json.dumps(data or {}, allow_nan=False),
        }
        pipe = self.redis.pipeline(transaction=False)
        pipe.xadd(self.job_key(job_id), fields, maxlen=self.job_maxlen, approximate=True)
        pipe.expire(self.job_key(job_id), self.ttl_s)
        pipe.xadd(self.owner_key(owner), fields, maxlen=self.owner_maxlen, approximate=True)
        pipe.expire(self.owner_key(owner), self.ttl_s)
        if webhook and type_ in webhook.get("events", ()):
            queue = WebhookQueue(self.redis, self.prefix)
            queue.add(pipe, queue.task(job_id, owner, webhook, type_, data or {}, at))
        return _text(pipe.execute()[0])

    def forget(self, job_id: str) -> None:
        """Drop a deleted job's stream (its events stay in the owner's until they age out)."""
        self.redis.delete(self.job_key(job_id))

    @staticmethod
    def decode(entries: list) -> list[JobEvent]:
        """XRANGE/XREAD entries -> events."""
        out = []
        for entry_id, fields in entries:
            f = {_text(k): _text(v) for k, v in fields.items()}
            out.append(
                JobEvent(
                    id=_text(entry_id),
                    type=f.get("type", ""),
                    job=f.get("job", ""),
                    time=float(f.get("time", 0.0)),
                    data=json.loads(f.get("data") or "{}"),
                )
            )
        return out

    def history(self, job_id: str, after: str = "-") -> list[JobEvent]:
        """The job's events after ``after`` (an event id; "-": all), sync client."""
        start = "-" if after == "-" else f"({after}"
        return self.decode(self.redis.xrange(self.job_key(job_id), min=start))
