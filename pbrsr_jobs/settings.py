"""Every ``PBRSR_*`` environment variable of the service and the workers, in one place.

``Settings`` is read from the environment (and an optional ``.env`` file) by pydantic-settings
and validated when it is built, so a bad value stops ``pbrsr serve`` / ``pbrsr worker`` at
start-up with a message naming the variable. The API takes it through the
:func:`get_settings` dependency (cached; tests override it), the worker builds it once.
docs/SERVICE.md has the table of every variable; keep the two in step (a test checks).
"""

from __future__ import annotations

import os
import re
from functools import lru_cache
from pathlib import Path
from typing import Annotated, Literal
from urllib.parse import urlsplit

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from pbrsr_core import runtime
from pbrsr_core.cli.environment import configure_from_env
from pbrsr_core.limits import Limits
from pbrsr_core.options import DEFAULT_PRIOR

_MB = 1024 * 1024
PRIORITIES = ("high", "normal", "low")
"""Job priorities, each its own set of RQ queues that workers drain in this order."""
_DEVICE_RE = re.compile(r"^(auto|cpu|cuda|cuda:\d+)$")
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


def _default_storage() -> Path:
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "pbrsr"


def _split_csv(value: object) -> object:
    """``"a, b,,c"`` -> ``["a", "b", "c"]``; lists pass through; ``""``/None -> ``[]``."""
    if value is None:
        return []
    if isinstance(value, str):
        return [part.strip() for part in value.split(",") if part.strip()]
    return value


