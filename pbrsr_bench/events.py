"""The service benchmarks' view of job events: Server-Sent Events clients and a webhook
receiver, both in the benchmark process, and what each of them saw.

:class:`EventWatch` follows the caller's key stream (``/v1/events``) from the moment it is
started, and each job's own stream (``/v1/jobs/{id}/events``) once :meth:`EventWatch.job`
names the job; the streams are read by one asyncio loop in a thread of their own, and a
stream that drops is reopened with the last id seen (``Last-Event-ID``), as a browser does.
:class:`WebhookReceiver` is a local HTTP endpoint for ``callback_url`` that checks every
delivery's signature (:func:`pbrsr_jobs.webhooks.verify`) and answers 200, or 401 to a bad
one. Every event either of them receives is a :class:`Received`.

:func:`delivery_report` compares the channels: the job's own stream (what was published, the
terminal event included) against the key stream and the webhooks; an event one of them
lacks is lost. Latency is receipt time minus the event's ``time`` (both this machine's
clock); events a job stream replays (published before the stream opened) are counted but
not timed.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import threading
import time
from collections.abc import Iterable
from concurrent.futures import Future
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import numpy as np

from pbrsr_jobs.events import EVENT_TYPES, TERMINAL_EVENTS
from pbrsr_jobs.webhooks import DELIVERY_HEADER, SIGNATURE_HEADER, TIMESTAMP_HEADER, verify

WEBHOOK_EVENTS = tuple(t for t in EVENT_TYPES if t != "progress")
"""The events the benchmarks' jobs ask webhooks for: every one but progress (which the
streams carry at most once a second and a pipeline may skip)."""


@dataclass(frozen=True)
class Received:
    """One event as a client got it."""

    channel: str  # "job" (the job's stream), "key" (the key's stream) or "webhook"
    job: str
    type: str
    time: float  # the event's own timestamp, set where it was published
    at: float  # time.time() on receipt
    live: bool  # published while the stream was open (a replayed event is not timed)
    data: dict[str, Any] = field(default_factory=dict, compare=False)


def parse_sse(lines: Iterable[str]) -> list[dict[str, str]]:
    """Server-Sent Events text lines -> messages ``{"id", "event", "data"}`` (comments and
    ``retry:`` lines dropped; a message ends at an empty line)."""
    out: list[dict[str, str]] = []
    message: dict[str, str] = {}
    for line in lines:
        if not line:
            if "data" in message:
                out.append(message)
            message = {}
            continue
        if line.startswith(":"):
            continue
        name, _, value = line.partition(":")
        value = value[1:] if value.startswith(" ") else value
        if name == "data" and "data" in message:
            message["data"] += "\n" + value
        elif name in ("id", "event", "data"):
            message[name] = value
    return out


class EventWatch:
    """SSE clients of the key stream and of each named job's stream (see the module
    docstring). Use as a context manager, or :meth:`start` and :meth:`close`."""

    def __init__(self, base_url: str, timeout: float = 60.0):
        self.base_url = base_url
        self.timeout = timeout
        self.received: list[Received] = []
        self.errors: list[str] = []
        self.reconnects = 0
        self._lock = threading.Lock()
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, daemon=True)
        self._client: Any = None
        self._key_open = threading.Event()

    # -- lifecycle -------------------------------------------------------------------------
    def start(self, key_stream: bool = True) -> EventWatch:
        """Open the HTTP client and, with ``key_stream``, follow ``/v1/events`` from now on."""
        self._thread.start()
        self._submit(self._open_client()).result(timeout=30)
        if key_stream:
            # the key stream's ids are Redis's "<ms>-<seq>": starting after this millisecond
            # misses nothing published from now on and replays nothing earlier
            after = f"{int(time.time() * 1000) - 1}-0"
            self._submit(self._follow("/v1/events", "key", after))
            if not self._key_open.wait(self.timeout):
                raise TimeoutError("the key's event stream did not open")
        return self

    def close(self) -> None:
        """Stop every stream and the loop."""
        if self._thread.is_alive():
            with contextlib.suppress(Exception):
                self._submit(self._shutdown()).result(timeout=30)
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(timeout=10)
        if not self._loop.is_closed() and not self._loop.is_running():
            self._loop.close()

    def __enter__(self) -> EventWatch:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def job(self, job_id: str) -> None:
        """Follow ``job_id``'s own stream (its whole history, then live until its outcome)."""
        self._submit(self._follow(f"/v1/jobs/{job_id}/events", "job"))

    # -- reading ---------------------------------------------------------------------------
    def events(self, channel: str | None = None) -> list[Received]:
        with self._lock:
            return [r for r in self.received if channel is None or r.channel == channel]

    def terminal(self, job_id: str, channel: str = "job") -> Received | None:
        """The first outcome event of ``job_id`` seen on ``channel``, if any."""
        return next(
            (r for r in self.events(channel) if r.job == job_id and r.type in TERMINAL_EVENTS),
            None,
        )

    def wait_outcomes(
        self, job_ids: list[str], timeout: float, receiver: WebhookReceiver | None = None
    ) -> float:
        """Wait up to ``timeout`` s until every job's outcome has arrived on its own stream,
        on the key stream and (with ``receiver``) by webhook; returns the seconds waited."""
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < timeout:
            hooks = set(job_ids) if receiver is None else receiver.outcomes()
            if all(
                j in hooks and self.terminal(j, "job") and self.terminal(j, "key") for j in job_ids
            ):
                break
            time.sleep(0.1)
        return time.perf_counter() - t0

    def wait_terminal(self, job_id: str, timeout: float, channel: str = "job") -> Received:
        """Block until ``job_id``'s outcome arrives on ``channel``; TimeoutError after
        ``timeout`` s."""
        deadline = time.monotonic() + timeout
        while (seen := self.terminal(job_id, channel)) is None:
            if time.monotonic() > deadline:
                raise TimeoutError(f"no outcome event of job {job_id} within {timeout:.0f} s")
            time.sleep(0.02)
        return seen

    # -- the loop's side -------------------------------------------------------------------
    def _submit(self, coro: Any) -> Future:
        return asyncio.run_coroutine_threadsafe(coro, self._loop)

    async def _open_client(self) -> None:
        import httpx

        limits = httpx.Limits(max_connections=None, max_keepalive_connections=None)
        # an open stream may be silent up to the server's keepalive (15 s)
        timeout = httpx.Timeout(self.timeout, read=60.0)
        self._client = httpx.AsyncClient(base_url=self.base_url, timeout=timeout, limits=limits)

    async def _shutdown(self) -> None:
        current = asyncio.current_task()
        for task in asyncio.all_tasks():
            if task is not current:
                task.cancel()
        await asyncio.sleep(0)
        if self._client is not None:
            await self._client.aclose()

    async def _follow(self, path: str, channel: str, last_id: str | None = None) -> None:
        """Read one stream until its outcome (job streams) or until cancelled, reopening it
        with the last id seen when it drops."""
        import httpx

        ends = channel == "job"
        while True:
            headers = {"Last-Event-ID": last_id} if last_id else {}
            try:
                async with self._client.stream("GET", path, headers=headers) as resp:
                    if resp.status_code != 200:
                        self._error(f"{path}: HTTP {resp.status_code}")
                        return
                    opened = time.time()
                    if channel == "key":
                        self._key_open.set()
                    lines: list[str] = []
                    async for line in resp.aiter_lines():
                        lines.append(line)
                        if line:
                            continue
                        for message in parse_sse(lines):
                            last_id = message.get("id") or last_id
                            done = self._record(channel, message, opened) and ends
                            if done:
                                return
                        lines = []
            except httpx.HTTPError as exc:
                self._error(f"{path}: {type(exc).__name__}: {exc}")
                await asyncio.sleep(0.5)
            with self._lock:
                self.reconnects += 1

    def _record(self, channel: str, message: dict[str, str], opened: float) -> bool:
        """Keep one SSE message; whether it was an outcome."""
        now = time.time()
        try:
            body = json.loads(message["data"])
            event = Received(
                channel,
                str(body["job"]),
                str(body["type"]),
                float(body["time"]),
                now,
                float(body["time"]) >= opened,
                body,
            )
        except (ValueError, KeyError, TypeError) as exc:
            self._error(
                f"{channel} stream: unreadable event {message.get('data', '')[:80]!r}: {exc}"
            )
            return False
        with self._lock:
            self.received.append(event)
        return event.type in TERMINAL_EVENTS

    def _error(self, what: str) -> None:
        with self._lock:
            self.errors.append(what)


