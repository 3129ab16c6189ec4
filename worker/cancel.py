"""Cancellation that does not wait for the pipeline's next progress call.

The cooperative path (``JobReporter`` raising ``Cancelled`` from the progress callback) stops
a run between optimizer iterations. Some stages call back rarely (rendering previews,
building G-buffers for many views), so while the pipeline runs a :class:`CancelWatchdog`
thread also polls the job's cancel flag and, once it has been set for ``grace_s``, raises
:class:`JobCancelled` in the job's thread (``PyThreadState_SetAsyncExc``, the mechanism RQ's
own job timeouts rely on, there through a signal). The exception arrives at the thread's next
Python bytecode - after the C call it is in (a torch op, a numba kernel) returns - and
unwinds through the pipeline's ``finally`` blocks like any error, so temporary files are
removed and memory is freed.

The watchdog is armed only around the pipeline call: on leaving, under the same lock the
watchdog fires with, it is disarmed and any exception not yet delivered is cleared, so none
can land in the job's bookkeeping afterwards.
"""

from __future__ import annotations

import ctypes
import logging
import threading
from typing import Any

from pbrsr_core.errors import Cancelled

log = logging.getLogger("pbrsr.worker")


class JobCancelled(Cancelled):
    """``Cancelled`` with a default message (an async exception is raised as a bare class)."""

    def __init__(self, message: str = "the job was canceled"):
        super().__init__(message)


def _set_async_exc(thread_id: int, exc: type[BaseException] | None) -> int:
    return ctypes.pythonapi.PyThreadState_SetAsyncExc(
        ctypes.c_ulong(thread_id), ctypes.py_object(exc) if exc is not None else None
    )


class CancelWatchdog:
    """Context manager: while inside, a set cancel flag interrupts the current thread."""

    def __init__(self, index: Any, job_id: str, *, poll_s: float = 0.25, grace_s: float = 0.5):
        self.index = index
        self.job_id = job_id
        self.poll_s = poll_s
        self.grace_s = grace_s
        self.fired = False
        self._lock = threading.Lock()
        self._armed = False
        self._stop = threading.Event()
        self._target = threading.get_ident()
        self._thread: threading.Thread | None = None

    def __enter__(self) -> CancelWatchdog:
        self._target = threading.get_ident()
        self._armed = True
        self._thread = threading.Thread(target=self._run, name="pbrsr-cancel", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        with self._lock:
            self._armed = False
            if self.fired:
                _set_async_exc(self._target, None)  # drop it if not delivered yet
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)

    def _run(self) -> None:
        seen_for = 0.0
        while not self._stop.wait(self.poll_s):
            try:
                requested = self.index.cancel_requested(self.job_id)
            except Exception as exc:  # noqa: BLE001 - Redis blip: try again next poll
                log.debug("cancel poll failed: %s", exc)
                continue
            seen_for = seen_for + self.poll_s if requested else 0.0
            if seen_for >= self.grace_s:
                with self._lock:
                    if self._armed and not self.fired:
                        self.fired = True
                        _set_async_exc(self._target, JobCancelled)
                        log.info("job %s: interrupting for cancellation", self.job_id)
                return
