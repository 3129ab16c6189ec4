"""JobReporter (the worker's progress callback) on real RQ jobs in Redis: rate-limited
job.meta writes, stage timings, history, overall fraction, cancellation, outcomes."""

from __future__ import annotations

import pytest
from rq import Queue
from rq.job import Job

from pbrsr_core.errors import Cancelled
from pbrsr_core.progress import Progress
from pbrsr_jobs.store import JobIndex, JobState
from tests.service_support import redis_client, settings_scope
from worker.progress import MAX_HISTORY, JobReporter


@pytest.fixture
def settings(tmp_path):
    yield from settings_scope(tmp_path)


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _job(settings) -> Job:
    redis = redis_client()
    job = Queue(settings.queue, connection=redis).enqueue(
        "worker.tasks.run_job", "x", meta={"owner": "anonymous", "name": "a.glb"}
    )
    JobIndex(redis, settings.key_prefix).add(job.id, "anonymous", 1.0)
    return job


def _stored_meta(job: Job) -> dict:
    return Job.fetch(job.id, connection=redis_client()).meta


def test_meta_writes_are_rate_limited_and_complete(settings):
    job = _job(settings)
    clock = Clock()
    index = JobIndex(redis_client(), settings.key_prefix)
    rep = JobReporter(job, index, interval_s=1.0, clock=clock)
    rep.start(attempt=1, worker_name="w1")
    assert _stored_meta(job)["state"] == "running"
    assert _stored_meta(job)["owner"] == "anonymous"  # enqueue-time fields survive

    rep(Progress(stage="optimize", step=0, total=100))  # stage change: written at once
    assert rep.saves == 1
    for i in range(1, 50):  # 49 calls within 0.49 s: no new write
        clock.t += 0.01
        rep(
            Progress(
                stage="optimize",
                step=i,
                total=100,
                losses={"total": 1.0 / i},
                metrics={"psnr_base_color": 20.0 + i / 10},
            )
        )
    assert rep.saves == 1
    clock.t += 0.6  # more than interval_s since the last write
    rep(
        Progress(
            stage="optimize",
            step=50,
            total=100,
            losses={"total": 0.02, "bad": float("nan")},
            metrics={"psnr_base_color": 25.0},
            eta_s=12.5,
        )
    )
    assert rep.saves == 2
    meta = _stored_meta(job)
    assert meta["stage"] == "optimize" and meta["step"] == 50 and meta["total"] == 100
    assert meta["losses"] == {"total": 0.02}  # NaN dropped
    assert meta["metrics"] == {"psnr_base_color": 25.0}
    assert meta["eta_s"] == 12.5
    assert 0 < meta["fraction"] < 1
    assert meta["history"][-1]["losses"] == {"total": 0.02}
    assert meta["timings"]["optimize"] == pytest.approx(1.09, abs=1e-6)


def test_stage_timings_fraction_and_outcome(settings):
    job = _job(settings)
    clock = Clock()
    index = JobIndex(redis_client(), settings.key_prefix)
    rep = JobReporter(job, index, interval_s=1.0, clock=clock)
    rep.start(attempt=2, worker_name="w2")
    fractions = []
    for stage, seconds in (("load", 2.0), ("init", 3.0), ("optimize", 5.0), ("export", 1.0)):
        for step in range(5):
            rep(Progress(stage=stage, step=step, total=5))
            fractions.append(rep.fraction)
            clock.t += seconds / 5
    assert fractions == sorted(fractions)  # never goes back
    rep.finish(JobState.FINISHED, summary={"wall_seconds": 11.0})
    meta = _stored_meta(job)
    assert meta["state"] == "finished" and meta["fraction"] == 1.0 and meta["attempt"] == 2
    assert meta["timings"] == pytest.approx(
        {"load": 2.0, "init": 3.0, "optimize": 5.0, "export": 1.0}
    )
    assert meta["summary"] == {"wall_seconds": 11.0}
    assert index.outcomes() == {"finished": 1}
    buckets, count, total = index.duration_histogram()
    assert count == 1 and total == pytest.approx(11.0)
    assert dict(buckets)["15"] == 1 and dict(buckets)["5"] == 0


