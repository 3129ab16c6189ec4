"""The ``Idempotency-Key`` header of ``POST /v1/jobs`` (records: :mod:`pbrsr_jobs.idempotency`).

A retry (same key, same file and form fields) answers 200 with the first job; the same key with
another body is 422 ``idempotency-key-reused``. A retry that arrives while the first request
is still checking its asset waits up to ``WAIT_S`` for it, then answers 409
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
from .uploads import Upload

WAIT_S = 5.0
POLL_S = 0.1

IdempotencyKeyHeader = Annotated[
    str | None,
    Header(
        alias="Idempotency-Key",
        description="1 to 255 printable ASCII characters, unique per intended job. A retry "
        "with the same key and the same file and options returns the first job (200).",
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


async def claim(keys: IdempotencyKeys, owner: str, key: str, upload: Upload) -> Reservation | str:
    """Reserve ``key`` for this request (a :class:`Reservation`), or the id of the job an
    earlier request with the same key and body created. Raises 422 for a reused key and 409
    when the earlier request is still running after ``WAIT_S``."""
    fp = fingerprint(upload.sha256, upload.fields)
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
                "use a new key for a new job",
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
    keys: IdempotencyKeys, owner: str, key: str, upload: Upload, create: Callable[[], str]
) -> tuple[str, bool]:
    """Run ``create`` (makes the job, returns its id) at most once per ``key`` and body.

    Returns ``(job id, True)`` when this request created the job, ``(first job's id, False)``
    for a retry (the upload is deleted). When ``create`` fails the key is released. Creating
    and recording run shielded from cancellation, so a client that hangs up cannot leave a
    job without its record.
    """
    try:
        found = await claim(keys, owner, key, upload)
    except BaseException:
        if upload.path is not None:
            upload.path.unlink(missing_ok=True)
        raise
    if isinstance(found, str):
        if upload.path is not None:
            upload.path.unlink(missing_ok=True)
        return found, False
    with anyio.CancelScope(shield=True):
        try:
            job_id = await run_in_threadpool(create)
        except BaseException:
            await run_in_threadpool(found.release)
            raise
        await run_in_threadpool(found.complete, job_id)
    return job_id, True
