"""The FastAPI application factory: ``uvicorn --factory service.app:create_app``."""

from __future__ import annotations

import logging
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles
from redis import Redis

from pbrsr_core import __version__
from pbrsr_jobs.objstore import open_store
from pbrsr_jobs.settings import Settings, get_settings
from pbrsr_jobs.store import JobFiles

from .problems import install_handlers
from .routes import batches, events, health, jobs, prometheus, vendor, webhooks

STATIC_DIR = Path(__file__).parent / "static"
log = logging.getLogger("pbrsr.service")


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the app. ``settings`` defaults to the environment's (validated here: a bad
    value, an unwritable PBRSR_STORAGE_DIR or an object store that cannot be used stops
    start-up with a clear message: ValueError, StoreUnavailable)."""
    settings = settings or get_settings()
    settings.prepare_storage()
    store = open_store(settings)
    store.check()

    @asynccontextmanager
    async def lifespan(app: FastAPI):  # noqa: ANN202
        yield
        for client in app.state.redis_clients.values():
            client.close()
        for aclient in app.state.async_redis_clients.values():
            await aclient.aclose()

    app = FastAPI(
        title="pbrsr",
        version=__version__,
        summary="PBR texture super-resolution for glTF/GLB assets (PBR-SR) as a job service.",
        docs_url="/docs",
        redoc_url=None,
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.files = JobFiles(store)
    app.state.redis_clients = {}
    app.state.async_redis_clients = {}

    def metrics_redis() -> Redis:
        client = app.state.redis_clients.get(settings.redis_url)
        if client is None:
            client = Redis.from_url(settings.redis_url, socket_connect_timeout=2, socket_timeout=5)
            app.state.redis_clients[settings.redis_url] = client
        return client

    app.state.metrics_redis = metrics_redis

    async def these_settings() -> Settings:  # async: no thread hop per request
        return settings

    app.dependency_overrides[get_settings] = these_settings

    install_handlers(app)
    prometheus.install_metrics(app)
    if settings.cors_origins:
        app.add_middleware(
            CORSMiddleware,
            allow_origins=settings.cors_origins,
            allow_methods=["GET", "POST", "DELETE"],
            allow_headers=["X-API-Key", "Content-Type"],
            expose_headers=["Location"],
        )
    app.include_router(jobs.router)
    app.include_router(batches.router)
    app.include_router(events.router)
    app.include_router(webhooks.router)
    app.include_router(health.router)
    app.include_router(prometheus.router)
    app.include_router(vendor.router)
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")

    @app.get("/", include_in_schema=False)
    def dashboard() -> FileResponse:
        return FileResponse(STATIC_DIR / "index.html", media_type="text/html")

    return app
