"""Faults with real processes (issue 6): Redis stopped during a job, and a full disk.

(a) A private, persistent ``redis-server`` (never the shared one) serves a real ``pbrsr
serve`` and a real ``pbrsr worker``; it is stopped mid-job and restarted on the same port
with the same data: ``/readyz`` answers 503 while it is down, the API answers clean problem
bodies (no crash), and after the restart the API is ready again and the job finishes.

(b) Full disk: the job storage is a 4 MB tmpfs (mounted when the test runs as root, the
realistic case: ENOSPC) and, everywhere, a worker whose RLIMIT_FSIZE forbids files beyond a
few kB (EFBIG; SIGXFSZ is ignored so the write fails instead of killing the worker). Either
way the job fails with a clear storage message and leaves no partial bundle.

(c) Cancel mid-job within 2 s: covered by tests/worker/test_e2e.py
(test_running_job_cancels_within_two_seconds).
SIGKILLed worker: tests/worker/test_faults.py.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import httpx
import pytest

from pbrsr_bench.load import free_port, wait_until
from pbrsr_jobs.store import JobLayout
from tests.service_support import (
    PBRSR,
    REPO,
    api_server,
    asset_bytes,
    cleanup_redis,
    make_settings,
    settings_env,
    stop_process,
    worker_process,
)

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
    return wait_until(
        lambda: (j := _job(base, job_id))["status"] in _TERMINAL and j,
        timeout,
        f"job {job_id} to end",
        0.2,
    )


def _assert_no_partial_bundle(job_dir: Path) -> None:
    names = sorted(p.name for p in job_dir.iterdir())
    assert not {"result.zip", "output", "thumbs", "crops"} & set(names), names
    assert [n for n in names if n.startswith(".tmp")] == [], names
    files = sorted(p.relative_to(job_dir).as_posix() for p in job_dir.rglob("*") if p.is_file())
    assert files == ["input/asset.glb", "job.json"], files  # nothing half-written anywhere


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

    wait_until(up, 15, "redis-server to start", 0.05)
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
            wait_until(
                lambda: _job(base, job_id)["status"] == "running", 120, "the job to run", 0.1
            )

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
            wait_until(
                lambda: httpx.get(f"{base}/readyz", timeout=10).status_code == 200,
                30,
                "/readyz to answer 200 again",
                0.2,
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


# ----------------------------------------------------------------------------- (b) full disk
@contextlib.contextmanager
def _small_tmpfs(path: Path, size: str = "4m"):
    """Mount a ``size`` tmpfs on ``path`` (root only); skip the test when mounting fails."""
    path.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a tmpfs needs root")
    r = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size},mode=0755", "tmpfs", str(path)],
        capture_output=True,
        text=True,
    )
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
    try:
        yield path
    finally:
        for _ in range(20):  # a process that just exited may still hold it for a moment
            if subprocess.run(["umount", str(path)], capture_output=True).returncode == 0:
                break
            time.sleep(0.25)
        else:
            subprocess.run(["umount", "-l", str(path)], capture_output=True)


def _fill(folder: Path, leave_bytes: int) -> None:
    """Write a filler file so that about ``leave_bytes`` stay free on ``folder``'s filesystem."""
    st = os.statvfs(folder)
    free = st.f_bavail * st.f_frsize
    with open(folder / "filler.bin", "wb") as f:
        f.write(b"\0" * max(0, free - leave_bytes))
    st = os.statvfs(folder)
    assert st.f_bavail * st.f_frsize <= leave_bytes + 8192


def _limited_worker(settings, log_path: Path, max_file_bytes: int) -> subprocess.Popen:
    """A real ``pbrsr worker`` that cannot write a file beyond ``max_file_bytes``: writes past
    it fail with EFBIG (SIGXFSZ ignored, so the write fails instead of killing the worker)."""
    import resource

    def limit() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (max_file_bytes, max_file_bytes))

    log_path.write_bytes(b"")
    with open(log_path, "ab") as log:
        return subprocess.Popen(
            [PBRSR, "worker"],
            env=settings_env(settings),
            stdout=log,
            stderr=subprocess.STDOUT,
            cwd=REPO,
            preexec_fn=limit,
        )


@pytest.mark.parametrize("mechanism", ["tmpfs", "rlimit"])
def test_full_disk_fails_the_job_with_a_storage_error_and_no_partial_bundle(tmp_path, mechanism):
    storage = tmp_path / "storage"
    with contextlib.ExitStack() as stack:
        if mechanism == "tmpfs":
            stack.enter_context(_small_tmpfs(storage))
        settings = make_settings(tmp_path, storage_dir=storage)
        stack.callback(cleanup_redis, settings)
        base = stack.enter_context(api_server(settings, tmp_path / "api.log"))
        # submitted before a worker runs, so the disk fills between intake and the run
        job_id = _post(base, asset_bytes(tmp_path)).json()["id"]
        if mechanism == "tmpfs":
            _fill(storage, leave_bytes=16 * 1024)
            worker = stack.enter_context(worker_process(settings, tmp_path / "worker.log"))
        else:
            worker = _limited_worker(settings, tmp_path / "worker.log", 24 * 1024)
            stack.callback(stop_process, worker)
        job = _wait_end(base, job_id, 180)
        log = (tmp_path / "worker.log").read_text()
        assert job["status"] == "failed", (job, log[-3000:])
        assert job["code"] == "storage-error", job
        error = job["error"]
        # a message the operator can act on: what failed and the reason
        assert "write" in error, error
        if mechanism == "tmpfs":
            assert "No space left on device" in error or "disk space" in error, error
        else:
            assert "File too large" in error or "storage" in error, error
        assert str(tmp_path) not in error and "/" not in error.split(":")[-1], error
        assert "Traceback" not in error
        assert httpx.get(f"{base}/v1/jobs/{job_id}/result", timeout=10).status_code == 409
        _assert_no_partial_bundle(JobLayout(storage).job_dir(job_id))
        assert not any((storage / "uploads").iterdir())
        assert worker.poll() is None, log[-3000:]  # the worker lives on
