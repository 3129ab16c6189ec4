"""From streamed uploads to enqueued jobs: validate everything first, then enqueue.

The checks run before anything is queued, so a bad asset is answered 4xx at once rather than
failing later on a worker: options (422), file kind by magic bytes (415), zip safety and
size (400/413), that the asset parses and every resource resolves (400), triangle and texture
limits (413), and that there is something to upscale (422). The input is unpacked and
checked in a temporary folder of this machine, then stored as the job's objects
(:class:`~pbrsr_jobs.store.JobFiles`). Stored names are generated (``input/asset.glb``; a
zip's ``.gltf`` is renamed ``asset.gltf`` beside its resources).

A batch (:func:`create_batch`) is all or nothing: every file is checked as a single job's
would be, and only when all pass are its jobs queued; the first bad file refuses the batch
with a problem naming it (``file 2 (chair.glb): ...``) and nothing is kept.
"""

from __future__ import annotations

import contextlib
import gc
import json
import os
import shutil
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pbrsr_core.errors import InvalidAsset, InvalidOptions, PbrsrError, UnprocessableAsset
from pbrsr_core.options import UpscaleOptions
from pbrsr_jobs.events import JobEvents
from pbrsr_jobs.objstore import StoreUnavailable
from pbrsr_jobs.settings import PRIORITIES, Settings
from pbrsr_jobs.store import (
    JobFiles,
    JobIndex,
    JobLayout,
    JobManifest,
    JobState,
    new_job_id,
    resolve_options,
    safe_display_name,
)
from pbrsr_jobs.webhooks import parse_webhook

from .deletion import take_back
from .problems import ProblemError
from .uploads import Upload, discard_uploads, file_label

JOB_FUNC = "worker.tasks.run_job"

# Loading an asset decodes every texture; bound how many uploads are checked at once so a burst
# of large uploads cannot take the API's memory.
_VALIDATION_SLOTS = threading.BoundedSemaphore(2)


def parse_options(text: str | None, settings: Settings) -> dict[str, Any]:
    """The ``options`` form field (JSON object) -> normalised options dict (device left out)."""
    if text is None or not text.strip():
        raw: Any = {}
    else:
        try:
            raw = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InvalidOptions(f"options is not valid JSON ({exc.msg})") from None
    resolve_options(raw, settings)  # raises InvalidOptions naming the field
    data = {k: v for k, v in raw.items() if k != "device"}
    return UpscaleOptions(**data).model_dump(exclude={"device"})


def check_asset(path: Path, options: dict[str, Any], settings: Settings) -> float:
    """Load the asset the way the worker will and check it can be processed. Returns the
    megapixels of all output maps (the job's size, for queue routing)."""
    from pbrsr_core.asset import load_asset
    from pbrsr_core.limits import check_output_size
    from pbrsr_core.maps import map_scales, upscalable_images

    limits = settings.limits()
    with _VALIDATION_SLOTS:
        asset = load_asset(path, limits, unwrap_missing_uvs=options["unwrap_missing_uvs"])
        try:
            images = upscalable_images(asset)
            if not images:
                raise UnprocessableAsset(
                    "nothing to upscale: no material of this asset uses a texture"
                )
            factors = map_scales(
                images,
                int(options["scale"]),
                options["max_size"],
                options["maps"],
                options["other_maps"],
            )
            check_output_size(images, factors, limits)
            return sum(img.width * img.height * factors[img.index] ** 2 for img in images) / 1e6
        finally:
            del asset
            gc.collect()


def _place_input(upload_path: Path, kind: str, input_dir: Path, settings: Settings) -> str:
    """Move/unpack the upload into ``input_dir``; return the asset's path relative to it."""
    input_dir.mkdir(parents=True, exist_ok=True)
    if kind in ("glb", "gltf"):
        target = input_dir / f"asset.{kind}"
        os.replace(upload_path, target)
        return target.name
    from pbrsr_core.asset import extract_zip

    inner = Path(extract_zip(upload_path, input_dir, settings.limits()))
    upload_path.unlink(missing_ok=True)
    renamed = inner.with_name("asset" + inner.suffix.lower())
    if renamed != inner:
        if renamed.exists():
            raise InvalidAsset(
                f"the zip holds both '{inner.name}' and a file named '{renamed.name}'"
            )
        os.replace(inner, renamed)
    return renamed.relative_to(input_dir).as_posix()


