"""A rich progress bar fed by pbrsr_core.progress events."""

from __future__ import annotations

from contextlib import contextmanager

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TaskID,
    TextColumn,
    TimeRemainingColumn,
)

from ..progress import Progress as Event


@contextmanager
def progress_bar(enabled: bool = True):
    """Yield a callback for ``progress=``; draws one bar per stage."""
    if not enabled:
        yield None
        return
    console = Console(stderr=True)
    with Progress(
        TextColumn("[bold]{task.description:<10}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[info]}"),
        TimeRemainingColumn(),
        console=console,
        transient=False,
    ) as bar:
        tasks: dict[str, TaskID] = {}

        def on_event(ev: Event) -> None:
            if ev.stage not in tasks:
                tasks[ev.stage] = bar.add_task(ev.stage, total=ev.total or None, info="")
            info = "  ".join(f"{k}={v:.4g}" for k, v in list(ev.losses.items())[:3])
            bar.update(tasks[ev.stage], completed=ev.step, total=ev.total or None, info=info)

        yield on_event
