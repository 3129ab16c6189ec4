"""The progress callback a job hands to ``upscale_asset``: job.meta writes and cancellation.

:class:`JobReporter` is a ``ProgressFn``. On every call it

* checks the job's cancel flag in Redis (at most every ``cancel_check_s``, 0.25 s) and raises
  :class:`~pbrsr_core.errors.Cancelled` when it is set - the pipeline calls back between
  iterations, so a running job stops within about an iteration plus 0.25 s;
* writes the job's progress to ``job.meta`` with ``save_meta()`` (which touches only the
  meta field, never RQ's own state) at most every ``interval_s`` (1 s) and at every stage
  change: stage, step/total, overall fraction, ETA, latest losses and metrics (consistency
  PSNR to the LR input), per-stage timings and a decimated history for the loss/PSNR plots.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

from redis.exceptions import ConnectionError as RedisConnectionError
from redis.exceptions import TimeoutError as RedisTimeoutError

from pbrsr_core.errors import Cancelled
from pbrsr_core.progress import Progress
from pbrsr_jobs.events import STATE_EVENTS, JobEvents
from pbrsr_jobs.store import JobIndex, JobState

# Share of the whole run each pipeline stage takes, per method, in the order the stages
# come (measured roughly on CPU: previews dominate bicubic, the optimizer dominates pbrsr).
# Used for the overall progress bar; a stage not listed leaves the bar where it is.
STAGE_WEIGHTS: dict[str, dict[str, float]] = {
    "bicubic": {"load": 0.05, "export": 0.90, "bundle": 0.05},
    "direct": {"load": 0.03, "load_prior": 0.05, "prior": 0.50, "export": 0.38, "bundle": 0.04},
    "pbrsr": {  # from a balanced run on WaterBottle (512 -> 2048, report.json timings)
        "load": 0.01,
        "load_prior": 0.01,
        "prior_check": 0.02,
        "init": 0.25,
        "gbuffers": 0.02,
        "pseudo_gt": 0.14,
        "optimize": 0.47,
        "export": 0.06,
        "bundle": 0.02,
    },
}
MAX_HISTORY = 400
REDIS_ERRORS = (RedisConnectionError, RedisTimeoutError)
log = logging.getLogger("pbrsr.worker")


def _with_retries(fn: Callable[[], Any], budget_s: float) -> None:
    """Run ``fn``, retrying Redis connection errors with backoff for up to ``budget_s``: a
    job's outcome must not be lost to a Redis restart."""
    deadline = time.monotonic() + budget_s
    wait = 0.5
    while True:
        try:
            fn()
            return
        except REDIS_ERRORS as exc:
            if time.monotonic() + wait > deadline:
                raise
            log.warning("redis unavailable (%s); retrying in %.1f s", exc, wait)
            time.sleep(wait)
            wait = min(wait * 2, 10.0)


def _finite(values: dict[str, Any]) -> dict[str, float]:
    out = {}
    for key, value in (values or {}).items():
        try:
            v = float(value)
        except (TypeError, ValueError):
            continue
        if v == v and abs(v) != float("inf"):
            out[str(key)] = v
    return out