RETRY_AFTER_S = 30


def check_capacity(
    owner: str, settings: Settings, index: JobIndex, queue: Any, count: int = 1
) -> None:
    """Refuse a submission of ``count`` jobs while they do not fit: the queues would be over
    their limit (503) or the key over its queued and running jobs (429), both with
    Retry-After; a batch larger than a limit itself is 413. Runs before any work on the
    assets."""
    limit_q, limit_key = settings.max_queued_jobs, settings.max_active_jobs_per_key
    if not (limit_q or limit_key):
        return
    for limit, what in ((limit_key, "this API key may have queued or running"),
                        (limit_q, "the queues may hold")):  # fmt: skip
        if limit and count > limit:
            raise ProblemError(
                413, "limit-exceeded",
                f"a batch of {count} jobs is more than {what} ({limit}); send smaller batches",
            )  # fmt: skip
    queues = [type(queue)(q, connection=queue.connection) for q in settings.listen_queues("all")]
    waiting, per_owner = index.active_jobs(queues)
    retry = {"Retry-After": str(RETRY_AFTER_S)}
    adds = f"; this batch adds {count}" if count > 1 else ""
    if limit_q and waiting + count > limit_q:
        raise ProblemError(
            503, "queue-full", f"the queue is full ({waiting} jobs waiting{adds}); retry later",
            headers=retry,
        )  # fmt: skip
    mine = per_owner.get(owner, 0)
    if limit_key and mine + count > limit_key:
        raise ProblemError(
            429, "too-many-jobs",
            f"this API key has {mine} jobs queued or running, of the {limit_key} it may have"
            f"{adds}; retry when one has ended", headers=retry,
        )  # fmt: skip


@dataclass(frozen=True)
class JobForm:
    """The checked form fields every job of one submission shares."""

    options: dict[str, Any]
    webhook: dict[str, Any] | None
    priority: str


def parse_form(fields: dict[str, str], settings: Settings) -> JobForm:
    """``options``, ``callback_url``/``callback_events`` and ``priority``, checked (422)."""
    options = parse_options(fields.get("options"), settings)
    webhook = parse_webhook(fields.get("callback_url"), fields.get("callback_events"))
    priority = (fields.get("priority") or "normal").strip()
    if priority not in PRIORITIES:
        raise InvalidOptions(f"priority must be one of {', '.join(PRIORITIES)}")
    return JobForm(options, webhook, priority)


@dataclass(frozen=True)
class StagedJob:
    """A checked asset stored as a job (input and manifest objects), not yet queued."""

    id: str
    owner: str
    meta: dict[str, Any]
    queue: str


def stage_job(
    upload: Upload,
    form: JobForm,
    owner: str,
    settings: Settings,
    layout: JobLayout,
    files: JobFiles,
    batch_id: str | None = None,
) -> StagedJob:
    """Check ``upload`` (a file part came) in a staging folder of this machine and store it
    as a new job's input and manifest objects (the upload and the staging folder are
    removed). On any error the upload, the job's working folder and objects are removed; a
    store that cannot be reached is StoreUnavailable (503)."""
    assert upload.path is not None
    job_id = new_job_id()
    try:
        if upload.size == 0:
            raise InvalidAsset("the uploaded file is empty")
        from pbrsr_core.asset import detect_kind

        kind = detect_kind(upload.path)
        staging = layout.tmp_dir(job_id, "input")
        rel = _place_input(upload.path, kind, staging, settings)
        output_mpix = check_asset(staging / rel, form.options, settings)
        name = safe_display_name(upload.filename, fallback=f"asset.{kind}")
        created = time.time()
        files.put_input(job_id, staging)
        files.write_manifest(
            JobManifest(
                id=job_id,
                owner=owner,
                name=name,
                kind=kind,
                input=rel,
                options=form.options,
                created_at=created,
            )
        )
    except BaseException:
        discard_uploads([upload])
        layout.remove(job_id)
        with contextlib.suppress(StoreUnavailable):  # unreachable: nothing more to remove
            files.remove(job_id)
        raise
    shutil.rmtree(staging, ignore_errors=True)
    layout.release(job_id)  # the filesystem backend's objects stay
    meta = {
        "owner": owner,
        "name": name,
        "kind": kind,
        "created_at": created,
        "options": form.options,
        "state": JobState.QUEUED.value,
        "priority": form.priority,
    }
    if form.webhook is not None:
        meta["webhook"] = form.webhook
    if batch_id is not None:
        meta["batch"] = batch_id
    return StagedJob(job_id, owner, meta, settings.queue_for(output_mpix, form.priority))


