"""Threads per worker: cgroup quota, affinity, division among the host's workers, the explicit
setting, counting workers in Redis, and a real ``pbrsr worker`` run with one thread."""

from __future__ import annotations

import re
import socket
from types import SimpleNamespace

import pytest

from pbrsr_bench.load import wait_until
from pbrsr_jobs.settings import Settings
from tests.service_support import (
    cleanup_redis,
    make_settings,
    redis_client,
    worker_process,
)
from worker import threads as wt


@pytest.mark.parametrize(
    ("text", "cpus"),
    [
        ("max 100000", None),
        ("max 100000\n", None),
        ("200000 100000\n", 2.0),
        ("150000 100000", 1.5),
        ("50000 100000", 0.5),
        ("", None),
        (None, None),
        ("garbage", None),
    ],
)
def test_cpu_max_is_parsed(text, cpus):
    assert wt.parse_cpu_max(text) == cpus


def test_cpu_max_file(tmp_path):
    assert wt.read_cpu_max(tmp_path / "missing") is None
    path = tmp_path / "cpu.max"
    path.write_text("400000 100000\n")
    assert wt.read_cpu_max(path) == 4.0
    path.write_text("max 100000\n")
    assert wt.read_cpu_max(path) is None


@pytest.mark.parametrize(
    ("affinity", "cpu_count", "quota", "cores"),
    [
        (8, 64, None, 8),  # the affinity mask, not the machine
        (None, 16, None, 16),  # no sched_getaffinity: the machine's count
        (None, None, None, 1),
        (8, 64, 2.0, 2),  # the quota is smaller
        (8, 64, 2.5, 2),  # rounded down
        (8, 64, 0.5, 1),  # at least one
        (4, 64, 16.0, 4),  # the affinity is smaller
    ],
)
def test_usable_cores(affinity, cpu_count, quota, cores):
    assert wt.usable_cores(affinity, cpu_count, quota) == cores


@pytest.mark.parametrize(
    ("cores", "workers", "threads"),
    [(8, 1, 8), (8, 2, 4), (10, 3, 3), (7, 2, 3), (2, 4, 1), (1, 1, 1), (4, 0, 4)],
)
def test_cores_are_divided_among_workers(cores, workers, threads):
    assert wt.threads_per_worker(cores, workers) == threads


def test_the_explicit_setting_wins():
    assert wt.threads_per_worker(64, 8, explicit=3) == 3
    assert wt.threads_per_worker(2, 8, explicit=6) == 6


def test_process_cores_follow_affinity_and_quota(tmp_path, monkeypatch):
    monkeypatch.setattr(wt.os, "sched_getaffinity", lambda pid: {0, 1, 2, 3, 4, 5}, raising=False)
    monkeypatch.setattr(wt.os, "cpu_count", lambda: 32)
    cpu_max = tmp_path / "cpu.max"
    assert wt.process_cores(cpu_max) == 6
    cpu_max.write_text("300000 100000\n")
    assert wt.process_cores(cpu_max) == 3
    monkeypatch.delattr(wt.os, "sched_getaffinity")
    cpu_max.write_text("max 100000\n")
    assert wt.process_cores(cpu_max) == 32


def test_host_workers_are_counted_by_host_and_queue():
    def worker(name, host, queues):
        return SimpleNamespace(name=name, hostname=host, queue_names=lambda: queues)

    workers = [
        worker("a", "h1", ["pbrsr"]),
        worker("b", "h1", ["pbrsr-large"]),
        worker("c", "h2", ["pbrsr"]),  # another host
        worker("d", "h1", ["other-app"]),  # another deployment's queue
        worker("me", "h1", ["pbrsr", "pbrsr-large"]),
    ]
    queues = ["pbrsr", "pbrsr-large"]
    assert wt.count_host_workers(workers, queues, "h1", exclude="me") == 2
    assert wt.count_host_workers(workers, queues, "h1") == 3