class Settings(BaseSettings):
    """Configuration of the job service and its workers (env prefix ``PBRSR_``)."""

    model_config = SettingsConfigDict(
        env_prefix="PBRSR_", env_file=".env", extra="ignore", case_sensitive=False
    )

    # -- where things live --------------------------------------------------------------
    redis_url: str = Field("redis://127.0.0.1:6379/0", description="Redis for the job queue.")
    storage_dir: Path = Field(
        default_factory=_default_storage,
        description="Root of job storage (jobs/<id>/input, output, result.zip); a shared "
        "NFS path when API and workers run on different machines. With the s3 backend: "
        "this machine's scratch space (uploads while they stream, a job's working folder).",
    )
    storage_backend: Literal["filesystem", "s3"] = Field(
        "filesystem",
        description="Where the files API and workers share live: 'filesystem' (under "
        "PBRSR_STORAGE_DIR) or 's3' (an S3-compatible bucket; PBRSR_STORAGE_DIR is then each "
        "machine's own scratch space).",
    )
    s3_endpoint_url: str | None = Field(
        None, description="S3 endpoint, http(s)://host[:port] (e.g. https://s3.eu-west-1."
        "amazonaws.com, http://minio:9000); required with the s3 backend."
    )  # fmt: skip
    s3_public_url: str | None = Field(
        None,
        description="The endpoint as clients reach it, when not PBRSR_S3_ENDPOINT_URL (e.g. "
        "the API and workers use http://minio:9000 inside a cluster, clients "
        "https://files.example.com): presigned URLs are made for it. Unset = the endpoint.",
    )
    s3_bucket: str | None = Field(
        None, description="Bucket of the job files; must exist. Required with the s3 backend."
    )
    s3_region: str = Field("us-east-1", description="The bucket's region (used to sign).")
    s3_access_key: SecretStr | None = Field(None, description="S3 access key id.")
    s3_secret_key: SecretStr | None = Field(None, description="S3 secret access key.")
    s3_key_prefix: str = Field(
        "", description="Prefix of every object key (e.g. 'pbrsr/'), to share a bucket."
    )
    s3_presign_expiry_s: int = Field(
        900,
        ge=1,
        le=7 * 86400,
        description="Seconds a presigned download URL (the 307 of a result, preview or "
        "thumbnail) stays valid.",
    )
    s3_path_style: bool = Field(
        True,
        description="Path-style addressing (endpoint/bucket/key), as MinIO and most "
        "self-hosted servers need; false = virtual-hosted (bucket.endpoint/key).",
    )
    queue: str = Field("pbrsr", description="RQ queue name (workers and API must agree).")
    large_job_mpix: float = Field(
        0.0,
        ge=0.0,
        description="Jobs whose output maps add up to at least this many megapixels go to the "
        "queue '<PBRSR_QUEUE>-large' (for big GPU workers); 0 = one queue for every job.",
    )
    worker_queues: str = Field(
        "all",
        pattern="^(all|small|large)$",
        description="Queues a worker takes jobs from: all (small first), small or large.",
    )
    key_prefix: str = Field(
        "pbrsr", description="Prefix of pbrsr's own Redis keys (job index, cancel flags)."
    )
    cache_dir: Path | None = Field(
        None, description="Converted prior weights, BRDF table and prefiltered lights."
    )
    npm_dir: Path | None = Field(None, description="node_modules holding the TF.js prior.")
    models_dir: Path | None = Field(
        None,
        description="Folder of extra prior weights a job may name as 'spandrel:<file>', "
        "'diffusion:<folder>' or 'texture:<folder>' (a set pbrsr priors train|finetune wrote); "
        "unset = only built-in priors.",
    )
    envmap_dir: Path | None = Field(
        None,
        description="Folder of environment maps a job may name (options.envmap = file name); "
        "unset = only the built-in procedural environment.",
    )

    # -- worker ----------------------------------------------------------------------------
    device: str = Field("auto", description="Worker device: auto, cpu, cuda or cuda:N.")
    worker_memory_mb: int = Field(
        0,
        ge=0,
        description="Memory one job may use (MiB); a job estimated above it is refused as "
        "limit-exceeded before it starts. 0 = what the machine has free when the job starts.",
    )
    job_timeout: int = Field(6 * 3600, ge=10, description="Seconds one job may run.")
    job_retries: int = Field(
        2, ge=0, le=10, description="Retries of a job whose worker died (killed, OOM)."
    )
    heartbeat_s: float = Field(
        10.0,
        gt=0,
        description="Worker heartbeat period during a job; a job whose worker is silent for "
        "3 periods is abandoned and retried by another worker.",
    )
    maintenance_s: int = Field(
        30,
        ge=1,
        description="How often an idle worker recovers abandoned jobs and expires old ones.",
    )
    progress_interval_s: float = Field(
        1.0, gt=0, description="Least seconds between two progress writes to job.meta."
    )
    preload_priors: Annotated[list[str], NoDecode] = Field(
        default_factory=lambda: [DEFAULT_PRIOR],
        description="Priors a worker loads at start (comma-separated; empty = none).",
    )
    worker_threads: int = Field(
        0,
        ge=0,
        description="Threads of one worker (torch and numba); 0 = the cores this process may "
        "use (CPU affinity, cgroup quota) divided among the workers on this host.",
    )
    workers_per_host: int = Field(
        0,
        ge=0,
        description="Workers that share this host's cores when PBRSR_WORKER_THREADS is 0; "
        "0 = count the live workers of this queue on this host in Redis.",
    )
    log_level: str = Field("INFO", description="Logging level of API and workers.")

    # -- API -------------------------------------------------------------------------------
    api_keys: Annotated[list[str], NoDecode] = Field(
        default_factory=list,
        description="Comma-separated API keys; empty = no authentication. With keys, each "
        "key sees only its own jobs.",
    )
    cors_origins: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="Comma-separated CORS origins; empty = CORS off."
    )
    retention_hours: float = Field(
        72.0, gt=0, description="Hours a finished, failed or canceled job is kept."
    )
    page_size_max: int = Field(100, ge=1, le=1000, description="Largest page of GET /v1/jobs.")
    idempotency_ttl_s: int = Field(
        86400,
        ge=60,
        description="Seconds an Idempotency-Key of POST /v1/jobs is remembered (per API key).",
    )
    max_active_jobs_per_key: int = Field(
        0,
        ge=0,
        description="Queued and running jobs one API key may have; a submission over it is 429 "
        "with Retry-After. 0 = no limit.",
    )
    max_queued_jobs: int = Field(
        0,
        ge=0,
        description="Jobs waiting in all queues together; a submission over it is 503 with "
        "Retry-After. 0 = no limit.",
    )
    max_batch_files: int = Field(
        100, ge=1, le=10_000, description="Most files (jobs) in one POST /v1/batches."
    )

    # -- webhooks (pbrsr_jobs.webhooks) -------------------------------------------------
    webhook_secret: str | None = Field(
        None,
        description="Server secret each API key's webhook signing secret derives from; unset "
        "= one made once and kept in Redis.",
    )
    webhook_timeout_s: float = Field(10.0, gt=0, le=120, description="Seconds per delivery.")
    webhook_max_attempts: int = Field(
        6, ge=1, le=20, description="Deliveries of one event before it is given up."
    )
    webhook_backoff_s: float = Field(
        2.0, gt=0, description="Wait before the first retry; doubled for each next one."
    )

    # -- input limits (pbrsr_core.limits.Limits) ------------------------------------------
    max_upload_mb: float = Field(512, gt=0, description="Largest upload (refused while streaming).")
    max_triangles: int = Field(2_000_000, ge=1, description="Most triangles in one asset.")
    max_texture_dim: int = Field(8192, ge=1, description="Largest input texture side (px).")
    max_output_dim: int = Field(16384, ge=1, description="Largest output texture side (px).")
    max_data_uri_mb: float = Field(64, gt=0, description="Largest data: URI in a .gltf.")
    max_zip_entries: int = Field(1000, ge=1, description="Most entries in an uploaded zip.")
    max_unpacked_mb: float = Field(
        1024, gt=0, description="Most bytes a zip may unpack to (the files the asset uses)."
    )
    max_compression_ratio: float = Field(
        200,
        ge=1,
        description="Highest uncompressed/compressed size ratio of a zip entry the asset uses, "
        "and of all of them against the zip's size.",
    )

    # -- validation --------------------------------------------------------------------
    @field_validator("api_keys", "cors_origins", "preload_priors", mode="before")
    @classmethod
    def _csv(cls, value: object) -> object:
        return _split_csv(value)

    @field_validator("device")
    @classmethod
    def _device(cls, value: str) -> str:
        value = value.strip().lower()
        if not _DEVICE_RE.match(value):
            raise ValueError(f"{value!r} is not a device: use auto, cpu, cuda or cuda:N")
        return value

    @field_validator("redis_url")
    @classmethod
    def _redis_url(cls, value: str) -> str:
        if not value.startswith(("redis://", "rediss://", "unix://")):
            raise ValueError("must start with redis://, rediss:// or unix://")
        return value

    @field_validator("s3_endpoint_url", "s3_public_url")
    @classmethod
    def _endpoint(cls, value: str | None) -> str | None:
        if value is None or not value.strip():
            return None
        parts = urlsplit(value.strip())
        if parts.scheme not in ("http", "https") or not parts.netloc:
            raise ValueError("must be http(s)://host[:port]")
        if parts.path.strip("/") or parts.query:
            raise ValueError("must be http(s)://host[:port] without a path (the bucket is "
                             "PBRSR_S3_BUCKET)")  # fmt: skip
        return f"{parts.scheme}://{parts.netloc}"

    @field_validator("s3_key_prefix")
    @classmethod
    def _key_prefix(cls, value: str) -> str:
        value = value.strip("/")
        if value and not re.match(r"^[A-Za-z0-9][A-Za-z0-9_./-]{0,199}$", value) or ".." in value:
            raise ValueError("use letters, digits, '.', '_', '-' and '/' (at most 200)")
        return value + "/" if value else ""

    @model_validator(mode="after")
    def _backend(self) -> Settings:
        if self.storage_backend == "s3" and not (self.s3_endpoint_url and self.s3_bucket):
            raise ValueError(
                "PBRSR_STORAGE_BACKEND=s3 needs PBRSR_S3_ENDPOINT_URL and PBRSR_S3_BUCKET"
            )
        return self

    @field_validator("queue", "key_prefix")
    @classmethod
    def _name(cls, value: str) -> str:
        if not _NAME_RE.match(value):
            raise ValueError(f"{value!r}: use letters, digits, '.', '_' or '-' (at most 64)")
        return value

    @field_validator("api_keys")
    @classmethod
    def _keys(cls, value: list[str]) -> list[str]:
        for key in value:
            if len(key) < 16:
                raise ValueError("every API key must be at least 16 characters long")
        return value

    @field_validator("cors_origins")
    @classmethod
    def _origins(cls, value: list[str]) -> list[str]:
        for origin in value:
            if origin != "*" and not origin.startswith(("http://", "https://")):
                raise ValueError(f"CORS origin {origin!r} must be '*' or start with http(s)://")
        return value

    @field_validator("log_level")
    @classmethod
    def _level(cls, value: str) -> str:
        value = value.upper()
        if value not in {"DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"}:
            raise ValueError("use DEBUG, INFO, WARNING, ERROR or CRITICAL")
        return value

    # -- derived -------------------------------------------------------------------------
    def limits(self) -> Limits:
        """The input limits every upload and job is held to."""
        return Limits(
            max_file_bytes=int(self.max_upload_mb * _MB),
            max_triangles=self.max_triangles,
            max_texture_dim=self.max_texture_dim,
            max_output_dim=self.max_output_dim,
            max_data_uri_bytes=int(self.max_data_uri_mb * _MB),
            max_zip_entries=self.max_zip_entries,
            max_unpacked_bytes=int(self.max_unpacked_mb * _MB),
            max_compression_ratio=self.max_compression_ratio,
        )

    @property
    def large_queue(self) -> str:
        """The queue of jobs at or over ``large_job_mpix``."""
        return f"{self.queue}-large"

    def queue_for(self, output_mpix: float, priority: str = "normal") -> str:
        """The queue a job with ``output_mpix`` megapixels of output maps and ``priority``
        (high, normal, low) goes to: ``<queue>[-large][-high|-low]``."""
        base = self.queue
        if self.large_job_mpix > 0 and output_mpix >= self.large_job_mpix:
            base = self.large_queue
        return base if priority == "normal" else f"{base}-{priority}"

    def listen_queues(self, which: str | None = None) -> list[str]:
        """Queue names a worker listens on, in the order it takes jobs: every high-priority
        queue first, then normal, then low; within one priority, small jobs first."""
        which = which or self.worker_queues
        bases = {
            "all": [self.queue, self.large_queue],
            "small": [self.queue],
            "large": [self.large_queue],
        }[which]
        return [b if p == "normal" else f"{b}-{p}" for p in PRIORITIES for b in bases]

    @property
    def retention_s(self) -> int:
        return int(self.retention_hours * 3600)

    @property
    def auth_enabled(self) -> bool:
        return bool(self.api_keys)

    def prepare_storage(self) -> Path:
        """Create the storage root and check it is writable (start-up check).

        Raises ``ValueError`` naming PBRSR_STORAGE_DIR when it cannot be used.
        """
        root = self.storage_dir.expanduser()
        try:
            (root / "jobs").mkdir(parents=True, exist_ok=True)
            (root / "uploads").mkdir(parents=True, exist_ok=True)
            probe = root / f".write-probe-{os.getpid()}"
            probe.write_bytes(b"ok")
            probe.unlink()
        except OSError as exc:
            raise ValueError(
                f"PBRSR_STORAGE_DIR is not a writable folder ({exc.strerror or exc})"
            ) from None
        return root

    def configure_runtime(self) -> None:
        """Install the core's runtime settings for this process: the ``PBRSR_*`` tuning
        variables (:mod:`pbrsr_core.cli.environment`), then this configuration's cache and npm
        folders."""
        configure_from_env()
        folders = {"cache_dir": self.cache_dir, "npm_dir": self.npm_dir}
        runtime.configure(**{k: v for k, v in folders.items() if v is not None})


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process's settings (built once). FastAPI dependency; tests override it."""
    return Settings()
