"""``/healthz`` (the process answers) and ``/readyz`` (Redis reachable, storage writable)."""

from __future__ import annotations

import contextlib
import os
import uuid

from fastapi import APIRouter, Response

from ..deps import LayoutDep, RedisDep
from ..schemas import Health, Readiness

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health, summary="Liveness")
def healthz() -> Health:
    return Health(status="ok")


@router.get(
    "/readyz",
    response_model=Readiness,
    responses={503: {"model": Readiness, "description": "Redis or storage unavailable."}},
    summary="Readiness: Redis reachable and storage writable",
)
def readyz(response: Response, redis: RedisDep, layout: LayoutDep) -> Readiness:
    try:
        redis_ok = bool(redis.ping())
    except Exception:  # noqa: BLE001 - any failure means not ready
        redis_ok = False
    storage_ok = True
    probe = layout.root / f".ready-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    try:
        probe.write_bytes(b"ok")
    except OSError:
        storage_ok = False
    finally:
        with contextlib.suppress(OSError):
            probe.unlink(missing_ok=True)
    ok = redis_ok and storage_ok
    if not ok:
        response.status_code = 503
    return Readiness(status="ready" if ok else "unavailable", redis=redis_ok, storage=storage_ok)