class JobReporter:
    """``ProgressFn`` for one run of one RQ job (``job``: an ``rq.job.Job``)."""

    def __init__(
        self,
        job: Any,
        index: JobIndex,
        *,
        interval_s: float = 1.0,
        cancel_check_s: float = 0.25,
        clock: Callable[[], float] = time.monotonic,
        method: str = "pbrsr",
        finish_retry_s: float = 120.0,
    ):
        self.job = job
        self.index = index
        self.interval_s = interval_s
        self.cancel_check_s = cancel_check_s
        self.clock = clock
        self.finish_retry_s = finish_retry_s
        self.weights = STAGE_WEIGHTS.get(method, STAGE_WEIGHTS["pbrsr"])
        self.t0 = clock()
        self.last_save = -float("inf")
        self.last_cancel_check = -float("inf")
        self.stage: str | None = None
        self.stage_t0 = self.t0
        self.timings: dict[str, float] = {}
        self.history: list[dict[str, Any]] = []
        self.fraction = 0.0
        self.saves = 0
        self.events = JobEvents(index.redis, index.prefix)
        self.owner = str(job.meta.get("owner", ""))

    def _publish(self, type_: str, data: dict[str, Any], *, retry_s: float = 0.0) -> None:
        """One job event (pbrsr_jobs.events); progress events are best effort, the others
        are retried like the outcome."""
        try:
            webhook = self.job.meta.get("webhook")
            publish = self.events.publish
            _with_retries(lambda: publish(self.job.id, self.owner, type_, data, webhook), retry_s)
        except REDIS_ERRORS as exc:
            log.warning("job %s: %s event not published: %s", self.job.id, type_, exc)

    # -- lifecycle -------------------------------------------------------------------------
    def start(self, attempt: int, worker_name: str) -> None:
        meta = self.job.meta
        for key in ("stage", "step", "total", "eta_s", "losses", "metrics", "error", "code"):
            meta.pop(key, None)
        meta.update(
            state=JobState.RUNNING.value,
            attempt=attempt,
            worker=worker_name,
            started_at=time.time(),
            fraction=0.0,
            timings={},
            history=[],
            updated_at=time.time(),
        )
        self.job.save_meta()
        self._publish("started", {"attempt": attempt, "worker": worker_name}, retry_s=10.0)

    def finish(
        self,
        state: JobState,
        *,
        error: str | None = None,
        code: str | None = None,
        summary: dict[str, Any] | None = None,
    ) -> None:
        """Record the outcome in ``job.meta`` and the outcome counters."""
        now = self.clock()
        if self.stage is not None:
            self.timings[self.stage] = self.timings.get(self.stage, 0.0) + now - self.stage_t0
        meta = self.job.meta
        meta.update(
            state=state.value,
            ended_at=time.time(),
            timings={k: round(v, 3) for k, v in self.timings.items()},
            history=self.history,
            updated_at=time.time(),
            eta_s=0.0 if state == JobState.FINISHED else None,
        )
        if state == JobState.FINISHED:
            meta["fraction"] = 1.0
        if error is not None:
            meta["error"] = error
            meta["code"] = code or "error"
        if summary:
            meta["summary"] = summary
        _with_retries(self.job.save_meta, self.finish_retry_s)
        _with_retries(
            lambda: self.index.record_outcome(
                state, now - self.t0 if state == JobState.FINISHED else None
            ),
            self.finish_retry_s,
        )
        outcome = {k: meta[k] for k in ("error", "code", "summary") if k in meta}
        self._publish(STATE_EVENTS[state], outcome, retry_s=self.finish_retry_s)

    def check_cancel(self) -> None:
        try:
            requested = self.index.cancel_requested(self.job.id)
        except REDIS_ERRORS as exc:  # Redis away for a moment: keep working
            log.warning("job %s: cannot read the cancel flag: %s", self.job.id, exc)
            return
        if requested:
            raise Cancelled("the job was canceled")

    # -- ProgressFn ------------------------------------------------------------------------
    def __call__(self, event: Progress) -> None:
        if event.stage == "done":  # the pipeline's end marker, not a stage of its own
            self.check_cancel()
            return
        now = self.clock()
        stage_changed = event.stage != self.stage
        if stage_changed:
            if self.stage is not None:
                self.timings[self.stage] = self.timings.get(self.stage, 0.0) + now - self.stage_t0
            self.stage = event.stage
            self.stage_t0 = now
        self.fraction = max(self.fraction, self._overall(event))
        if now - self.last_cancel_check >= self.cancel_check_s:
            self.last_cancel_check = now
            self.check_cancel()
        if stage_changed or now - self.last_save >= self.interval_s:
            self._save(event, now)

    def _overall(self, event: Progress) -> float:
        """Fraction of the whole run done, from the stage weights (monotonic, < 1)."""
        if event.stage not in self.weights:
            return self.fraction
        done = 0.0
        for stage, weight in self.weights.items():
            if stage == event.stage:
                break
            done += weight
        total = sum(self.weights.values())
        here = self.weights[event.stage] * min(max(event.fraction, 0.0), 1.0)
        return min((done + here) / total, 0.99)

    def _eta(self, event: Progress, now: float) -> float | None:
        """Seconds left for the whole run: from the overall fraction once it means something,
        never less than the stage's own estimate (``event.eta_s``, when given)."""
        elapsed = now - self.t0
        estimate = None
        if self.fraction >= 0.05 and elapsed > 0:
            estimate = elapsed * (1.0 - self.fraction) / self.fraction
        if event.eta_s is not None:
            stage_left = max(float(event.eta_s), 0.0)
            estimate = stage_left if estimate is None else max(estimate, stage_left)
        return estimate

    def _save(self, event: Progress, now: float) -> None:
        self.last_save = now
        losses, metrics = _finite(event.losses), _finite(event.metrics)
        eta = self._eta(event, now)
        if losses or metrics:
            self.history.append(
                {
                    "t": round(now - self.t0, 3),
                    "stage": event.stage,
                    "step": event.step,
                    "losses": losses,
                    "metrics": metrics,
                }
            )
            if len(self.history) > MAX_HISTORY:  # keep the curve's shape, halve the points
                self.history = self.history[::2]
        timings = dict(self.timings)
        timings[event.stage] = timings.get(event.stage, 0.0) + now - self.stage_t0
        meta = self.job.meta
        meta.update(
            state=JobState.RUNNING.value,
            stage=event.stage,
            step=event.step,
            total=event.total,
            message=event.message,
            fraction=round(self.fraction, 4),
            eta_s=None if eta is None else round(eta, 1),
            losses=losses,
            metrics=metrics,
            timings={k: round(v, 3) for k, v in timings.items()},
            history=self.history,
            updated_at=time.time(),
        )
        try:
            self.job.save_meta()
        except REDIS_ERRORS as exc:  # progress is best effort; the run goes on
            log.warning("job %s: progress not saved: %s", self.job.id, exc)
            return
        self.saves += 1
        keys = ("stage", "step", "total", "fraction", "eta_s", "losses", "metrics")
        self._publish("progress", {k: meta[k] for k in keys})
