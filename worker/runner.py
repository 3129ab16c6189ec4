"""The ``pbrsr worker`` process: one RQ worker, one device, priors loaded once.

Why ``SimpleWorker`` and not RQ's default ``Worker``
----------------------------------------------------
RQ's ``Worker`` forks a new "work horse" child for every job. Anything the parent loaded is
shared copy-on-write, but whatever the job loads (a prior's weights, the CUDA context, the
converted TF.js graph) is loaded again in every child and thrown away with it; and a forked
child cannot re-initialise CUDA once the parent has touched it. PBR-SR jobs are long (minutes)
and start by loading a large prior, so per-job forking wastes exactly what we want to keep.
``SimpleWorker`` runs each job in the worker process itself: :func:`run_worker` preloads the
priors named in ``PBRSR_PRELOAD_PRIORS`` on the configured device, and
``pbrsr_core.prior.load_prior``'s per-process cache hands every later job the same model.

What ``SimpleWorker`` gives up, and how :class:`PbrsrWorker` makes up for it:

* **Heartbeats.** ``SimpleWorker`` sends none while a job runs and registers the job as
  alive for ``job_timeout + 60`` s, so a killed worker's job would sit "started" for hours.
  ``PbrsrWorker`` beats from a background thread every ``heartbeat_s`` during a job and asks
  for a TTL of only ``3 * heartbeat_s``; when the process dies (SIGKILL, OOM killer) the job's
  entry in RQ's StartedJobRegistry expires within that time, and the next maintenance pass of
  any other live worker (every ``maintenance_s``; idle workers wake up for it) retries it
  through the job's ``Retry``. The job then reuses the dead attempt's cached intermediates
  (``jobs/<id>/work``) and removes its temporary files.
* **Stopping a job from outside.** There is no child to kill, so cancellation is cooperative:
  the API sets a flag in Redis that the job's progress callback checks between iterations
  (``worker.progress.JobReporter``), and the job ends within about 2 s and frees its memory.
* **Isolation.** A crash of a job takes the worker down with it; RQ's retry and another
  worker (or the supervisor restarting this one: docker ``restart: unless-stopped``) recover.

One worker per GPU on a farm: run ``PBRSR_DEVICE=cuda:N pbrsr worker`` once per device.

Threads: before it loads anything, a worker sets torch's and numba's thread counts to
``PBRSR_WORKER_THREADS``, or, when that is 0, to the cores it may use divided among the
workers on its host (:mod:`worker.threads`), so that several workers on one machine do not
each start a thread per core and slow one another down. Workers counted in Redis count again
before each job, so workers started at the same moment, or started and stopped later, settle
on their share (torch's inter-op threads keep their start-up value).
"""

from __future__ import annotations

import logging
import math
import socket
import threading
import uuid
from collections.abc import Callable
from functools import partial
from typing import Any

from rq import Queue, SimpleWorker
from rq.worker import WorkerStatus

from pbrsr_core.errors import PbrsrError
from pbrsr_jobs.objstore import open_store
from pbrsr_jobs.settings import Settings
from pbrsr_jobs.store import JobFiles, JobIndex, JobLayout, sweep_expired

from .tasks import WorkerContext, set_context
from .threads import apply_threads, host_workers, process_cores, threads_per_worker
from .webhooks import WebhookDispatcher

log = logging.getLogger("pbrsr.worker")


class PbrsrWorker(SimpleWorker):
    """``SimpleWorker`` with short job heartbeats from a thread and job expiry on maintenance."""

    def __init__(
        self,
        *args: Any,
        heartbeat_s: float = 10.0,
        sweep: Any = None,
        threads: int = 0,
        fit_threads: Callable[[int], int] | None = None,
        **kwargs: Any,
    ):
        super().__init__(*args, **kwargs)
        self.heartbeat_s = float(heartbeat_s)
        self._sweep = sweep
        self.threads = threads  # torch/numba threads of this process (0: not set by pbrsr)
        self._fit_threads = fit_threads

    def get_heartbeat_ttl(self, job: Any, working_time: float = 0.0) -> int:
        """Seconds a running job stays registered without a heartbeat: three periods."""
        return max(2, int(math.ceil(3 * self.heartbeat_s)))

    def execute_job(self, job: Any, queue: Any) -> None:
        if self._fit_threads is not None:
            try:  # workers may have started or stopped on this host since the last job
                self.threads = self._fit_threads(self.threads)
            except Exception as exc:  # noqa: BLE001 - keep the threads it has
                log.warning("threads not re-fitted: %s", exc)
        execution = self.prepare_execution(job)
        stop = threading.Event()
        beat = threading.Thread(
            target=self._beat, args=(job, execution, stop), name="pbrsr-heartbeat", daemon=True
        )
        beat.start()
        try:
            self.perform_job(job, queue, execution)
        finally:
            stop.set()
            beat.join(timeout=5)
        self.set_state(WorkerStatus.IDLE)

    def _beat(self, job: Any, execution: Any, stop: threading.Event) -> None:
        while not stop.wait(self.heartbeat_s):
            try:
                self.maintain_heartbeats(job, execution)
            except Exception as exc:  # noqa: BLE001 - Redis blips must not kill the job
                log.warning("heartbeat failed: %s", exc)

    def run_maintenance_tasks(self) -> None:
        super().run_maintenance_tasks()
        if self._sweep is not None:
            try:
                self._sweep()
            except Exception:  # noqa: BLE001 - expiry is retried on the next pass
                log.exception("expiring old jobs failed")


