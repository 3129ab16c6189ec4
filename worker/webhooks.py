"""The webhook dispatcher each worker runs beside its jobs (pbrsr_jobs.webhooks).

A daemon thread reads delivery tasks from the ``<prefix>:webhooks`` stream as a member of one
consumer group, so the workers share them and each task goes to one of them. A delivery is a
signed POST with a timeout; a 2xx ends it, anything else is retried after ``backoff_s``,
2x, 4x ... up to ``max_attempts`` (the retry waits in a sorted set, not in the thread). A task
a dead worker held for ``claim_after_s`` is taken over by another dispatcher. Every attempt is
logged to the job's delivery log.
"""

from __future__ import annotations

import json
import logging
import random
import threading
import time
from typing import Any

from redis.exceptions import RedisError, ResponseError

from pbrsr_jobs.webhooks import (
    DELIVERY_HEADER,
    EVENT_HEADER,
    SIGNATURE_HEADER,
    TIMESTAMP_HEADER,
    WebhookQueue,
    key_secret,
    server_secret,
    sign,
)

log = logging.getLogger("pbrsr.worker.webhooks")


class WebhookDispatcher(threading.Thread):
    def __init__(
        self,
        redis: Any,
        prefix: str,
        *,
        name: str,
        secret: str | None = None,
        timeout_s: float = 10.0,
        max_attempts: int = 6,
        backoff_s: float = 2.0,
        claim_after_s: float = 60.0,
    ):
        super().__init__(name=f"webhooks-{name}", daemon=True)
        self.queue = WebhookQueue(redis, prefix)
        self.redis = redis
        self.prefix = prefix
        self.consumer = name
        self.secret = secret
        self.timeout_s = timeout_s
        self.max_attempts = max_attempts
        self.backoff_s = backoff_s
        self.claim_after_s = claim_after_s
        self.stopping = threading.Event()
        self.delivered = 0

    def stop(self, timeout: float = 15.0) -> None:
        self.stopping.set()
        if self.is_alive():
            self.join(timeout)

    # -- the loop --------------------------------------------------------------------------
    def run(self) -> None:
        import httpx

        with httpx.Client(timeout=self.timeout_s, follow_redirects=False) as client:
            while not self.stopping.is_set():
                try:
                    self._ensure_group()
                    self._requeue_due()
                    for entry_id, task in self._take():
                        self._deliver(client, entry_id, task)
                except RedisError as exc:  # Redis away for a moment: try again shortly
                    log.warning("webhook dispatcher: %s", exc)
                    self.stopping.wait(2.0)

    def _ensure_group(self) -> None:
        try:
            self.redis.xgroup_create(self.queue.stream, WebhookQueue.GROUP, id="0", mkstream=True)
        except ResponseError as exc:
            if "BUSYGROUP" not in str(exc):
                raise

    def _requeue_due(self) -> None:
        """Retries whose time has come go back into the stream."""
        now = time.time()
        due = self.redis.zrangebyscore(self.queue.retries, "-inf", now, start=0, num=50)
        for raw in due:
            if self.redis.zrem(self.queue.retries, raw):  # this dispatcher won it
                with self.redis.pipeline(transaction=False) as pipe:
                    self.queue.add(pipe, json.loads(raw))
                    pipe.execute()

    def _take(self) -> list[tuple[str, dict]]:
        """Tasks held too long by a dispatcher that went away, else new ones (waits 1 s)."""
        idle_ms = int(self.claim_after_s * 1000)
        claimed = self.redis.xautoclaim(
            self.queue.stream, WebhookQueue.GROUP, self.consumer, idle_ms, "0-0", count=10
        )
        entries = claimed[1] if claimed else []
        if not entries:
            reply = self.redis.xreadgroup(
                WebhookQueue.GROUP, self.consumer, {self.queue.stream: ">"}, count=10, block=1000
            )
            entries = reply[0][1] if reply else []
        out = []
        for entry_id, fields in entries:
            if not fields:  # deleted while pending
                self.redis.xack(self.queue.stream, WebhookQueue.GROUP, entry_id)
                continue
            raw = fields.get(b"task") or fields.get("task")
            out.append((entry_id, json.loads(raw)))
        return out

    # -- one delivery ----------------------------------------------------------------------
    def _deliver(self, client: Any, entry_id: Any, task: dict) -> None:
        import httpx

        body = json.dumps(task["body"], separators=(",", ":")).encode()
        stamp = str(int(time.time()))
        secret = key_secret(server_secret(self.redis, self.prefix, self.secret), task["owner"])
        headers = {
            "Content-Type": "application/json",
            "User-Agent": "pbrsr-webhooks",
            EVENT_HEADER: task["body"]["type"],
            DELIVERY_HEADER: task["body"]["id"],
            TIMESTAMP_HEADER: stamp,
            SIGNATURE_HEADER: sign(secret, stamp, body),
        }
        t0 = time.perf_counter()
        status, error = None, None
        try:
            status = client.post(task["url"], content=body, headers=headers).status_code
        except httpx.HTTPError as exc:
            error = f"{type(exc).__name__}: {str(exc)[:200]}"
        ok = status is not None and 200 <= status < 300
        if not ok and error is None:
            error = f"HTTP {status}"
        attempt = int(task.get("attempt", 1))
        retry_in = None
        if not ok and attempt < self.max_attempts:
            retry_in = self.backoff_s * 2 ** (attempt - 1) * random.uniform(1.0, 1.25)
        entry = {
            "delivery": task["body"]["id"],
            "event": task["body"]["type"],
            "attempt": attempt,
            "at": round(time.time(), 3),
            "ms": round((time.perf_counter() - t0) * 1e3, 1),
            "status": status,
            "ok": ok,
            "error": error,
            "retry_in_s": None if retry_in is None else round(retry_in, 2),
        }
        job_id = task["body"]["job"]
        self.queue.log(job_id, entry)
        with self.redis.pipeline(transaction=False) as pipe:
            if retry_in is not None:
                again = {**task, "attempt": attempt + 1}
                pipe.zadd(self.queue.retries, {json.dumps(again): time.time() + retry_in})
            pipe.xack(self.queue.stream, WebhookQueue.GROUP, entry_id)
            pipe.xdel(self.queue.stream, entry_id)
            pipe.execute()
        if ok:
            self.delivered += 1
        else:
            log.info(
                "webhook %s for job %s: %s (attempt %d)", entry["event"], job_id, error, attempt
            )
