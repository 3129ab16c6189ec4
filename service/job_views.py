"""Job views: an RQ job + its meta + the job's stored files -> the API's response models; a
batch's jobs -> its aggregate view."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any
from urllib.parse import quote

from pydantic import TypeAdapter, ValidationError

from pbrsr_jobs.store import JobFiles, JobIndex, JobState, job_state
from pbrsr_jobs.webhooks import WebhookQueue

from .schemas import (
    BatchDetail,
    BatchLinks,
    CropList,
    HistoryPoint,
    JobDetail,
    JobLinks,
    JobSummary,
    MapCrop,
)

DIED_MESSAGE = (
    "the worker running this job stopped unexpectedly (killed or out of memory) on every "
    "attempt; try a smaller asset, a lower scale or a faster preset"
)


def _dt(value: Any) -> datetime | None:
    if value is None:
        return None
    if isinstance(value, datetime):
        return value if value.tzinfo else value.replace(tzinfo=UTC)
    try:
        return datetime.fromtimestamp(float(value), tz=UTC)
    except (TypeError, ValueError, OverflowError):
        return None


def rq_status(job: Any) -> str | None:
    status = job.get_status(refresh=False)
    return None if status is None else str(getattr(status, "value", status))


def state_of(job: Any) -> JobState:
    return job_state(rq_status(job), job.meta or {})


def links(
    job_id: str, state: JobState, store: JobFiles | None = None, files: dict | None = None
) -> JobLinks:
    """The job's URLs; a finished job's previews, thumbnails and asset file by the names its
    worker recorded in ``files`` (``meta['files']``), else as the store lists them."""
    base = f"/v1/jobs/{job_id}"
    result = previews = thumbs = crops = model = None
    if state == JobState.FINISHED and (store is not None or files):
        result, crops = f"{base}/result", f"{base}/crops"
        if files:
            preview_list, thumb_list = files.get("previews", []), files.get("thumbs", [])
            model_name = files.get("model")
        else:
            assert store is not None
            preview_list, thumb_list = store.preview_names(job_id), store.thumb_names(job_id)
            model_name = store.model_name(job_id)
        previews = {n: f"{base}/previews/{n}" for n in preview_list}
        thumbs = {n: f"{base}/thumbs/{n}" for n in thumb_list}
        model = f"{base}/files/{quote(model_name)}" if isinstance(model_name, str) else None
    return JobLinks(
        self=base,
        cancel=base,
        result=result,
        previews=previews or {},
        thumbs=thumbs or {},
        crops=crops,
        model=model,
    )


def crop_list(job_id: str, files: dict | None) -> CropList:
    """A finished job's detail crops as its worker recorded them in ``files``, with URLs;
    malformed entries left out."""
    base = f"/v1/jobs/{job_id}/crops"
    items = []
    for entry in (files or {}).get("crops") or []:
        try:
            crop = MapCrop.model_validate(entry)
        except ValidationError:
            continue
        crop.lr, crop.hr = f"{base}/{quote(crop.lr)}", f"{base}/{quote(crop.hr)}"
        items.append(crop)
    return CropList(items=items)


def crop_names(files: dict | None) -> list[str]:
    """The crop files a finished job's worker recorded in ``files``."""
    names = []
    for entry in (files or {}).get("crops") or []:
        if isinstance(entry, dict):
            names += [n for n in (entry.get("lr"), entry.get("hr")) if isinstance(n, str)]
    return names


