"""Deleting a job for good: what ``DELETE`` of an ended job or batch does, and how a
submission that failed half-way is taken back."""

from __future__ import annotations

import contextlib
import logging

from rq.exceptions import NoSuchJobError
from rq.job import Job

from pbrsr_jobs.events import JobEvents
from pbrsr_jobs.objstore import StoreUnavailable
from pbrsr_jobs.store import JobFiles, JobIndex, JobLayout

log = logging.getLogger("pbrsr.service")


def delete_job(job_id: str, index: JobIndex, layout: JobLayout, files: JobFiles) -> None:
    """Delete a job: its objects in the store first (while the store cannot be used this
    raises StoreUnavailable, answered 503, and the job is kept whole), then the rest as
    :func:`_forget` does."""
    files.remove(job_id)
    _forget(job_id, index, layout)


def take_back(job_id: str, index: JobIndex, layout: JobLayout, files: JobFiles) -> None:
    """Delete a job of a submission that failed half-way, queued or not: off its queue and
    out of Redis first, then its objects. When the store cannot be used its objects stay
    (logged) and the rest goes even so."""
    _forget(job_id, index, layout)
    try:
        files.remove(job_id)
    except StoreUnavailable as exc:
        log.warning("job %s: its objects stay in the store, which is unavailable: %s", job_id, exc)


def _forget(job_id: str, index: JobIndex, layout: JobLayout) -> None:
    """Delete a job's RQ job if there is one (off its queue and registries), this machine's
    working files, its index entries and place in its batch, and its event stream."""
    with contextlib.suppress(NoSuchJobError):
        Job.fetch(job_id, connection=index.redis).delete()
    layout.remove(job_id)
    index.remove(job_id)
    JobEvents(index.redis, index.prefix).forget(job_id)
