"""``/healthz`` (the process answers) and ``/readyz`` (Redis reachable, storage writable)."""

from __future__ import annotations

from fastapi import APIRouter, Response

from pbrsr_jobs.objstore import StoreUnavailable

from ..deps import FilesDep, RedisDep
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
def readyz(response: Response, redis: RedisDep, files: FilesDep) -> Readiness:
    try:
        redis_ok = bool(redis.ping())
    except Exception:  # noqa: BLE001 - any failure means not ready
        redis_ok = False
    try:
        files.store.check()  # an object written and deleted (a folder or the bucket)
        storage_ok = True
    except StoreUnavailable:
        storage_ok = False
    ok = redis_ok and storage_ok
    if not ok:
        response.status_code = 503
    return Readiness(status="ready" if ok else "unavailable", redis=redis_ok, storage=storage_ok)