def _preload(names: list[str], device: Any) -> None:
    """Import the pipeline and load the named priors now, so no job pays for it."""
    try:
        import pbrsr_core.pipeline  # noqa: F401 - heavy imports (torch, numba kernels)
    except ImportError:
        log.exception("the pipeline cannot be imported; jobs will fail until this is fixed")
    if not names:
        return
    from pbrsr_core.prior import load_prior

    for name in names:
        try:
            load_prior(name, device)
            log.info("prior %s loaded on %s", name, device)
        except PbrsrError as exc:
            log.warning("prior %s not preloaded: %s", name, exc.message)


def _choose_threads(settings: Settings, redis: Any, name: str) -> tuple[int, str]:
    """Threads for this worker and why: PBRSR_WORKER_THREADS, else this process's cores
    divided among PBRSR_WORKERS_PER_HOST workers or, when that is 0, the host's workers in
    Redis (this one included)."""
    if settings.worker_threads > 0:
        return settings.worker_threads, "PBRSR_WORKER_THREADS"
    cores = process_cores()
    if settings.workers_per_host > 0:
        workers, source = settings.workers_per_host, "PBRSR_WORKERS_PER_HOST"
    else:
        workers, source = host_workers(redis, settings.listen_queues("all"), name), "in Redis"
    threads = threads_per_worker(cores, workers)
    return threads, f"{cores} usable cores / {workers} workers on this host ({source})"


def _fit_threads(settings: Settings, redis: Any, name: str, current: int = 0) -> int:
    """Choose this worker's threads and, when they are not ``current``, set them in torch
    and numba and log the choice. Returns the threads."""
    threads, why = _choose_threads(settings, redis, name)
    if threads != current:
        set_to = apply_threads(threads)
        log.info(
            "%d threads: %s; torch %d (inter-op %d), numba %d",
            threads,
            why,
            set_to["torch"],
            set_to["interop"],
            set_to["numba"],
        )
    return threads


def build_worker(settings: Settings, *, name: str | None = None) -> PbrsrWorker:
    """Connect, check storage and device, preload priors, and make the worker (not started)."""
    from redis import Redis

    from pbrsr_core.device import resolve_device

    settings.configure_runtime()
    layout = JobLayout(settings.prepare_storage())
    files = JobFiles(open_store(settings))
    files.store.check()  # StoreUnavailable: the worker does not start
    redis = Redis.from_url(settings.redis_url)
    redis.ping()
    device = resolve_device(settings.device)
    index = JobIndex(redis, settings.key_prefix)
    name = name or f"pbrsr-{socket.gethostname()}-{uuid.uuid4().hex[:6]}"
    # before any torch work: inter-op threads can be set only until parallel work has run
    threads = _fit_threads(settings, redis, name)
    counted = settings.worker_threads == 0 and settings.workers_per_host == 0
    _preload(settings.preload_priors, device)

    def sweep() -> None:
        if index.try_sweep_lock(settings.maintenance_s):
            sweep_expired(redis, index, layout, files, settings.retention_s)

    worker = PbrsrWorker(
        [Queue(q, connection=redis) for q in settings.listen_queues()],
        connection=redis,
        name=name,
        # An idle worker blocks on the queue for worker_ttl - 15 s; keep that no longer than
        # the maintenance period so idle workers recover abandoned jobs in time.
        worker_ttl=max(16, settings.maintenance_s + 15),
        maintenance_interval=settings.maintenance_s,
        job_monitoring_interval=max(1, int(settings.heartbeat_s)),
        heartbeat_s=settings.heartbeat_s,
        sweep=sweep,
        threads=threads,
        # workers counted in Redis: count again before each job (others may have started)
        fit_threads=partial(_fit_threads, settings, redis, name) if counted else None,
    )
    set_context(
        WorkerContext(
            settings=settings,
            layout=layout,
            files=files,
            index=index,
            device=str(device),
            worker_name=name,
        )
    )
    return worker


def run_worker(
    settings: Settings,
    *,
    burst: bool = False,
    name: str | None = None,
    max_jobs: int | None = None,
) -> bool:
    """Run a worker until stopped (or, with ``burst``, until the queue is empty)."""
    logging.basicConfig(
        level=settings.log_level, format="%(asctime)s %(name)s %(levelname)s %(message)s"
    )
    worker = build_worker(settings, name=name)
    log.info(
        "worker %s on queues %s, %d threads",
        worker.name,
        ", ".join(settings.listen_queues()),
        worker.threads,
    )
    dispatcher = WebhookDispatcher(
        worker.connection,
        settings.key_prefix,
        name=worker.name,
        secret=settings.webhook_secret,
        timeout_s=settings.webhook_timeout_s,
        max_attempts=settings.webhook_max_attempts,
        backoff_s=settings.webhook_backoff_s,
    )
    dispatcher.start()  # beside the jobs, never in their way
    try:
        return worker.work(burst=burst, logging_level=settings.log_level, max_jobs=max_jobs)
    finally:
        dispatcher.stop()
