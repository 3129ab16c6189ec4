"""Progress reporting shared by the CLI (a progress bar) and the worker (job.meta).

A long-running function takes ``progress: ProgressFn | None`` and calls it with a
:class:`Progress` at each stage change and between iterations. To cancel, the callback raises
:class:`pbrsr_core.errors.Cancelled`; the run stops there and cleans up.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
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

    def __call__(self, done: float) -> float | None:
        if done <= 0:
            return None
        per = (time.perf_counter() - self.start) / done
        return per * max(self.total - done, 0)


class StageTimer:
    """Wall seconds per named stage, in order."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0


class MapProgress:
    """Progress of a stage that runs the prior over several maps, tile by tile: the fraction
    of all the maps' pixels done (out of ``STEPS``), the map and tile in the message, and an
    ETA from the time per pixel so far."""

    STEPS = 1000

    def __init__(self, progress: ProgressFn | None, stage: str, images) -> None:
        self.progress, self.stage = progress, stage
        self.pixels = {img.index: img.width * img.height for img in images}
        self.before: dict[int, int] = {}
        done = 0
        for img in images:
            self.before[img.index] = done
            done += self.pixels[img.index]
        self.total = max(done, 1)
        self.eta = Eta(self.STEPS)
        emit(progress, Progress(stage=stage, step=0, total=self.STEPS))

    def on(self, img) -> Callable[[int, int], None]:
        """The prior's tile callback for ``img``: ``(tiles done, tiles)``."""

        def tile(done: int, total: int) -> None:
            pixels = self.before[img.index] + self.pixels[img.index] * done / max(total, 1)
            step = self.STEPS * pixels / self.total
            event = Progress(
                stage=self.stage,
                step=int(step),
                total=self.STEPS,
                eta_s=self.eta(step),
                message=f"{img.name}: tile {done}/{total}",
            )
            emit(self.progress, event)

        return tile