def test_workers_in_redis_are_counted(tmp_path):
    from rq import Queue, Worker

    settings = make_settings(tmp_path)
    redis = redis_client()
    queues = settings.listen_queues("all")
    others = [
        Worker([Queue(q, connection=redis) for q in queues], connection=redis, name=f"{n}-{q}")
        for n, q in enumerate([settings.queue] * 2)
    ]
    try:
        assert wt.host_workers(redis, queues, "me") == 1  # a starting worker counts itself
        for w in others:
            w.register_birth()
        assert wt.host_workers(redis, queues, "me") == 3
        assert wt.host_workers(redis, queues, others[0].name) == 2  # counted once
        assert socket.gethostname() == others[0].hostname
    finally:
        for w in others:
            w.register_death()


def test_settings_default_to_automatic(monkeypatch):
    monkeypatch.delenv("PBRSR_WORKER_THREADS", raising=False)
    monkeypatch.delenv("PBRSR_WORKERS_PER_HOST", raising=False)
    s = Settings(_env_file=None)
    assert (s.worker_threads, s.workers_per_host) == (0, 0)
    monkeypatch.setenv("PBRSR_WORKER_THREADS", "3")
    monkeypatch.setenv("PBRSR_WORKERS_PER_HOST", "2")
    s = Settings(_env_file=None)
    assert (s.worker_threads, s.workers_per_host) == (3, 2)


def test_a_worker_runs_the_threads_it_is_given(tmp_path):
    settings = make_settings(tmp_path, worker_threads=1)
    log_path = tmp_path / "worker.log"
    with worker_process(settings, log_path) as proc:

        def started() -> bool:
            if proc.poll() is not None:
                raise AssertionError(f"pbrsr worker exited: {log_path.read_text()[-2000:]}")
            return " threads" in log_path.read_text() and "on queues" in log_path.read_text()

        wait_until(started, 120, "the worker to start", 0.2)
    text = log_path.read_text()
    assert re.search(r"1 threads: PBRSR_WORKER_THREADS; torch 1 \(inter-op 1\), numba 1", text)
    assert re.search(r"worker \S+ on queues .*, 1 threads", text)


def test_threads_are_fitted_again_when_workers_come_and_go(tmp_path, monkeypatch):
    from rq import Queue, Worker

    from worker import runner

    applied: list[int] = []

    def fake_apply(threads):
        applied.append(threads)
        return {"torch": threads, "interop": threads, "numba": threads}

    monkeypatch.setattr(runner, "process_cores", lambda: 8)
    monkeypatch.setattr(runner, "apply_threads", fake_apply)
    settings = make_settings(tmp_path, worker_threads=0)
    redis = redis_client()
    assert runner._fit_threads(settings, redis, "me") == 8  # alone on the host
    other = Worker(
        [Queue(settings.queue, connection=redis)], connection=redis, name=f"other-{settings.queue}"
    )
    other.register_birth()
    try:
        assert runner._fit_threads(settings, redis, "me", 8) == 4
        assert runner._fit_threads(settings, redis, "me", 4) == 4
    finally:
        other.register_death()
    assert runner._fit_threads(settings, redis, "me", 4) == 8
    assert applied == [8, 4, 8]  # set only when the count changed
    per_host = make_settings(tmp_path, worker_threads=0, workers_per_host=3)
    assert runner._fit_threads(per_host, redis, "me") == 2
    assert runner._fit_threads(make_settings(tmp_path, worker_threads=5), redis, "me") == 5


def test_a_counting_worker_fits_its_threads_before_each_job(tmp_path):
    from rq import Queue

    from worker.runner import PbrsrWorker

    settings = make_settings(tmp_path, worker_threads=0)
    redis = redis_client()
    queue = Queue(settings.queue, connection=redis)
    seen: list[int] = []

    def fit(current: int) -> int:
        seen.append(current)
        return current + 1

    worker = PbrsrWorker(
        [queue], connection=redis, name=f"fit-{settings.queue}", threads=2, fit_threads=fit
    )
    try:
        for _ in range(2):
            queue.enqueue("math.sqrt", 4.0)
        assert worker.work(burst=True, max_jobs=2)
        assert seen == [2, 3] and worker.threads == 4
    finally:
        cleanup_redis(settings)
