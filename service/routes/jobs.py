"""``/v1/jobs``: submit, inspect, list, cancel, download."""

from __future__ import annotations

import contextlib
from functools import partial
from typing import Annotated, Any

from fastapi import APIRouter, BackgroundTasks, Depends, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse, RedirectResponse
from pydantic import BaseModel
from rq.exceptions import InvalidJobOperation, NoSuchJobError
from rq.job import Job

from pbrsr_jobs.events import JobEvents
from pbrsr_jobs.idempotency import IdempotencyKeys
from pbrsr_jobs.settings import Settings
from pbrsr_jobs.store import JobIndex, JobState, check_job_id, sweep_expired
from pbrsr_jobs.webhooks import LOG_ENTRIES, WebhookQueue

from ..deletion import delete_job
from ..deps import (
    AsyncRedisDep,
    FilesDep,
    IndexDep,
    LayoutDep,
    OwnerDep,
    QueueDep,
    RedisDep,
    SettingsDep,
)
from ..idempotency import IdempotencyKeyHeader, check_key, create_once
from ..intake import create_job
from ..job_views import crop_list, crop_names, detail_view, links, state_of, summary_view
from ..problems import PROBLEM_RESPONSES, Problem, ProblemError
from ..schemas import CropList, DownloadLink, JobCreated, JobDetail, JobPage
from ..uploads import receive_upload

router = APIRouter(prefix="/v1/jobs", tags=["jobs"], responses=PROBLEM_RESPONSES)

_NOT_FOUND = {404: {"model": Problem, "description": "No such job (or not yours)."}}

UPLOAD_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["file"],
                    "properties": {
                        "file": {
                            "type": "string",
                            "format": "binary",
                            "description": "A .glb, a self-contained .gltf, or a .zip holding "
                            "one .gltf with its buffers and images.",
                        },
                        "options": {
                            "type": "string",
                            "description": 'JSON object of UpscaleOptions, e.g. {"scale": 4, '
                            '"preset": "fast", "seed": 0, "image_format": "png"}.',
                        },
                    },
                }
            }
        },
    }
}


def fetch_job(job_id: str, owner: str, redis: Any, index: JobIndex) -> Job:
    """The caller's job, or 404 (also for someone else's job: its existence is not revealed)."""
    if not check_job_id(job_id) or index.owner(job_id) != owner:
        raise ProblemError(404, "not-found", "no such job")
    try:
        return Job.fetch(job_id, connection=redis)
    except NoSuchJobError:
        raise ProblemError(404, "not-found", "no such job (it may have expired)") from None


@router.post(
    "",
    status_code=202,
    response_model=JobCreated,
    openapi_extra=UPLOAD_BODY,
    responses={
        200: {"model": JobCreated, "description": "A retry: the Idempotency-Key's first job."},
        400: {"model": Problem, "description": "Not a readable asset, or a bad Idempotency-Key."},
        409: {"model": Problem, "description": "The Idempotency-Key's first request is running."},
        413: {"model": Problem, "description": "Over a size, triangle or texture limit."},
        415: {"model": Problem, "description": "Not a glTF/GLB/zip, or not multipart."},
        422: {
            "model": Problem,
            "description": "Bad options, nothing to upscale, or an Idempotency-Key reused "
            "with another file or options.",
        },
    },
    summary="Submit an asset to upscale",
)
async def submit_job(
    request: Request,
    response: Response,
    settings: SettingsDep,
    owner: OwnerDep,
    layout: LayoutDep,
    files: FilesDep,
    index: IndexDep,
    queue: QueueDep,
    idempotency_key: IdempotencyKeyHeader = None,
) -> JobCreated:
    """Stream the upload to storage, check it, and queue it. Answers 202 with the job's id
    (200 with the first job's id for a retry under the same ``Idempotency-Key``)."""
    key = check_key(idempotency_key)
    limits = settings.limits()
    dest = layout.new_upload_path()
    upload = await receive_upload(request, dest, limits.max_file_bytes, digest=key is not None)
    create = partial(create_job, upload, owner, settings, layout, files, index, queue)
    if key is None:
        job_id = await run_in_threadpool(create)
    else:
        keys = IdempotencyKeys(index.redis, settings.key_prefix, settings.idempotency_ttl_s)
        job_id, created = await create_once(keys, owner, key, [upload], upload.fields, create)
        if not created:
            response.status_code = 200
    response.headers["Location"] = f"/v1/jobs/{job_id}"
    return JobCreated(id=job_id, status=JobState.QUEUED, links=links(job_id, JobState.QUEUED))


