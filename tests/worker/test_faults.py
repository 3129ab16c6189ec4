"""Faults with real processes: a worker SIGKILLed mid-job; its job is recovered by the other
worker (RQ's abandoned-job handling + Retry) and finishes with one bundle and no partial
files."""

from __future__ import annotations

import io
import os
import signal
import zipfile

import pytest
from fastapi.testclient import TestClient
from rq.job import Job

from pbrsr_bench.load import wait_until
from service.app import create_app
from tests.bundles import assert_one_bundle
from tests.service_support import (
    asset_bytes,
    cleanup_redis,
    make_settings,
    post_asset,
    redis_client,
    worker_process,
)

pytestmark = pytest.mark.slow


def test_killed_worker_job_is_retried_elsewhere_and_finishes(tmp_path):
    settings = make_settings(tmp_path, heartbeat_s=1.0, maintenance_s=1)
    try:
        with (
            worker_process(settings, tmp_path / "a.log", name="victim-a") as a,
            worker_process(settings, tmp_path / "b.log", name="victim-b") as b,
            TestClient(create_app(settings), raise_server_exceptions=False) as client,
        ):
            procs = {"victim-a": a, "victim-b": b}
            job_id = post_asset(
                client, asset_bytes(tmp_path), options={"method": "bicubic"}
            ).json()["id"]

            def stage():
                j = client.get(f"/v1/jobs/{job_id}").json()
                return j["status"] == "running" and j["stage"] == "export" and j

            wait_until(stage, 240, "the job to be mid-run", 0.2)
            meta = Job.fetch(job_id, connection=redis_client()).meta
            victim = meta["worker"]
            os.kill(procs[victim].pid, signal.SIGKILL)
            procs[victim].wait(timeout=10)
            survivor = procs["victim-b" if victim == "victim-a" else "victim-a"]

            def ended():
                assert survivor.poll() is None
                j = client.get(f"/v1/jobs/{job_id}").json()
                return j["status"] in ("finished", "failed", "canceled") and j

            job = wait_until(ended, 300, "the job to be retried and end", 0.5)
            assert job["status"] == "finished", job
            assert job["attempt"] == 2
            meta = Job.fetch(job_id, connection=redis_client()).meta
            assert meta["worker"] != victim

            r = client.get(f"/v1/jobs/{job_id}/result")
            assert r.status_code == 200
            names = zipfile.ZipFile(io.BytesIO(r.content)).namelist()
            assert "asset.glb" in names and "report.json" in names
            job_dir = assert_one_bundle(settings.storage_dir, job_id)
            assert not list((job_dir / "output").rglob(".*"))
    finally:
        cleanup_redis(settings)