class WebhookReceiver:
    """A local endpoint for ``callback_url`` (``secret``: the API key's webhook secret);
    every delivery with a good signature is a :class:`Received`, kept once per delivery id."""

    def __init__(self, secret: str):
        self.secret = secret
        self.received: list[Received] = []
        self.deliveries: set[str] = set()
        self.duplicates = 0
        self.bad_signatures = 0
        self._lock = threading.Lock()
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802 - http.server's name
                body = self.rfile.read(int(self.headers.get("Content-Length") or 0))
                ok = receiver.accept(dict(self.headers), body)
                self.send_response(200 if ok else 401)
                self.send_header("Content-Length", "0")
                self.end_headers()

            def log_message(self, *args: Any) -> None:
                pass

        self._server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self._server.server_port}/hook"
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True)

    def accept(self, headers: dict[str, str], body: bytes) -> bool:
        """Check and keep one delivery; False for a bad signature or body."""
        now = time.time()
        stamp = headers.get(TIMESTAMP_HEADER, "")
        if not verify(self.secret, stamp, body, headers.get(SIGNATURE_HEADER, "")):
            with self._lock:
                self.bad_signatures += 1
            return False
        try:
            payload = json.loads(body)
            event = Received(
                "webhook",
                str(payload["job"]),
                str(payload["type"]),
                float(payload["time"]),
                now,
                True,
                payload.get("data") or {},
            )
        except (ValueError, KeyError, TypeError):
            with self._lock:
                self.bad_signatures += 1
            return False
        delivery = headers.get(DELIVERY_HEADER) or str(payload.get("id"))
        with self._lock:
            if delivery in self.deliveries:
                self.duplicates += 1
            else:
                self.deliveries.add(delivery)
                self.received.append(event)
        return True

    def events(self) -> list[Received]:
        with self._lock:
            return list(self.received)

    def outcomes(self) -> set[str]:
        """The jobs whose outcome was delivered."""
        return {e.job for e in self.events() if e.type in TERMINAL_EVENTS}

    def start(self) -> WebhookReceiver:
        self._thread.start()
        return self

    def close(self) -> None:
        if self._thread.is_alive():
            self._server.shutdown()
        self._server.server_close()

    def __enter__(self) -> WebhookReceiver:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


