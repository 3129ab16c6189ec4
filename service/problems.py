"""Error responses as RFC 9457 problem details (``application/problem+json``).

Every error the API returns has ``type``, ``title``, ``status``, ``detail`` (a sentence a user
can act on) and ``code`` (a stable slug). Bodies never contain tracebacks, server paths or
echoed input: unexpected exceptions become a generic 500 with a reference that appears in
the server log next to the traceback.
"""

from __future__ import annotations

import logging
import uuid
from http import HTTPStatus
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException

from pbrsr_core.errors import PbrsrError
from pbrsr_jobs.objstore import StoreUnavailable

log = logging.getLogger("pbrsr.service")

PROBLEM_JSON = "application/problem+json"


class FieldError(BaseModel):
    loc: list[str | int] = Field(description="Where: e.g. ['query', 'limit'].")
    msg: str


class Problem(BaseModel):
    """An error response body."""

    type: str = Field("about:blank", description="A URI naming the kind of problem.")
    title: str = Field(description="Short summary of the kind of problem (the HTTP reason).")
    status: int
    detail: str = Field(description="What is wrong, in words a user can act on.")
    code: str = Field(description="Stable machine-readable slug, e.g. 'invalid-asset'.")
    errors: list[FieldError] | None = None


class ProblemError(Exception):
    """Raise from a route to answer with a problem body."""

    def __init__(
        self, status: int, code: str, detail: str, *, headers: dict[str, str] | None = None
    ):
        super().__init__(detail)
        self.status = status
        self.code = code
        self.detail = detail
        self.headers = headers


def problem_response(
    status: int,
    code: str,
    detail: str,
    *,
    headers: dict[str, str] | None = None,
    errors: list[dict[str, Any]] | None = None,
) -> JSONResponse:
    title = HTTPStatus(status).phrase if status in HTTPStatus._value2member_map_ else "Error"
    body = Problem(
        type=f"https://pbrsr.dev/problems/{code}",
        title=title,
        status=status,
        detail=detail,
        code=code,
        errors=[FieldError(**e) for e in errors] if errors else None,
    )
    return JSONResponse(
        body.model_dump(exclude_none=True),
        status_code=status,
        headers=headers,
        media_type=PROBLEM_JSON,
    )


# Responses every /v1 route may give, for the OpenAPI document.
PROBLEM_RESPONSES: dict[int | str, dict[str, Any]] = {
    401: {"model": Problem, "description": "Missing or unknown X-API-Key."},
    503: {"model": Problem, "description": "The job queue (Redis) or storage is unreachable."},
}

_SLUGS = {
    400: "bad-request",
    401: "unauthorized",
    403: "forbidden",
    404: "not-found",
    405: "method-not-allowed",
    409: "conflict",
    413: "too-large",
    415: "unsupported-media-type",
    422: "invalid-request",
    503: "unavailable",
}


def _where(loc: list[str | int]) -> str:
    parts = [str(p) for p in loc if p not in ("body", "query", "path", "header")]
    return ".".join(parts) or "request"


def install_handlers(app: FastAPI) -> None:
    """Map every exception to a problem body."""
    import redis.exceptions

    @app.exception_handler(ProblemError)
    async def _problem(_: Request, exc: ProblemError) -> JSONResponse:
        return problem_response(exc.status, exc.code, exc.detail, headers=exc.headers)

    @app.exception_handler(PbrsrError)
    async def _pbrsr(_: Request, exc: PbrsrError) -> JSONResponse:
        status = exc.http_status if 400 <= exc.http_status < 600 else 500
        return problem_response(status, exc.code, exc.message)

    @app.exception_handler(RequestValidationError)
    async def _validation(_: Request, exc: RequestValidationError) -> JSONResponse:
        errors = [
            {
                "loc": [p for p in e.get("loc", ()) if isinstance(p, (str, int))],
                "msg": str(e.get("msg", "invalid")),
            }
            for e in exc.errors()
        ]
        detail = "; ".join(f"{_where(e['loc'])}: {e['msg']}" for e in errors)
        return problem_response(422, "invalid-request", detail or "invalid request", errors=errors)

    @app.exception_handler(StarletteHTTPException)
    async def _http(_: Request, exc: StarletteHTTPException) -> JSONResponse:
        detail = exc.detail if isinstance(exc.detail, str) else HTTPStatus(exc.status_code).phrase
        if exc.status_code == 404 and detail == "Not Found":
            detail = "no such resource"
        return problem_response(
            exc.status_code,
            _SLUGS.get(exc.status_code, "error"),
            detail,
            headers=getattr(exc, "headers", None),
        )

    @app.exception_handler(redis.exceptions.ConnectionError)
    @app.exception_handler(redis.exceptions.TimeoutError)
    async def _redis(_: Request, exc: Exception) -> JSONResponse:
        log.warning("redis unavailable: %s", exc)
        return problem_response(
            503,
            "queue-unavailable",
            "the job queue is unavailable right now; try again in a minute",
            headers={"Retry-After": "30"},
        )

    @app.exception_handler(StoreUnavailable)
    async def _store(_: Request, exc: StoreUnavailable) -> JSONResponse:
        log.warning("job storage unavailable: %s", exc)
        return problem_response(
            503,
            "storage-unavailable",
            "the job storage is unavailable right now; try again in a minute",
            headers={"Retry-After": "30"},
        )

    @app.exception_handler(Exception)
    async def _internal(_: Request, exc: Exception) -> JSONResponse:
        ref = uuid.uuid4().hex[:12]
        log.error("internal error (reference %s)", ref, exc_info=exc)
        return problem_response(
            500,
            "internal-error",
            f"internal server error (reference {ref}); the administrator can find the details "
            "in the server log",
        )