@router.get("", response_model=JobPage, summary="List your jobs")
def list_jobs(
    redis: RedisDep,
    settings: SettingsDep,
    owner: OwnerDep,
    layout: LayoutDep,
    files: FilesDep,
    index: IndexDep,
    background: BackgroundTasks,
    status: Annotated[JobState | None, Query(description="Only jobs in this state.")] = None,
    batch: Annotated[
        str | None, Query(description="Only the jobs of this batch, in the order of its files.")
    ] = None,
    offset: Annotated[int, Query(ge=0)] = 0,
    limit: Annotated[int, Query(ge=1, le=1000)] = 20,
) -> Response:
    """Newest first (a batch's jobs: in the order of its files); ``offset``/``limit``
    pagination; optional ``status`` and ``batch`` filters (an unknown batch, or another
    key's, is 404)."""
    limit = min(limit, settings.page_size_max)
    if index.try_sweep_lock(settings.maintenance_s):
        background.add_task(sweep_expired, redis, index, layout, files, settings.retention_s)
    if status is None and batch is None:
        ids, total = index.page(owner, offset, limit)
        jobs = [j for j in Job.fetch_many(ids, connection=redis) if j is not None]
    else:
        if batch is None:
            all_ids, _ = index.page(owner, 0, 1_000_000)
        else:
            all_ids = fetch_batch(batch, owner, index)[1]
        matching = [
            j for j in fetch_jobs(all_ids, redis) if status is None or state_of(j) == status
        ]
        total = len(matching)
        jobs = matching[offset : offset + limit]
    cancels = index.cancel_flags([j.id for j in jobs if not state_of(j).is_terminal])
    items = [summary_view(j, index, files, j.id in cancels) for j in jobs]
    nxt = None
    if offset + limit < total:
        nxt = f"/v1/jobs?offset={offset + limit}&limit={limit}"
        if status is not None:
            nxt += f"&status={status.value}"
        if batch is not None:
            nxt += f"&batch={batch}"
    return _json(JobPage(items=items, total=total, offset=offset, limit=limit, next=nxt))


def fetch_jobs(job_ids: list[str], redis: Any) -> list[Job]:
    """The RQ jobs of ``job_ids`` that still exist, in order, read 500 at a time."""
    jobs: list[Job] = []
    for start in range(0, len(job_ids), 500):
        chunk = Job.fetch_many(job_ids[start : start + 500], connection=redis)
        jobs.extend(j for j in chunk if j is not None)
    return jobs


def fetch_batch(batch_id: str, owner: str, index: JobIndex) -> tuple[float, list[str]]:
    """The caller's batch (creation time, job ids), or 404 (also for someone else's)."""
    found = index.batch(batch_id) if check_job_id(batch_id) else None
    if found is None or found[0] != owner:
        raise ProblemError(404, "not-found", "no such batch")
    return found[1], found[2]


@router.get("/{job_id}", response_model=JobDetail, responses=_NOT_FOUND, summary="Job status")
async def get_job(
    job_id: str,
    aredis: AsyncRedisDep,
    redis: RedisDep,
    owner: OwnerDep,
    files: FilesDep,
    index: IndexDep,
) -> Response:
    """Status, stage, progress, ETA, latest losses/metrics, timings, history, error, links.

    One Redis round trip on the event loop (owner, the RQ job's hash and its cancel flag in
    one pipeline); no file is read for it."""
    if not check_job_id(job_id):
        raise ProblemError(404, "not-found", "no such job")
    hooks = WebhookQueue(None, index.prefix)
    async with aredis.pipeline(transaction=False) as pipe:
        pipe.hget(index.owners_key(), job_id)
        pipe.hgetall(Job.key_for(job_id))
        pipe.exists(index.cancel_key(job_id))
        pipe.lrange(hooks.log_key(job_id), 0, LOG_ENTRIES - 1)
        job_owner, raw, cancel, log = await pipe.execute()
    if job_owner is None or job_owner.decode() != owner:
        raise ProblemError(404, "not-found", "no such job")
    if not raw:
        raise ProblemError(404, "not-found", "no such job (it may have expired)")
    job = Job(job_id, connection=redis)
    job.restore(raw)
    sent = WebhookQueue.decode_log(log)
    if job.meta.get("state") == JobState.FINISHED.value and "files" not in job.meta:
        # finished before its worker recorded its files: list them off the event loop
        detail = await run_in_threadpool(detail_view, job, index, files, bool(cancel), sent)
    else:
        detail = detail_view(job, index, files, bool(cancel), sent)
    return _json(detail)


