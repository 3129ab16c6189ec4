"""From a streamed upload to an enqueued job: validate everything first, then enqueue.

The checks run before anything is queued, so a bad asset is answered 4xx at once rather than
failing later on a worker: options (422), file kind by magic bytes (415), zip safety and
size (400/413), that the asset parses and every resource resolves (400), triangle and texture
limits (413), and that there is something to upscale (422). The input is unpacked and
checked in a temporary folder of this machine, then stored as the job's objects
(:class:`~pbrsr_jobs.store.JobFiles`). Stored names are generated (``input/asset.glb``; a
zip's ``.gltf`` is renamed ``asset.gltf`` beside its resources).
"""

from __future__ import annotations

import contextlib
import gc
import json
import os
import shutil
import threading
import time
from pathlib import Path
from typing import Any

from pbrsr_core.errors import InvalidAsset, InvalidOptions, UnprocessableAsset
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

from .problems import ProblemError
from .uploads import Upload

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
    from pbrsr_core.maps import upscalable_images

    limits = settings.limits()
    with _VALIDATION_SLOTS:
        asset = load_asset(path, limits, unwrap_missing_uvs=options["unwrap_missing_uvs"])
        try:
            images = upscalable_images(asset)
            if not images:
                raise UnprocessableAsset(
                    "nothing to upscale: no material of this asset uses a texture"
                )
            scale = int(options["scale"])
            check_output_size(images, scale, limits)
            return sum(img.width * img.height for img in images) * scale * scale / 1e6
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


def check_capacity(owner: str, settings: Settings, index: JobIndex, queue: Any) -> None:
    """Refuse a submission while the queues are full (503) or the key has as many queued and
    running jobs as it may (429), both with Retry-After; before any work on the asset."""
    if not (settings.max_queued_jobs or settings.max_active_jobs_per_key):
        return
    queues = [type(queue)(q, connection=queue.connection) for q in settings.listen_queues("all")]
    waiting, per_owner = index.active_jobs(queues)
    retry = {"Retry-After": str(RETRY_AFTER_S)}
    if settings.max_queued_jobs and waiting >= settings.max_queued_jobs:
        raise ProblemError(
            503, "queue-full", f"the queue is full ({waiting} jobs waiting); retry later",
            headers=retry,
        )  # fmt: skip
    mine = per_owner.get(owner, 0)
    if settings.max_active_jobs_per_key and mine >= settings.max_active_jobs_per_key:
        raise ProblemError(
            429, "too-many-jobs",
            f"this API key has {mine} jobs queued or running, the most it may have; retry "
            "when one has ended", headers=retry,
        )  # fmt: skip


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
    from rq import Retry

    job_id = new_job_id()
    try:
        if upload.path is None:
            raise ProblemError(400, "bad-request", "the request has no 'file' part")
        if upload.size == 0:
            raise InvalidAsset("the uploaded file is empty")
        options = parse_options(upload.fields.get("options"), settings)
        webhook = parse_webhook(
            upload.fields.get("callback_url"), upload.fields.get("callback_events")
        )
        priority = (upload.fields.get("priority") or "normal").strip()
        if priority not in PRIORITIES:
            raise InvalidOptions(f"priority must be one of {', '.join(PRIORITIES)}")
        check_capacity(owner, settings, index, queue)
        from pbrsr_core.asset import detect_kind

        kind = detect_kind(upload.path)
        staging = layout.tmp_dir(job_id, "input")
        rel = _place_input(upload.path, kind, staging, settings)
        output_mpix = check_asset(staging / rel, options, settings)
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
                options=options,
                created_at=created,
            )
        )
        meta = {
            "owner": owner,
            "name": name,
            "kind": kind,
            "created_at": created,
            "options": options,
            "state": JobState.QUEUED.value,
            "priority": priority,
        }
        if webhook is not None:
            meta["webhook"] = webhook
        index.add(job_id, owner, created)
        events = JobEvents(index.redis, index.prefix)
        events.publish(job_id, owner, "queued", webhook=webhook)  # before a worker's "started"
        target = settings.queue_for(output_mpix, priority)
        if target != queue.name:
            queue = type(queue)(target, connection=queue.connection)
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
                description=f"pbrsr upscale {name}",
            )
        except Exception:
            index.remove(job_id)
            events.forget(job_id)
            raise
    except BaseException:
        if upload.path is not None:
            upload.path.unlink(missing_ok=True)
        layout.remove(job_id)
        with contextlib.suppress(StoreUnavailable):  # unreachable: nothing was stored
            files.remove(job_id)
        raise
    shutil.rmtree(staging, ignore_errors=True)
    layout.release(job_id)  # the filesystem backend's objects stay
    return job_id