def test_cancel_flag_raises_between_iterations(settings):
    job = _job(settings)
    clock = Clock()
    index = JobIndex(redis_client(), settings.key_prefix)
    rep = JobReporter(job, index, interval_s=1.0, cancel_check_s=0.25, clock=clock)
    rep.start(attempt=1, worker_name="w")
    rep(Progress(stage="optimize", step=0, total=10))
    index.request_cancel(job.id, 60)
    clock.t += 0.1  # checks are at most every 0.25 s
    rep(Progress(stage="optimize", step=1, total=10))
    clock.t += 0.2
    with pytest.raises(Cancelled):
        rep(Progress(stage="optimize", step=2, total=10))
    rep.finish(JobState.CANCELED)
    assert _stored_meta(job)["state"] == "canceled"
    assert index.outcomes() == {"canceled": 1}


def test_history_is_bounded_and_keeps_both_ends(settings):
    job = _job(settings)
    clock = Clock()
    rep = JobReporter(
        job, JobIndex(redis_client(), settings.key_prefix), interval_s=0.0, clock=clock
    )
    rep.start(attempt=1, worker_name="w")
    for step in range(3 * MAX_HISTORY):
        clock.t += 0.5
        rep(Progress(stage="optimize", step=step, total=3 * MAX_HISTORY, losses={"l": 1.0}))
    history = _stored_meta(job)["history"]
    assert len(history) <= MAX_HISTORY
    assert history[0]["step"] == 0 and history[-1]["step"] >= 3 * MAX_HISTORY - 3


def test_watchdog_interrupts_a_run_that_never_calls_back(settings):
    import threading
    import time

    from worker.cancel import CancelWatchdog

    index = JobIndex(redis_client(), settings.key_prefix)
    job_id = "f" * 32
    threading.Timer(0.3, index.request_cancel, args=(job_id, 60)).start()
    t0 = time.monotonic()
    with pytest.raises(Cancelled), CancelWatchdog(index, job_id, poll_s=0.1, grace_s=0.2):
        while time.monotonic() - t0 < 10:  # busy work with no progress callback
            sum(range(1000))
    elapsed = time.monotonic() - t0
    assert 0.3 < elapsed < 2.0


def test_watchdog_disarmed_after_exit_and_quiet_without_flag(settings):
    import time

    from worker.cancel import CancelWatchdog

    index = JobIndex(redis_client(), settings.key_prefix)
    with CancelWatchdog(index, "e" * 32, poll_s=0.05, grace_s=0.1) as dog:
        time.sleep(0.4)  # no flag: nothing happens
    assert not dog.fired
    index.request_cancel("e" * 32, 60)
    time.sleep(0.4)  # flag set after exit: nothing may be raised here
    assert not dog.fired


def _private_redis(port: int, tmp_path):
    import shutil
    import subprocess

    exe = shutil.which("redis-server")
    if exe is None:
        pytest.skip("redis-server is not installed")
    proc = subprocess.Popen(
        # persistent, as in docker-compose.yml: the job must outlive the restart
        [
            exe,
            "--port",
            str(port),
            "--bind",
            "127.0.0.1",
            "--save",
            "",
            "--appendonly",
            "yes",
            "--dir",
            str(tmp_path),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    from redis import Redis

    client = Redis(host="127.0.0.1", port=port, socket_connect_timeout=0.5, socket_timeout=1)
    from pbrsr_bench.load import wait_until

    def up():
        try:
            return client.ping()
        except Exception:  # noqa: BLE001
            return False

    wait_until(up, 10, "redis-server to start", 0.05)
    return proc, client


def test_redis_outage_does_not_kill_the_run_and_the_outcome_is_kept(tmp_path):
    import threading

    from pbrsr_bench.load import free_port

    port = free_port()
    proc, client = _private_redis(port, tmp_path)
    try:
        job = Queue("outage", connection=client).enqueue("worker.tasks.run_job", "x")
        index = JobIndex(client, "outage")
        rep = JobReporter(job, index, interval_s=0.0, cancel_check_s=0.0, finish_retry_s=30)
        rep.start(attempt=1, worker_name="w")
        proc.terminate()
        proc.wait(timeout=10)
        for step in range(3):  # progress and cancel checks while Redis is away: no error
            rep(Progress(stage="optimize", step=step, total=3, losses={"l": 1.0}))

        restarted = {}

        def restart():
            restarted["proc"], _ = _private_redis(port, tmp_path)

        timer = threading.Timer(1.0, restart)
        timer.start()
        rep.finish(JobState.FINISHED)  # retries until Redis is back
        timer.join()
        assert Job.fetch(job.id, connection=client).meta["state"] == "finished"
        assert index.outcomes() == {"finished": 1}
    finally:
        for p in (proc, locals().get("restarted", {}).get("proc")):
            if p is not None and p.poll() is None:
                p.terminate()
                p.wait(timeout=10)