def enqueue_staged(staged: StagedJob, settings: Settings, index: JobIndex, queue: Any) -> None:
    """Index a staged job, announce it (``queued``) and put it on its RQ queue. When the
    enqueue fails its index entries and events are removed (its objects are the caller's)."""
    from rq import Retry

    job_id, meta = staged.id, staged.meta
    index.add(job_id, staged.owner, meta["created_at"])
    events = JobEvents(index.redis, index.prefix)
    events.publish(job_id, staged.owner, "queued", webhook=meta.get("webhook"))  # before "started"
    if staged.queue != queue.name:
        queue = type(queue)(staged.queue, connection=queue.connection)
    try:
        queue.enqueue(
            JOB_FUNC,
            job_id,
            job_id=job_id,
            meta=meta,
            job_timeout=settings.job_timeout,
            result_ttl=settings.retention_s,
            failure_ttl=settings.retention_s,
            retry=Retry(max=settings.job_retries) if settings.job_retries else None,
            description=f"pbrsr upscale {meta['name']}",
        )
    except Exception:
        index.remove(job_id)
        events.forget(job_id)
        raise


def create_job(
    upload: Upload,
    owner: str,
    settings: Settings,
    layout: JobLayout,
    files: JobFiles,
    index: JobIndex,
    queue: Any,
) -> str:
    """Validate ``upload``, store it as a new job and enqueue it. Returns the job id.

    On any error nothing is left behind (upload, job objects, working folder) and nothing is
    queued; a store that cannot be reached is StoreUnavailable (503).
    """
    try:
        if upload.path is None:
            raise ProblemError(400, "bad-request", "the request has no 'file' part")
        form = parse_form(upload.fields, settings)
        check_capacity(owner, settings, index, queue)
    except BaseException:
        discard_uploads([upload])
        raise
    staged = stage_job(upload, form, owner, settings, layout, files)
    try:
        enqueue_staged(staged, settings, index, queue)
    except BaseException:
        take_back(staged.id, index, layout, files)
        raise
    return staged.id


def create_batch(
    uploads: list[Upload],
    fields: dict[str, str],
    owner: str,
    settings: Settings,
    layout: JobLayout,
    files: JobFiles,
    index: JobIndex,
    queue: Any,
) -> tuple[str, list[str]]:
    """Validate every upload, then store and enqueue one job each as one batch. Returns the
    batch id and the job ids in the order of the files.

    All or nothing: a bad form field is refused as for one job, a bad file with a problem
    that names it (number and name), a batch that does not fit the limits with 429/503/413;
    on any error nothing is left behind and nothing stays queued; a store that cannot be
    reached is StoreUnavailable (503).
    """
    staged: list[StagedJob] = []
    try:
        if not uploads:
            raise ProblemError(400, "bad-request", "the request has no 'file' part")
        form = parse_form(fields, settings)
        check_capacity(owner, settings, index, queue, len(uploads))
        batch_id = new_job_id()
        for number, upload in enumerate(uploads, 1):
            try:
                staged.append(stage_job(upload, form, owner, settings, layout, files, batch_id))
            except PbrsrError as exc:
                label = file_label(number, upload.filename)
                raise ProblemError(exc.http_status, exc.code, f"{label}: {exc.message}") from None
            except ProblemError as exc:
                label = file_label(number, upload.filename)
                raise ProblemError(
                    exc.status, exc.code, f"{label}: {exc.detail}", headers=exc.headers
                ) from None
        job_ids = [job.id for job in staged]
        index.add_batch(batch_id, owner, time.time(), job_ids)
        for job in staged:
            enqueue_staged(job, settings, index, queue)
    except BaseException:
        discard_uploads(uploads)
        for job in staged:
            take_back(job.id, index, layout, files)  # queued or not
        raise
    return batch_id, job_ids
