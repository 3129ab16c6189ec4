"""Shared helpers for the service/worker/dashboard tests (this module holds no tests).

Every test run talks to the real Redis at 127.0.0.1:6379, in database ``TEST_REDIS_DB``, with
its own queue name and key prefix (a random tag), and deletes its keys afterwards.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import signal
import subprocess
import sys
import uuid
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from pydantic import SecretStr

from pbrsr_bench.load import free_port, wait_until
from pbrsr_jobs.settings import Settings

REPO = Path(__file__).resolve().parents[1]
TEST_REDIS_DB = 9
REDIS_URL = f"redis://127.0.0.1:6379/{TEST_REDIS_DB}"
PBRSR = str(REPO / ".venv" / "bin" / "pbrsr")
if not Path(PBRSR).exists():  # another venv layout: the console script beside python
    PBRSR = str(Path(sys.executable).with_name("pbrsr"))
LONG_KEY_A = "key-alpha-0123456789abcdef"
LONG_KEY_B = "key-bravo-0123456789abcdef"


def redis_client():
    from redis import Redis

    client = Redis.from_url(REDIS_URL, socket_connect_timeout=1)
    try:
        client.ping()
    except Exception as exc:  # noqa: BLE001
        pytest.fail(f"the service tests need Redis at 127.0.0.1:6379 ({exc})")
    return client


def make_settings(tmp_path: Path, **overrides: Any) -> Settings:
    tag = uuid.uuid4().hex[:10]
    values: dict[str, Any] = {
        "redis_url": REDIS_URL,
        "storage_dir": tmp_path / "storage",
        "queue": f"test-{tag}",
        "key_prefix": f"pbrsr-test-{tag}",
        "preload_priors": [],
        "device": "cpu",
        "worker_threads": 1,  # workers under test stay on one thread, as OMP_NUM_THREADS=1
        "heartbeat_s": 1.0,
        "maintenance_s": 1,
        "progress_interval_s": 0.2,
        "job_retries": 2,
    }
    values.update(overrides)
    return Settings(**values)


def settings_env(settings: Settings) -> dict[str, str]:
    """The PBRSR_* environment that rebuilds ``settings`` in a subprocess."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PBRSR_")}
    for name, value in settings.model_dump().items():
        if value is None:
            continue
        if isinstance(value, SecretStr):
            value = value.get_secret_value()
        if isinstance(value, list):
            value = ",".join(value)
        env[f"PBRSR_{name.upper()}"] = str(value)
    env.setdefault("OMP_NUM_THREADS", "1")
    env["PYTHONUNBUFFERED"] = "1"
    return env


def cleanup_redis(settings: Settings) -> None:
    """Delete every key this test's queue and prefix made (jobs included)."""
    client = redis_client()
    job_ids = [i.decode() for i in client.zrange(f"{settings.key_prefix}:jobs", 0, -1)]
    patterns = [f"{settings.key_prefix}:*", f"*{settings.queue}*"]
    keys: set[bytes] = set()
    for pattern in patterns:
        keys.update(client.scan_iter(match=pattern, count=1000))
    for job_id in job_ids:
        keys.update(client.scan_iter(match=f"rq:*{job_id}*", count=1000))
    if keys:
        client.delete(*keys)


def settings_scope(tmp_path: Path, **overrides: Any) -> Iterator[Settings]:
    """Body of each test module's ``settings`` fixture: fresh names, keys deleted after."""
    s = make_settings(tmp_path, **overrides)
    yield s
    cleanup_redis(s)


def asset_bytes(tmp_path: Path, kind: str = "glb", size: int = 32, **kw: Any) -> bytes:
    from pbrsr_core.asset import make_test_asset

    path = make_test_asset(
        tmp_path / f"src-{uuid.uuid4().hex[:6]}.{kind}", size=size, kind=kind, **kw
    )
    return path.read_bytes()


def gltf_zip_bytes(tmp_path: Path, size: int = 32) -> bytes:
    """A .zip holding a .gltf with its external buffer and image files."""
    from pbrsr_core.asset import make_test_asset

    folder = tmp_path / f"zipsrc-{uuid.uuid4().hex[:6]}"
    folder.mkdir()
    make_test_asset(folder / "scene.gltf", size=size, kind="gltf")
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for path in sorted(folder.rglob("*")):
            if path.is_file():
                zf.write(path, f"model/{path.relative_to(folder).as_posix()}")
    return buf.getvalue()


def post_asset(
    client: Any,
    data: bytes,
    filename: str = "asset.glb",
    options: dict | str | None = None,
    headers: dict | None = None,
) -> Any:
    files = {"file": (filename, data, "application/octet-stream")}
    form = {}
    if options is not None:
        form["options"] = options if isinstance(options, str) else json.dumps(options)
    return client.post("/v1/jobs", files=files, data=form, headers=headers or {})


@contextmanager
def worker_process(
    settings: Settings, log_path: Path, name: str | None = None, extra: list[str] | None = None
) -> Iterator[subprocess.Popen]:
    """A real ``pbrsr worker`` subprocess; stopped (SIGTERM, then SIGKILL) on exit."""
    args = [PBRSR, "worker", *(extra or [])]
    if name:
        args += ["--name", name]
    with open(log_path, "ab") as log:
        proc = subprocess.Popen(
            args, env=settings_env(settings), stdout=log, stderr=subprocess.STDOUT, cwd=REPO
        )
    try:
        yield proc
    finally:
        stop_process(proc)


def stop_process(proc: subprocess.Popen, timeout: float = 10) -> None:
    if proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=5)


@contextmanager
def api_server(settings: Settings, log_path: Path) -> Iterator[str]:
    """A real ``pbrsr serve`` on a free localhost port; yields its base URL."""
    import httpx

    port = free_port()
    with open(log_path, "ab") as log:
        proc = subprocess.Popen(
            [PBRSR, "serve", "--host", "127.0.0.1", "--port", str(port)],
            env=settings_env(settings),
            stdout=log,
            stderr=subprocess.STDOUT,
            cwd=REPO,
        )
    base = f"http://127.0.0.1:{port}"
    try:

        def up() -> bool:
            if proc.poll() is not None:
                raise AssertionError(f"pbrsr serve exited: {log_path.read_text()[-2000:]}")
            try:
                return httpx.get(base + "/healthz", timeout=1).status_code == 200
            except httpx.HTTPError:
                return False

        wait_until(up, 30, "the API to start", 0.2)
        yield base
    finally:
        stop_process(proc)


def require_redis_server() -> None:
    """The benchmarks start a private redis-server (scripts/test makes sure Redis is there):
    without the binary a test fails, saying so, rather than pass unrun."""
    if shutil.which("redis-server") is None:
        pytest.fail("redis-server is not installed (Debian's redis-server package)")
