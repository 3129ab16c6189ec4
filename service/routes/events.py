"""Server-Sent Events: ``/v1/jobs/{id}/events`` (one job, from its queueing to its outcome)
and ``/v1/events`` (every job of the caller's key). See :mod:`pbrsr_jobs.events`.

A client that reconnects sends the last id it saw as ``Last-Event-ID`` (a browser's
EventSource does so itself) and gets exactly what it missed. Without it, the job stream
replays the job's whole history and the key's stream starts with what happens next. A
comment line every ``KEEPALIVE_S`` keeps proxies from closing an idle stream.
"""

from __future__ import annotations

import logging
import time
from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import APIRouter, Header, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import StreamingResponse
from redis.exceptions import RedisError

from pbrsr_jobs.events import STATE_EVENTS, TERMINAL_EVENTS, JobEvent, JobEvents

from ..deps import IndexDep, OwnerDep, RedisDep, SettingsDep
from ..job_views import state_of
from ..problems import PROBLEM_RESPONSES, Problem
from .jobs import fetch_job

log = logging.getLogger("pbrsr.service")
router = APIRouter(tags=["events"], responses=PROBLEM_RESPONSES)

KEEPALIVE_S = 15.0
_ID_CHARS = set("0123456789-")
_SSE = {200: {"content": {"text/event-stream": {}}, "description": "An event stream."}}
LastEventId = Annotated[str | None, Header(alias="Last-Event-ID")]


def _checked_id(last_id: str | None, default: str) -> str:
    """A stream id ``<ms>-<seq>`` from the client, or ``default`` for anything else."""
    if last_id and len(last_id) <= 41 and set(last_id) <= _ID_CHARS and last_id.count("-") == 1:
        return last_id
    return default


async def _stream(url: str, request: Request, key: str, after: str, stop_on_terminal: bool):
    """The stream's events from ``after`` on, read with blocking XREADs on a connection of
    its own (closed when the stream ends)."""
    from redis.asyncio import Redis as AsyncRedis

    # a blocking read waits up to KEEPALIVE_S: the socket's own timeout must be longer
    client = AsyncRedis.from_url(url, socket_connect_timeout=2, socket_timeout=KEEPALIVE_S + 15)
    try:
        yield "retry: 2000\n\n"
        if after == "$":  # "from now": pinned to the newest id, so nothing falls between reads
            newest = await client.xrevrange(key, count=1)
            after = JobEvents.decode(newest)[0].id if newest else "0-0"
        while not await request.is_disconnected():
            reply = await client.xread({key: after}, count=200, block=int(KEEPALIVE_S * 1000))
            if not reply:
                yield ": keepalive\n\n"
                continue
            for event in JobEvents.decode(reply[0][1]):
                after = event.id
                yield event.sse()
                if stop_on_terminal and event.type in TERMINAL_EVENTS:
                    return
    except RedisError as exc:  # the client reconnects (retry: 2 s) from the last id it saw
        log.warning("event stream %s ended: %s", key, exc)
    finally:
        await client.aclose()


def _response(body: AsyncIterator[str]) -> StreamingResponse:
    headers = {"Cache-Control": "no-cache", "X-Accel-Buffering": "no"}
    return StreamingResponse(body, media_type="text/event-stream", headers=headers)


@router.get(
    "/v1/jobs/{job_id}/events",
    response_class=StreamingResponse,
    responses={**_SSE, 404: {"model": Problem, "description": "No such job (or not yours)."}},
    summary="Events of one job (Server-Sent Events)",
)
async def job_events(
    job_id: str,
    request: Request,
    redis: RedisDep,
    owner: OwnerDep,
    index: IndexDep,
    settings: SettingsDep,
    last_event_id: LastEventId = None,
) -> StreamingResponse:
    """queued, started, progress (at most one a second), then one of succeeded, failed or
    cancelled, after which the stream ends. ``data`` is JSON with ``job``, ``type``,
    ``time`` and the event's fields (progress: stage, step, total, fraction, eta_s, losses,
    metrics; failed: error, code; succeeded: summary)."""
    job = await run_in_threadpool(fetch_job, job_id, owner, redis, index)  # 404 unless yours
    events = JobEvents(redis, settings.key_prefix)
    after = _checked_id(last_event_id, "0-0")
    state = state_of(job)
    if state.is_terminal:  # what it missed, and the outcome even if its events have expired
        past = await run_in_threadpool(events.history, job_id, after)
        if not any(e.type in TERMINAL_EVENTS for e in past):
            meta = job.meta or {}
            data = {k: meta[k] for k in ("error", "code", "summary") if k in meta}
            past.append(JobEvent("", STATE_EVENTS[state], job_id, time.time(), data))
        return _response(_replay(past))
    key = events.job_key(job_id)
    return _response(_stream(settings.redis_url, request, key, after, True))


async def _replay(events: list[JobEvent]) -> AsyncIterator[str]:
    for event in events:
        yield event.sse()


@router.get("/v1/events", response_class=StreamingResponse, responses=_SSE,
            summary="Events of all your jobs (Server-Sent Events)")  # fmt: skip
async def owner_events(
    request: Request,
    owner: OwnerDep,
    settings: SettingsDep,
    last_event_id: LastEventId = None,
) -> StreamingResponse:
    """Every event of every job of the caller's API key, as ``/v1/jobs/{id}/events`` sends
    them; the stream stays open. Without ``Last-Event-ID`` it starts with the next event."""
    key = JobEvents(None, settings.key_prefix).owner_key(owner)
    return _response(
        _stream(settings.redis_url, request, key, _checked_id(last_event_id, "$"), False)
    )