def _json(model: BaseModel) -> Response:
    """A response model already built and valid, serialised once by pydantic (FastAPI's own
    path would validate and encode it again: 10 ms for a 400-point history)."""
    return Response(model.model_dump_json(), media_type="application/json")


@router.delete(
    "/{job_id}",
    response_model=JobDetail,
    status_code=202,
    responses={**_NOT_FOUND, 204: {"description": "A finished job and its files were deleted."}},
    summary="Cancel a job (or delete a finished one)",
)
def cancel_job(
    job_id: str,
    response: Response,
    redis: RedisDep,
    settings: SettingsDep,
    owner: OwnerDep,
    layout: LayoutDep,
    files: FilesDep,
    index: IndexDep,
) -> Any:
    """Queued: canceled at once. Running: the worker stops within about 2 s (poll the job).
    Finished, failed or canceled: the job and its files are deleted (204)."""
    job = fetch_job(job_id, owner, redis, index)
    state = state_of(job)
    if state.is_terminal:
        delete_job(job.id, index, layout, files)
        return Response(status_code=204)
    cancel_active(job, state, owner, settings, index)
    return detail_view(job, index, files)


def cancel_active(
    job: Job, state: JobState, owner: str, settings: Settings, index: JobIndex
) -> None:
    """Cancel a job not yet ended (``state``): flag it for its worker; a queued one is
    taken off its queue at once and announced ``cancelled``."""
    index.request_cancel(job.id, settings.job_timeout + 3600)
    if state == JobState.QUEUED:
        with contextlib.suppress(InvalidJobOperation):
            job.cancel()
        job.refresh()
        if state_of(job) == JobState.CANCELED:  # a worker did not take it first
            webhook = (job.meta or {}).get("webhook")
            JobEvents(index.redis, index.prefix).publish(job.id, owner, "cancelled", {}, webhook)


_DOWNLOAD = {
    307: {"description": "With the s3 storage backend: a presigned URL of the file."},
}
_PNG_DOWNLOAD = {**_NOT_FOUND, **_DOWNLOAD, 200: {"content": {"image/png": {}}}}
RedirectQuery = Annotated[
    bool,
    Query(
        description="false: with the s3 backend, answer the presigned URL as JSON "
        "(DownloadLink) instead of redirecting to it (a browser's fetch with X-API-Key, which "
        "must not follow the key to the bucket). The filesystem backend serves the file."
    ),
]


class JobDownload:
    """What a download route needs: the caller's job (``job``; 404 as :func:`fetch_job`) and
    :meth:`send`, the answer for one of its stored objects."""

    def __init__(
        self,
        job_id: str,
        redis: RedisDep,
        owner: OwnerDep,
        settings: SettingsDep,
        files: FilesDep,
        index: IndexDep,
        redirect: RedirectQuery = True,
    ) -> None:
        self.files = files
        self.link_expiry_s = None if redirect else settings.s3_presign_expiry_s
        self.job = fetch_job(job_id, owner, redis, index)

    def send(self, key: str, media_type: str, filename: str | None = None) -> Response:
        """The object ``key``: a 307 to a presigned URL when the store gives one (s3), or that
        URL as JSON with ``redirect=false``; else the file itself."""
        url = self.files.store.url(key, filename=filename, media_type=media_type)
        if url is not None and self.link_expiry_s is not None:
            return _json(DownloadLink(url=url, expires_in_s=self.link_expiry_s))
        if url is not None:
            return RedirectResponse(url, status_code=307)
        path = self.files.store.local_path(key)
        if path is None:
            raise ProblemError(404, "not-found", "this file is gone (the job may have expired)")
        return FileResponse(path, media_type=media_type, filename=filename)


DownloadDep = Annotated[JobDownload, Depends()]


