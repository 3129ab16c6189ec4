"""Deleting a job for good: what ``DELETE`` of an ended job or batch does, and how a batch
that failed half-way is taken back."""

from __future__ import annotations

import contextlib

from rq.exceptions import NoSuchJobError
from rq.job import Job

from pbrsr_jobs.events import JobEvents
from pbrsr_jobs.store import JobIndex, JobLayout


def delete_job(job_id: str, index: JobIndex, layout: JobLayout) -> None:
    """Delete a job: its RQ job if there is one (off its queue and registries), its files,
    its index entries and place in its batch, and its event stream."""
    with contextlib.suppress(NoSuchJobError):
        Job.fetch(job_id, connection=index.redis).delete()
    layout.remove(job_id)
    index.remove(job_id)
    JobEvents(index.redis, index.prefix).forget(job_id)
