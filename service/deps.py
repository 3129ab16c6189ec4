"""FastAPI dependencies: settings, Redis, storage (this machine's folders and the object
store), the queue and the caller's identity."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Request, Security
from fastapi.security import APIKeyHeader
from redis import Redis
from redis.asyncio import Redis as AsyncRedis
from rq import Queue

from pbrsr_jobs.settings import Settings, get_settings
from pbrsr_jobs.store import JobFiles, JobIndex, JobLayout, owner_of

from .problems import ProblemError

SettingsDep = Annotated[Settings, Depends(get_settings)]

_api_key = APIKeyHeader(
    name="X-API-Key",
    auto_error=False,
    description="Required when the server has PBRSR_API_KEYS set; each key sees only its jobs.",
)


# The dependencies below do no I/O: async, so FastAPI runs them on the event loop instead of
# handing each to the thread pool.
async def get_redis(request: Request, settings: SettingsDep) -> Redis:
    """One client (connection pool) per app and Redis URL."""
    clients: dict[str, Redis] = request.app.state.redis_clients
    client = clients.get(settings.redis_url)
    if client is None:
        client = Redis.from_url(
            settings.redis_url,
            socket_connect_timeout=2,
            socket_timeout=10,
            health_check_interval=30,
        )
        clients[settings.redis_url] = client
    return client


RedisDep = Annotated[Redis, Depends(get_redis)]


async def get_async_redis(request: Request, settings: SettingsDep) -> AsyncRedis:
    """An asyncio client (connection pool) per app and Redis URL, for reads on the event loop
    (a job's status); closed with the app."""
    clients: dict[str, AsyncRedis] = request.app.state.async_redis_clients
    client = clients.get(settings.redis_url)
    if client is None:
        client = AsyncRedis.from_url(
            settings.redis_url, socket_connect_timeout=2, socket_timeout=10
        )
        clients[settings.redis_url] = client
    return client


AsyncRedisDep = Annotated[AsyncRedis, Depends(get_async_redis)]


async def get_layout(settings: SettingsDep) -> JobLayout:
    return JobLayout(settings.storage_dir.expanduser())


async def get_files(request: Request) -> JobFiles:
    """The app's object store (one client, built and checked at start-up)."""
    return request.app.state.files


async def get_index(redis: RedisDep, settings: SettingsDep) -> JobIndex:
    return JobIndex(redis, settings.key_prefix)


async def get_queue(redis: RedisDep, settings: SettingsDep) -> Queue:
    return Queue(settings.queue, connection=redis)


async def get_owner(settings: SettingsDep, key: Annotated[str | None, Security(_api_key)]) -> str:
    """The caller's owner tag; 401 when keys are configured and the key is missing/unknown."""
    if not settings.auth_enabled:
        return owner_of(None)
    if key:
        given = key.encode()
        matched = False
        for known in settings.api_keys:  # compare with every key: no early exit to time
            matched |= hmac.compare_digest(given, known.encode())
        if matched:
            return owner_of(key)
    raise ProblemError(
        401,
        "unauthorized",
        "this server needs a valid API key in the X-API-Key header",
        headers={"WWW-Authenticate": "APIKey"},
    )


LayoutDep = Annotated[JobLayout, Depends(get_layout)]
FilesDep = Annotated[JobFiles, Depends(get_files)]
IndexDep = Annotated[JobIndex, Depends(get_index)]
QueueDep = Annotated[Queue, Depends(get_queue)]
OwnerDep = Annotated[str, Depends(get_owner)]
