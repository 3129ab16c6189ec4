"""Request and response bodies of the REST API (pydantic v2)."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, ConfigDict, Field

from pbrsr_jobs.store import JobState


class JobLinks(BaseModel):
    """Where to go next. ``result`` is set once the job has finished."""

    model_config = ConfigDict(populate_by_name=True, serialize_by_alias=True)

    self_: str = Field(alias="self", description="This job.")
    cancel: str = Field(description="DELETE this to cancel (or delete a finished job).")
    result: str | None = Field(None, description="The bundle (a zip), once finished.")
    previews: dict[str, str] = Field(
        default_factory=dict, description="Before/after renders by name, once finished."
    )
    thumbs: dict[str, str] = Field(
        default_factory=dict, description="Thumbnails of the HR maps by name, once finished."
    )
    crops: str | None = Field(
        None, description="Per-map LR/HR detail crops (a CropList), once finished."
    )
    model: str | None = Field(
        None,
        description="The upscaled asset file (.glb, or .gltf whose relative URIs resolve "
        "beside it), once finished: for a 3D viewer.",
    )


class MapCrop(BaseModel):
    """One map's detail crop: the same region of the input map (LR) and of the result (HR)."""

    map: str = Field(description="The map's file stem in the bundle's maps/.")
    label: str = Field(description="The material slots using it: base_color, normal, orm...")
    scale: int
    lr_region: list[int] = Field(description="[x, y, width, height] in texels of the LR map.")
    hr_region: list[int] = Field(description="[x, y, width, height] in texels of the HR map.")
    lr_size: list[int] = Field(description="[width, height] of the LR map.")
    hr_size: list[int] = Field(description="[width, height] of the HR map.")
    lr: str = Field(description="URL of the LR crop, a PNG at LR texels (show it `scale` x).")
    hr: str = Field(description="URL of the HR crop, a PNG.")


class CropList(BaseModel):
    items: list[MapCrop]


class JobCreated(BaseModel):
    id: str
    status: JobState
    links: JobLinks


class HistoryPoint(BaseModel):
    t: float = Field(description="Seconds since the run started.")
    stage: str
    step: int
    losses: dict[str, float] = Field(default_factory=dict)
    metrics: dict[str, float] = Field(default_factory=dict)


class JobSummary(BaseModel):
    id: str
    status: JobState
    name: str = Field(description="The uploaded file's name (display only).")
    created_at: datetime
    started_at: datetime | None = None
    ended_at: datetime | None = None
    stage: str | None = Field(None, description="Current pipeline stage.")
    fraction: float = Field(0.0, ge=0, le=1, description="Overall progress, 0..1.")
    eta_s: float | None = Field(None, description="Seconds left, when known.")
    error: str | None = Field(None, description="Why the job failed (no internals).")
    cancel_requested: bool = False
    batch: str | None = Field(None, description="The id of the batch the job came in, if any.")
    links: JobLinks


class JobDetail(JobSummary):
    step: int = Field(0, description="Iteration (or item) done in the current stage.")
    total: int = Field(0, description="Iterations (or items) in the current stage; 0 = unknown.")
    code: str | None = Field(None, description="Slug of the error, when failed.")
    attempt: int = Field(0, description="Run attempt (above 1 after a worker died).")
    options: dict = Field(default_factory=dict, description="The options asked for.")
    losses: dict[str, float] = Field(default_factory=dict, description="Latest losses.")
    metrics: dict[str, float] = Field(
        default_factory=dict, description="Latest metrics, e.g. consistency PSNR to the LR input."
    )
    timings: dict[str, float] = Field(default_factory=dict, description="Seconds per stage.")
    history: list[HistoryPoint] = Field(
        default_factory=list, description="Losses and metrics over time (for plots)."
    )
    summary: dict = Field(default_factory=dict, description="Report summary, once finished.")
    webhook: dict | None = Field(None, description="callback_url and callback_events, if any.")
    deliveries: list[dict] = Field(
        default_factory=list,
        description="Webhook delivery attempts, oldest first: delivery, event, attempt, at, "
        "ms, status, ok, error, retry_in_s.",
    )


class JobPage(BaseModel):
    items: list[JobSummary]
    total: int = Field(description="Jobs matching the filter.")
    offset: int
    limit: int
    next: str | None = Field(None, description="The next page, if any.")


class DownloadLink(BaseModel):
    """A presigned URL of a job's file (``?redirect=false`` with the s3 storage backend)."""

    url: str = Field(description="GET it without credentials until it expires.")
    expires_in_s: int = Field(description="Seconds the URL stays valid.")


class BatchLinks(BaseModel):
    model_config = ConfigDict(populate_by_name=True, serialize_by_alias=True)

    self_: str = Field(alias="self", description="This batch.")
    cancel: str = Field(
        description="DELETE this to cancel the jobs not yet ended (or delete an ended batch)."
    )
    jobs: str = Field(description="The batch's jobs as a page of GET /v1/jobs.")


class BatchCreated(BaseModel):
    id: str
    jobs: list[JobCreated] = Field(description="One job per file, in the order of the files.")
    links: BatchLinks


class BatchDetail(BaseModel):
    id: str
    status: JobState = Field(
        description="queued: no job has started; running: some job has not ended and some "
        "has started or ended; once every job has ended: finished when all finished, else "
        "failed when one failed, else canceled."
    )
    created_at: datetime
    total: int = Field(description="Jobs of the batch (jobs deleted since not counted).")
    counts: dict[JobState, int] = Field(description="Jobs per state (every state listed).")
    fraction: float = Field(
        ge=0, le=1, description="Overall progress, 0..1: the mean of the jobs' (ended ones 1)."
    )
    jobs: list[JobSummary] = Field(description="The jobs, in the order of the files.")
    links: BatchLinks


class Health(BaseModel):
    status: str = "ok"


class Readiness(BaseModel):
    status: str = Field(description="'ready' or 'unavailable'.")
    redis: bool
    storage: bool
