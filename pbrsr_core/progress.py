"""Progress reporting shared by the CLI (a progress bar) and the worker (job.meta).

A long-running function takes ``progress: ProgressFn | None`` and calls it with a
:class:`Progress` at each stage change and between iterations. To cancel, the callback raises
:class:`pbrsr_core.errors.Cancelled`; the run stops there and cleans up.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field


@dataclass
class Progress:
    stage: str  # e.g. "load", "gbuffers", "prior", "pseudo_gt", "optimize", "export"
    step: int = 0  # iterations (or items) done in this stage
    total: int = 0  # iterations (or items) in this stage; 0 when unknown
    losses: dict[str, float] = field(default_factory=dict)
    metrics: dict[str, float] = field(default_factory=dict)  # e.g. consistency PSNR per map
    eta_s: float | None = None  # seconds left for the whole run, when known
    message: str = ""

    @property
    def fraction(self) -> float:
        return self.step / self.total if self.total else 0.0


ProgressFn = Callable[[Progress], None]


def emit(progress: ProgressFn | None, event: Progress) -> None:
    if progress is not None:
        progress(event)


class Eta:
    """Seconds-left estimate for ``total`` equal steps, from the mean time per step so far."""

    def __init__(self, total: int):
        self.total = total
        self.start = time.perf_counter()

    def __call__(self, done: int) -> float | None:
        if done <= 0:
            return None
        per = (time.perf_counter() - self.start) / done
        return per * max(self.total - done, 0)
