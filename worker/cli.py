"""``pbrsr worker``: registered on the ``pbrsr`` typer app through the ``pbrsr.commands``
entry point group."""

from __future__ import annotations

import typer


def register(app: typer.Typer) -> None:
    @app.command("worker")
    def worker_command(
        burst: bool = typer.Option(False, help="Quit when the queue is empty."),
        name: str | None = typer.Option(None, help="Worker name (default: host + random)."),
        max_jobs: int | None = typer.Option(None, min=1, help="Quit after this many jobs."),
    ) -> None:
        """Run a job worker (RQ) on the device and queue from the PBRSR_* settings."""
        from pydantic import ValidationError

        from pbrsr_core.cli.extras import needs_extra

        with needs_extra("worker", "service"):
            from redis.exceptions import ConnectionError as RedisConnectionError

            from pbrsr_jobs.objstore import StoreUnavailable
            from pbrsr_jobs.settings import Settings

            from .runner import run_worker

        try:
            settings = Settings()
        except ValidationError as exc:
            typer.secho(f"error: invalid settings:\n{exc}", fg="red", err=True)
            raise typer.Exit(2) from None
        try:
            run_worker(settings, burst=burst, name=name, max_jobs=max_jobs)
        except ValueError as exc:  # storage not writable
            typer.secho(f"error: {exc}", fg="red", err=True)
            raise typer.Exit(2) from None
        except StoreUnavailable as exc:
            typer.secho(f"error: job storage: {exc}", fg="red", err=True)
            raise typer.Exit(2) from None
        except RedisConnectionError:
            typer.secho(
                "error: cannot reach Redis at PBRSR_REDIS_URL; start it or fix the URL",
                fg="red",
                err=True,
            )
            raise typer.Exit(2) from None