def latencies_ms(events: Iterable[Received]) -> list[float]:
    """Receipt minus publication (ms) of the live events."""
    return [(e.at - e.time) * 1e3 for e in events if e.live]


def latency_ms(events: Iterable[Received]) -> dict[str, Any]:
    """Count, p50, p99 and max of :func:`latencies_ms`."""
    lat = np.asarray(latencies_ms(events), dtype=np.float64)
    if not lat.size:
        return {"timed": 0, "p50_ms": None, "p99_ms": None, "max_ms": None}
    return {
        "timed": int(lat.size),
        "p50_ms": float(np.percentile(lat, 50)),
        "p99_ms": float(np.percentile(lat, 99)),
        "max_ms": float(lat.max()),
    }


def delivery_report(
    job_ids: list[str], watch: EventWatch, receiver: WebhookReceiver | None
) -> dict[str, Any]:
    """Per channel: events received, latency, and events lost: a job without an outcome on
    its own stream, and every event of the job streams (of the types the webhooks asked for,
    for them) that the key stream or the webhooks did not deliver."""
    wanted = set(job_ids)
    raw: dict[str, list[Received]] = {}

    def keys(events: Iterable[Received]) -> set[tuple[str, str, float]]:
        return {(e.job, e.type, round(e.time, 3)) for e in events if e.job in wanted}

    job_events = raw["sse_job"] = [e for e in watch.events("job") if e.job in wanted]
    published = keys(job_events)
    channels: dict[str, dict[str, Any]] = {}
    no_outcome = sorted(j for j in job_ids if watch.terminal(j, "job") is None)
    channels["sse_job"] = {
        "events": len(job_events),
        "lost": len(no_outcome),
        "lost_samples": [f"{j}: no outcome" for j in no_outcome[:10]],
        **latency_ms(job_events),
    }
    key_events = raw["sse_key"] = [e for e in watch.events("key") if e.job in wanted]
    missing = sorted(published - keys(key_events))
    channels["sse_key"] = {
        "events": len(key_events),
        "lost": len(missing),
        "lost_samples": [f"{j}: {t} at {at:.3f}" for j, t, at in missing[:10]],
        **latency_ms(key_events),
    }
    if receiver is not None:
        hooks = raw["webhook"] = [e for e in receiver.events() if e.job in wanted]
        asked = {k for k in published if k[1] in WEBHOOK_EVENTS}
        missing = sorted(asked - keys(hooks))
        channels["webhook"] = {
            "events": len(hooks),
            "lost": len(missing),
            "lost_samples": [f"{j}: {t} at {at:.3f}" for j, t, at in missing[:10]],
            "duplicates": receiver.duplicates,
            **latency_ms(hooks),
        }
    return {
        "jobs": len(job_ids),
        "channels": channels,
        "bad_signatures": 0 if receiver is None else receiver.bad_signatures,
        "stream_errors": len(watch.errors),
        "stream_error_samples": watch.errors[:10],
        "reconnects": watch.reconnects,
        "lost": sum(c["lost"] for c in channels.values()),
        "latencies_ms": {c: latencies_ms(events) for c, events in raw.items()},
    }
