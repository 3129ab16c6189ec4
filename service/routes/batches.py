"""``/v1/batches``: submit several assets as one batch of jobs, inspect it, cancel it."""

from __future__ import annotations

from functools import partial
from typing import Any

from fastapi import APIRouter, Request, Response
from fastapi.concurrency import run_in_threadpool

from pbrsr_jobs.idempotency import IdempotencyKeys
from pbrsr_jobs.store import JobState

from ..deletion import delete_job
from ..deps import FilesDep, IndexDep, LayoutDep, OwnerDep, QueueDep, RedisDep, SettingsDep
from ..idempotency import IdempotencyKeyHeader, check_key, create_once
from ..intake import create_batch
from ..job_views import batch_links, batch_view, links, state_of
from ..problems import PROBLEM_RESPONSES, Problem
from ..schemas import BatchCreated, BatchDetail, JobCreated
from ..uploads import receive_uploads
from .jobs import UPLOAD_BODY, cancel_active, fetch_batch, fetch_jobs

router = APIRouter(prefix="/v1/batches", tags=["batches"], responses=PROBLEM_RESPONSES)

_NOT_FOUND = {404: {"model": Problem, "description": "No such batch (or not yours)."}}

_FORM = UPLOAD_BODY["requestBody"]["content"]["multipart/form-data"]["schema"]
_FILES = {
    "type": "array",
    "items": {"type": "string", "format": "binary"},
    "description": "One 'file' part per asset (up to PBRSR_MAX_BATCH_FILES), each a .glb, a "
    "self-contained .gltf, or a .zip holding one .gltf with its buffers and images.",
}
_BATCH_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {**_FORM, "properties": {**_FORM["properties"], "file": _FILES}}
            }
        },
    }
}


@router.post(
    "",
    status_code=202,
    response_model=BatchCreated,
    openapi_extra=_BATCH_BODY,
    responses={
        200: {"model": BatchCreated, "description": "A retry: the Idempotency-Key's batch."},
        400: {"model": Problem, "description": "A file is not a readable asset (named)."},
        409: {"model": Problem, "description": "The Idempotency-Key's first request is running."},
        413: {
            "model": Problem,
            "description": "Too many files, or a file over a size, triangle or texture limit.",
        },
        415: {"model": Problem, "description": "A file is not glTF/GLB/zip, or not multipart."},
        422: {
            "model": Problem,
            "description": "Bad options, a file with nothing to upscale, or an Idempotency-Key "
            "reused with other files or options.",
        },
        429: {"model": Problem, "description": "The batch would take the key over its limit."},
    },
    summary="Submit several assets as one batch",
)
async def submit_batch(
    request: Request,
    response: Response,
    settings: SettingsDep,
    owner: OwnerDep,
    layout: LayoutDep,
    files: FilesDep,
    index: IndexDep,
    queue: QueueDep,
    idempotency_key: IdempotencyKeyHeader = None,
) -> BatchCreated:
    """One job per ``file`` part, all with the same ``options``, ``priority`` and webhook.
    All or nothing: every file is checked before any job is queued; one bad file refuses
    the batch with a problem naming it (its number and name), and a batch that would pass
    the key's or the queues' limit is refused whole (429/503, Retry-After). Answers 202 with
    the batch id and its jobs (200 with the first batch for a retry under the same
    ``Idempotency-Key``)."""
    key = check_key(idempotency_key)
    max_bytes = settings.limits().max_file_bytes
    uploads, fields = await receive_uploads(
        request, layout.new_upload_path, max_bytes, settings.max_batch_files, digest=key is not None
    )
    create = partial(create_batch, uploads, fields, owner, settings, layout, files, index, queue)
    if key is None:
        batch_id, job_ids = await run_in_threadpool(create)
    else:
        keys = IdempotencyKeys(
            index.redis, settings.key_prefix, settings.idempotency_ttl_s, namespace="idem-batch"
        )
        batch_id, created = await create_once(
            keys, owner, key, uploads, fields, lambda: create()[0]
        )
        job_ids = (await run_in_threadpool(fetch_batch, batch_id, owner, index))[1]
        if not created:
            response.status_code = 200
    response.headers["Location"] = f"/v1/batches/{batch_id}"
    jobs = [
        JobCreated(id=j, status=JobState.QUEUED, links=links(j, JobState.QUEUED)) for j in job_ids
    ]
    return BatchCreated(id=batch_id, jobs=jobs, links=batch_links(batch_id))


@router.get("/{batch_id}", response_model=BatchDetail, responses=_NOT_FOUND, summary="Batch status")
def get_batch(
    batch_id: str, redis: RedisDep, owner: OwnerDep, files: FilesDep, index: IndexDep
) -> Response:
    """Every job's summary, the jobs per state, the overall state and progress."""
    created, job_ids = fetch_batch(batch_id, owner, index)
    view = batch_view(batch_id, created, fetch_jobs(job_ids, redis), index, files)
    return Response(view.model_dump_json(), media_type="application/json")


@router.delete(
    "/{batch_id}",
    response_model=BatchDetail,
    status_code=202,
    responses={
        **_NOT_FOUND,
        204: {"description": "Every job had ended: the batch, its jobs and files were deleted."},
    },
    summary="Cancel a batch (or delete an ended one)",
)
def cancel_batch(
    batch_id: str,
    redis: RedisDep,
    settings: SettingsDep,
    owner: OwnerDep,
    layout: LayoutDep,
    files: FilesDep,
    index: IndexDep,
) -> Any:
    """Cancels every job not yet ended as ``DELETE /v1/jobs/{id}`` does (queued ones at once,
    running ones within about 2 s) and answers the batch (202); ended jobs are kept. When
    every job has already ended, the batch and all its jobs and files are deleted (204)."""
    created, job_ids = fetch_batch(batch_id, owner, index)
    jobs = fetch_jobs(job_ids, redis)
    states = [state_of(job) for job in jobs]
    if all(state.is_terminal for state in states):
        for job_id in job_ids:  # those whose RQ job expired too
            delete_job(job_id, index, layout, files)
        return Response(status_code=204)
    for job, state in zip(jobs, states, strict=True):
        if not state.is_terminal:
            cancel_active(job, state, owner, settings, index)
    return batch_view(batch_id, created, jobs, index, files)