@router.get(
    "/{job_id}/result",
    response_class=FileResponse,
    responses={
        **_NOT_FOUND,
        **_DOWNLOAD,
        200: {"content": {"application/zip": {}}, "description": "The bundle."},
        409: {"model": Problem, "description": "The job has not finished."},
    },
    summary="Download the bundle",
)
def get_result(job_id: str, download: DownloadDep) -> Response:
    """A zip: the upscaled asset in the input's form, every HR map, report.json, previews."""
    job, files = download.job, download.files
    state = state_of(job)
    key = files.bundle_key(job_id)
    if state != JobState.FINISHED or not files.store.exists(key):
        raise ProblemError(
            409, "not-finished", f"the job is {state.value}; the result exists once it finished"
        )
    name = (job.meta or {}).get("name", "asset").rsplit(".", 1)[0] or "asset"
    scale = ((job.meta or {}).get("options") or {}).get("scale", "")
    return download.send(key, "application/zip", f"{name}-pbrsr-x{scale}.zip")


def _named(name: str, names: list[str]) -> None:
    if name not in names:  # only names the store lists: never a path from the URL
        raise ProblemError(404, "not-found", f"no file '{name[:64]}' for this job")


@router.get(
    "/{job_id}/previews/{name}",
    response_class=FileResponse,
    responses=_PNG_DOWNLOAD,
    summary="A before/after render",
)
def get_preview(job_id: str, name: str, download: DownloadDep) -> Response:
    """``preview.png`` (side by side) or ``before_<env>.png`` / ``after_<env>.png``."""
    _named(name, download.files.preview_names(job_id))
    return download.send(download.files.preview_key(job_id, name), "image/png")


@router.get(
    "/{job_id}/thumbs/{name}",
    response_class=FileResponse,
    responses=_PNG_DOWNLOAD,
    summary="A thumbnail of one HR map",
)
def get_thumb(job_id: str, name: str, download: DownloadDep) -> Response:
    _named(name, download.files.thumb_names(job_id))
    return download.send(download.files.thumb_key(job_id, name), "image/png")


def _finished_files(job: Job) -> dict:
    """A job's ``meta['files']`` (recorded by its worker when it finished), or 409."""
    state = state_of(job)
    if state != JobState.FINISHED:
        raise ProblemError(
            409, "not-finished", f"the job is {state.value}; its files exist once it finished"
        )
    return (job.meta or {}).get("files") or {}


@router.get(
    "/{job_id}/crops",
    response_model=CropList,
    responses={**_NOT_FOUND, 409: {"model": Problem, "description": "Not finished."}},
    summary="Detail crops of every map, before and after",
)
def list_crops(job_id: str, redis: RedisDep, owner: OwnerDep, index: IndexDep) -> CropList:
    """Per map: the same region of the input map (LR) and of the result (HR), chosen where
    the LR map has the most local variance, with the PNGs' URLs."""
    job = fetch_job(job_id, owner, redis, index)
    return crop_list(job_id, _finished_files(job))


@router.get(
    "/{job_id}/crops/{name}",
    response_class=FileResponse,
    responses=_PNG_DOWNLOAD,
    summary="One LR or HR detail crop",
)
def get_crop(job_id: str, name: str, download: DownloadDep) -> Response:
    _named(name, crop_names((download.job.meta or {}).get("files")))
    return download.send(download.files.crop_key(job_id, name), "image/png")


_MEDIA_TYPES = {
    ".glb": "model/gltf-binary",
    ".gltf": "model/gltf+json",
    ".bin": "application/octet-stream",
    ".png": "image/png",
    ".jpg": "image/jpeg",
    ".jpeg": "image/jpeg",
    ".exr": "image/x-exr",
    ".json": "application/json",
}


@router.get(
    "/{job_id}/files/{path:path}",
    response_class=FileResponse,
    responses={
        **_NOT_FOUND,
        **_DOWNLOAD,
        409: {"model": Problem, "description": "Not finished."},
    },
    summary="One file of the finished bundle",
)
def get_file(job_id: str, path: str, download: DownloadDep) -> Response:
    """A file of the bundle by its path inside it (``links.model`` is the upscaled asset; a
    ``.gltf``'s relative URIs resolve to its buffers and images here)."""
    files = download.files
    _finished_files(download.job)
    if path not in files.output_files(job_id):  # only paths the store lists: never one to follow
        raise ProblemError(404, "not-found", f"no file '{path[:64]}' in this job's result")
    suffix = "." + path.rsplit(".", 1)[-1].lower() if "." in path else ""
    media = _MEDIA_TYPES.get(suffix, "application/octet-stream")
    return download.send(files.output_key(job_id, path), media)
