"""``pbrsr serve``: registered on the ``pbrsr`` typer app through the ``pbrsr.commands``
entry point group."""

from __future__ import annotations

import typer


def register(app: typer.Typer) -> None:
    @app.command("serve")
    def serve_command(
        host: str = typer.Option("127.0.0.1", help="Interface to listen on."),
        port: int = typer.Option(8000, min=1, max=65535, help="Port to listen on."),
        workers: int = typer.Option(1, min=1, help="API processes (uvicorn workers)."),
    ) -> None:
        """Run the job API and the dashboard (settings from PBRSR_* variables)."""
        import logging

        from pydantic import ValidationError

        from pbrsr_core.cli.extras import needs_extra

        with needs_extra("serve", "service"):
            import uvicorn

            import service.app  # noqa: F401  (uvicorn loads it by name)
            from pbrsr_jobs.objstore import StoreUnavailable, open_store
            from pbrsr_jobs.settings import Settings

        try:
            settings = Settings()
            settings.prepare_storage()
        except (ValidationError, ValueError) as exc:
            typer.secho(f"error: invalid settings:\n{exc}", fg="red", err=True)
            raise typer.Exit(2) from None
        try:
            open_store(settings).check()
        except StoreUnavailable as exc:
            typer.secho(f"error: job storage: {exc}", fg="red", err=True)
            raise typer.Exit(2) from None
        logging.basicConfig(
            level=settings.log_level, format="%(asctime)s %(name)s %(levelname)s %(message)s"
        )
        uvicorn.run(
            "service.app:create_app",
            factory=True,
            host=host,
            port=port,
            workers=workers,
            log_level=settings.log_level.lower(),
            proxy_headers=True,
        )