def _common(
    job: Any, index: JobIndex, store: JobFiles | None, cancel: bool | None
) -> dict[str, Any]:
    """``cancel``: whether a cancel was requested, when the caller read it already."""
    meta = job.meta or {}
    state = state_of(job)
    error = meta.get("error")
    if state == JobState.FAILED and not error:
        error = DIED_MESSAGE
    return {
        "id": job.id,
        "status": state,
        "name": meta.get("name", "asset"),
        "created_at": _dt(meta.get("created_at")) or _dt(job.created_at),
        "started_at": _dt(meta.get("started_at")),
        "ended_at": _dt(meta.get("ended_at")),
        "stage": meta.get("stage"),
        "fraction": float(min(max(meta.get("fraction", 0.0) or 0.0, 0.0), 1.0)),
        "eta_s": meta.get("eta_s") if state == JobState.RUNNING else None,
        "error": error if state == JobState.FAILED else None,
        "cancel_requested": (not state.is_terminal)
        and (index.cancel_requested(job.id) if cancel is None else cancel),
        "batch": meta.get("batch"),
        "links": links(job.id, state, store, meta.get("files")),
    }


def summary_view(
    job: Any, index: JobIndex, store: JobFiles | None = None, cancel: bool | None = None
) -> JobSummary:
    return JobSummary(**_common(job, index, store, cancel))


def _history(points: Any) -> list[HistoryPoint]:
    """The worker's history points, validated in one pass; malformed ones left out."""
    try:
        return _HISTORY.validate_python(points or [])
    except ValidationError:
        out = []
        for point in points if isinstance(points, list) else []:
            try:
                out.append(HistoryPoint.model_validate(point))
            except ValidationError:
                continue
        return out


_HISTORY = TypeAdapter(list[HistoryPoint])


def detail_view(
    job: Any,
    index: JobIndex,
    store: JobFiles,
    cancel: bool | None = None,
    deliveries: list[dict] | None = None,
) -> JobDetail:
    """``deliveries``: the webhook delivery log, when the caller read it already."""
    meta = job.meta or {}
    data = _common(job, index, store, cancel)
    history = _history(meta.get("history"))
    return JobDetail(
        **data,
        step=int(meta.get("step", 0) or 0),
        total=int(meta.get("total", 0) or 0),
        code=meta.get("code") if data["status"] == JobState.FAILED else None,
        attempt=int(meta.get("attempt", 0) or 0),
        options=meta.get("options") or {},
        losses=meta.get("losses") or {},
        metrics=meta.get("metrics") or {},
        timings=meta.get("timings") or {},
        history=history,
        summary=meta.get("summary") or {},
        webhook=meta.get("webhook"),
        deliveries=deliveries if deliveries is not None else _deliveries(job, index),
    )


def _deliveries(job: Any, index: JobIndex) -> list[dict]:
    if not (job.meta or {}).get("webhook"):
        return []
    return WebhookQueue(index.redis, index.prefix).deliveries(job.id)


def batch_links(batch_id: str) -> BatchLinks:
    base = f"/v1/batches/{batch_id}"
    return BatchLinks(self=base, cancel=base, jobs=f"/v1/jobs?batch={batch_id}")


def batch_status(states: list[JobState]) -> JobState:
    """A batch's state from its jobs' (see ``BatchDetail.status``)."""
    if not all(s.is_terminal for s in states):
        started = any(s != JobState.QUEUED for s in states)
        return JobState.RUNNING if started else JobState.QUEUED
    if all(s == JobState.FINISHED for s in states):
        return JobState.FINISHED
    return JobState.FAILED if JobState.FAILED in states else JobState.CANCELED


def batch_view(
    batch_id: str, created_at: float, jobs: list[Any], index: JobIndex, store: JobFiles
) -> BatchDetail:
    """``jobs``: the batch's RQ jobs in order. Cancel flags are read in one round trip."""
    cancels = index.cancel_flags([j.id for j in jobs if not state_of(j).is_terminal])
    items = [summary_view(j, index, store, j.id in cancels) for j in jobs]
    states = [item.status for item in items]
    counts = {state: states.count(state) for state in JobState}
    done = [1.0 if item.status.is_terminal else item.fraction for item in items]
    return BatchDetail(
        id=batch_id,
        status=batch_status(states),
        created_at=_dt(created_at) or datetime.now(UTC),
        total=len(items),
        counts=counts,
        fraction=sum(done) / len(done) if done else 1.0,
        jobs=items,
        links=batch_links(batch_id),
    )
