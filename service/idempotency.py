"""The ``Idempotency-Key`` header of ``POST /v1/jobs`` and ``POST /v1/batches`` (records:
:mod:`pbrsr_jobs.idempotency`).

A retry (same key, same files and form fields) answers 200 with the first job or batch; the
same key with another body is 422 ``idempotency-key-reused``. A retry that arrives while the
first request is still checking its assets waits up to ``WAIT_S`` for it, then answers 409
``idempotency-key-in-progress`` with ``Retry-After``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Annotated

import anyio
from fastapi import Header
from fastapi.concurrency import run_in_threadpool

from pbrsr_jobs.idempotency import IdempotencyKeys, Reservation, fingerprint, valid_key

from .problems import ProblemError
from .uploads import Upload, discard_uploads

WAIT_S = 5.0
POLL_S = 0.1

IdempotencyKeyHeader = Annotated[
    str | None,
    Header(
        alias="Idempotency-Key",
        description="1 to 255 printable ASCII characters, unique per intended job (or batch). "
        "A retry with the same key and the same files and options returns the first (200).",
    ),
]


def check_key(key: str | None) -> str | None:
    """The header's value, or 400 when it is not 1..255 printable ASCII characters."""
    if key is not None and not valid_key(key):
        raise ProblemError(
            400,
            "invalid-idempotency-key",
            "the Idempotency-Key header must be 1 to 255 printable ASCII characters",
        )
    return key


def request_fingerprint(uploads: list[Upload], fields: dict[str, str]) -> str:
    """The fingerprint of a request's files (their digests in order) and form fields."""
    digests = [u.sha256 or "" for u in uploads]
    return fingerprint(",".join(digests) if digests else None, fields)


async def claim(keys: IdempotencyKeys, owner: str, key: str, fp: str) -> Reservation | str:
    """Reserve ``key`` for a request of fingerprint ``fp`` (a :class:`Reservation`), or the id
    an earlier request with the same key and body created. Raises 422 for a reused key and
    409 when the earlier request is still running after ``WAIT_S``."""
    deadline = time.monotonic() + WAIT_S
    while True:
        found = await run_in_threadpool(keys.reserve, owner, key, fp)
        if isinstance(found, Reservation):
            return found
        if found.fingerprint != fp:
            raise ProblemError(
                422,
                "idempotency-key-reused",
                "this Idempotency-Key was already used with another file or other options; "
                "use a new key for a new submission",
            )
        if found.done:
            return found.ref
        if time.monotonic() >= deadline:
            raise ProblemError(
                409,
                "idempotency-key-in-progress",
                "a request with this Idempotency-Key is still being processed; retry shortly",
                headers={"Retry-After": "2"},
            )
        await anyio.sleep(POLL_S)


async def create_once(
    keys: IdempotencyKeys,
    owner: str,
    key: str,
    uploads: list[Upload],
    fields: dict[str, str],
    create: Callable[[], str],
) -> tuple[str, bool]:
    """Run ``create`` (makes the job or batch from ``uploads``, returns its id) at most once
    per ``key`` and body.

    Returns ``(id, True)`` when this request created it, ``(the first request's id, False)``
    for a retry (the uploads are deleted). When ``create`` fails the key is released.
    Creating and recording run shielded from cancellation, so a client that hangs up cannot
    leave a job without its record.
    """
    try:
        found = await claim(keys, owner, key, request_fingerprint(uploads, fields))
    except BaseException:
        discard_uploads(uploads)
        raise
    if isinstance(found, str):
        discard_uploads(uploads)
        return found, False
    with anyio.CancelScope(shield=True):
        try:
            job_id = await run_in_threadpool(create)
        except BaseException:
            await run_in_threadpool(found.release)
            raise
        await run_in_threadpool(found.complete, job_id)
    return job_id, True
