"""Job views: an RQ job + its meta + the files on disk -> the API's response models."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

from pbrsr_jobs.store import JobIndex, JobLayout, JobState, job_state

from .schemas import HistoryPoint, JobDetail, JobLinks, JobSummary

PREVIEW_MAIN = "preview.png"
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


def preview_names(layout: JobLayout, job_id: str) -> list[str]:
    out = layout.output_dir(job_id)
    names = [PREVIEW_MAIN] if (out / PREVIEW_MAIN).is_file() else []
    return names + layout.list_files(out / "previews", (".png",))


def thumb_names(layout: JobLayout, job_id: str) -> list[str]:
    return layout.list_files(layout.thumbs_dir(job_id), (".png",))


def links(job_id: str, state: JobState, layout: JobLayout | None = None) -> JobLinks:
    base = f"/v1/jobs/{job_id}"
    result = previews = thumbs = None
    if state == JobState.FINISHED and layout is not None:
        result = f"{base}/result"
        previews = {n: f"{base}/previews/{n}" for n in preview_names(layout, job_id)}
        thumbs = {n: f"{base}/thumbs/{n}" for n in thumb_names(layout, job_id)}
    return JobLinks(
        self=base, cancel=base, result=result, previews=previews or {}, thumbs=thumbs or {}
    )


def _common(job: Any, index: JobIndex, layout: JobLayout | None) -> dict[str, Any]:
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
        "cancel_requested": (not state.is_terminal) and index.cancel_requested(job.id),
        "links": links(job.id, state, layout),
    }


def summary_view(job: Any, index: JobIndex, layout: JobLayout | None = None) -> JobSummary:
    return JobSummary(**_common(job, index, layout))


def detail_view(job: Any, index: JobIndex, layout: JobLayout) -> JobDetail:
    meta = job.meta or {}
    data = _common(job, index, layout)
    history = []
    for point in meta.get("history") or []:
        try:
            history.append(HistoryPoint(**point))
        except (TypeError, ValueError):
            continue
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
    )
