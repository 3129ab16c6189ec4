"""What a finished job leaves in the job storage, checked alike by the end-to-end tests."""

from __future__ import annotations

from pathlib import Path

from pbrsr_jobs.store import JobLayout

FINISHED_JOB_ENTRIES = ["crops", "input", "job.json", "output", "result.zip", "thumbs"]


def assert_one_bundle(storage_dir: Path, job_id: str) -> Path:
    """Check that the folder of the finished job ``job_id`` holds its input, record, output,
    one bundle, thumbnails and detail crops and nothing else (nothing temporary); -> the
    folder."""
    job_dir = JobLayout(storage_dir).job_dir(job_id)
    names = sorted(p.name for p in job_dir.iterdir())
    assert names == FINISHED_JOB_ENTRIES, names
    return job_dir
