"""``pbrsr bench load``: the job service under load, with real processes on loopback.

One API process (``python -m pbrsr_core serve`` on 127.0.0.1 and a free port) and, for the
last phase, ``workers`` worker processes (``python -m pbrsr_core worker``), all pointed at a
private Redis (a ``redis-server`` started on a free loopback port when one is installed, else
``redis_url`` with a random queue and key prefix whose keys are deleted afterwards) and a
temporary storage folder. This module talks to them over HTTP only (httpx); it never imports
``service`` or ``worker``.

Phases (each bounded in count and time; the run stops by itself):

a. ``poll_only``: ``pollers`` clients alone loop on ``GET /v1/jobs/{id}``, ``GET /v1/jobs``
   and ``GET /healthz`` (the floor any request pays; the status reads' p50 are reported as
   multiples of its p50 in the same phase, against ``RATIO_TARGETS``) for ``baseline``
   seconds; then ``mixed``: the same pollers while ``uploaders`` clients loop on
   ``POST /v1/jobs`` with small procedural assets, for ``duration`` seconds (no worker runs:
   the API alone is measured). Every answer that is not the expected status (200, 202)
   and every transport error or timeout is an error.
b. ``big uploads``: ``uploaders`` concurrent clients post ``big_uploads`` GLBs of about
   ``upload_mb`` MB (a valid asset whose base colour is a noise texture, so it passes intake);
   time until the intake answer, MB/s per upload and aggregate.
   The jobs of a and b are then canceled and deleted through the API (counted as requests).
c. ``drain``: ``jobs`` small bicubic jobs are submitted and drained by ``workers`` worker
   processes (started and idle before the clock starts); finished must equal submitted.
   Meanwhile every job is followed on its own event stream and on the key's stream (opened
   before the first submission), and its webhooks (every event but progress) go to a
   receiver in this process that checks their signatures (:mod:`pbrsr_bench.events`):
   events received and lost per channel, and the latency from each event's timestamp to its
   receipt. A lost event or a bad signature fails the run.

``run(...)`` returns a JSON-able dict (also written to ``out_dir/load.json``), ``print_table``
prints it with rich, and ``load.png`` plots latency distributions and the drain curve.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pbrsr_core.errors import PbrsrError

OK_STATUS = {"healthz": 200, "get_job": 200, "list_jobs": 200, "upload": 202, "big_upload": 202}
# status reads against /healthz's p50 in the same phase: (request, phase) -> most allowed
RATIO_TARGETS = {
    ("get_job", "poll_only"): 2.0,
    ("get_job", "mixed"): 4.0,
    ("list_jobs", "poll_only"): 3.0,
    ("list_jobs", "mixed"): 3.0,
}
_MB = 1024 * 1024
_TERMINAL = ("finished", "failed", "canceled")


class LoadBenchError(PbrsrError):
    """The load benchmark could not set up its processes."""

    code = "bench-load"
    exit_code = 1


# ----------------------------------------------------------------------------- processes
def free_port() -> int:
    """A free TCP port on 127.0.0.1 (bound then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def stop_process(proc: subprocess.Popen, timeout: float = 10.0) -> None:
    """SIGTERM the process group ``proc`` leads, then SIGKILL it after ``timeout`` s."""
    if proc.poll() is not None:
        return
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=5)


def _popen(args: list[str], env: dict[str, str], log_path: Path) -> subprocess.Popen:
    with open(log_path, "ab") as log:
        return subprocess.Popen(
            args,
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,  # its own process group: stop_process ends all of it
        )


def wait_until(
    predicate: Callable[[], Any], timeout: float, what: str, interval: float = 0.1
) -> Any:
    """``predicate()``'s first truthy value, asked every ``interval`` s; LoadBenchError naming
    ``what`` after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise LoadBenchError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(interval)


@dataclass
class ServiceStack:
    """The processes of one run and how to reach them."""

    redis_url: str
    storage: Path
    queue: str
    prefix: str
    log_dir: Path
    base_url: str = ""
    procs: list[subprocess.Popen] = field(default_factory=list)
    workers: list[subprocess.Popen] = field(default_factory=list)
    private_redis: bool = False

    def env(self) -> dict[str, str]:
        env = {k: v for k, v in os.environ.items() if not k.startswith("PBRSR_")}
        env.update(
            PBRSR_REDIS_URL=self.redis_url,
            PBRSR_STORAGE_DIR=str(self.storage),
            PBRSR_QUEUE=self.queue,
            PBRSR_KEY_PREFIX=self.prefix,
            PBRSR_PRELOAD_PRIORS="",
            PBRSR_DEVICE="cpu",
            PBRSR_LOG_LEVEL="WARNING",
            PBRSR_PROGRESS_INTERVAL_S="0.5",
            PBRSR_HEARTBEAT_S="2",
            PBRSR_MAINTENANCE_S="5",
            PYTHONUNBUFFERED="1",
        )
        env.setdefault("OMP_NUM_THREADS", "1")
        if "PBRSR_CACHE_DIR" in os.environ:
            env["PBRSR_CACHE_DIR"] = os.environ["PBRSR_CACHE_DIR"]
        return env

    def start_api(self, timeout: float = 60.0) -> str:
        import httpx

        port = free_port()
        args = [sys.executable, "-m", "pbrsr_core", "serve", "--host", "127.0.0.1"]
        proc = _popen([*args, "--port", str(port)], self.env(), self.log_dir / "api.log")
        self.procs.append(proc)
        base = f"http://127.0.0.1:{port}"

        def ready() -> bool:
            if proc.poll() is not None:
                raise LoadBenchError(f"the API exited; see {self.log_dir / 'api.log'}")
            try:
                return httpx.get(base + "/readyz", timeout=2).status_code == 200
            except httpx.HTTPError:
                return False

        wait_until(ready, timeout, "the API to be ready", 0.2)
        self.base_url = base
        return base

    def start_workers(
        self, n: int, timeout: float = 120.0, env: dict[str, str] | None = None
    ) -> None:
        """Start ``n`` worker processes (``env``: settings over :meth:`env`'s) and wait until
        every worker of the stack is registered."""
        tag = uuid.uuid4().hex[:6]
        first = len(self.workers)
        for i in range(first, first + n):
            args = [sys.executable, "-m", "pbrsr_core", "worker", "--name", f"load-{tag}-{i}"]
            proc = _popen(args, {**self.env(), **(env or {})}, self.log_dir / f"worker-{i}.log")
            self.procs.append(proc)
            self.workers.append(proc)
        wanted = len(self.workers)

        def registered() -> bool:
            for i, p in enumerate(self.workers):
                if p.poll() is not None:
                    raise LoadBenchError(f"worker {i} exited; see {self.log_dir}/worker-{i}.log")
            return self.registered_workers() >= wanted

        wait_until(registered, timeout, f"{wanted} workers to register", 0.25)

    def registered_workers(self) -> int:
        """Workers registered in Redis, as the API's ``/metrics`` counts them."""
        import httpx

        return int(_gauge(httpx.get(self.base_url + "/metrics", timeout=5).text, "pbrsr_workers"))

    def stop_workers(self, timeout: float = 60.0) -> None:
        """Stop every worker (warm shutdown) and wait until none is registered."""
        for proc in self.workers:
            stop_process(proc)
            self.procs.remove(proc)
        self.workers.clear()
        wait_until(
            lambda: self.registered_workers() == 0, timeout, "the workers to unregister", 0.25
        )

    def close(self) -> None:
        for proc in reversed(self.procs):
            stop_process(proc)
        self.procs.clear()


def _gauge(metrics_text: str, name: str) -> float:
    for line in metrics_text.splitlines():
        if line.startswith(name + " "):
            return float(line.split()[1])
    return 0.0


def _start_private_redis(log_dir: Path) -> tuple[subprocess.Popen, str] | None:
    exe = shutil.which("redis-server")
    if exe is None:
        return None
    from redis import Redis

    port = free_port()
    args = [exe, "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no"]
    proc = _popen(args, dict(os.environ), log_dir / "redis.log")
    client = Redis(host="127.0.0.1", port=port, socket_connect_timeout=0.5)

    def up() -> bool:
        if proc.poll() is not None:
            raise LoadBenchError(f"redis-server exited; see {log_dir / 'redis.log'}")
        try:
            return bool(client.ping())
        except Exception:  # noqa: BLE001 - not up yet
            return False

    try:
        wait_until(up, 15, "redis-server to start", 0.05)
    except BaseException:
        stop_process(proc)
        raise
    return proc, f"redis://127.0.0.1:{port}/0"


def _delete_keys(redis_url: str, queue: str, prefix: str, job_ids: list[str]) -> None:
    """Remove every key this run made in a shared Redis (its queue, prefix and jobs)."""
    from redis import Redis

    client = Redis.from_url(redis_url, socket_connect_timeout=2)
    keys: set[bytes] = set()
    for pattern in (f"{prefix}:*", f"*{queue}*"):
        keys.update(client.scan_iter(match=pattern, count=1000))
    for job_id in job_ids:
        keys.update(client.scan_iter(match=f"rq:*{job_id}*", count=1000))
    keys_list = list(keys)
    for start in range(0, len(keys_list), 500):
        client.delete(*keys_list[start : start + 500])


@contextlib.contextmanager
def service_stack(work_dir: Path, redis_url: str | None = None) -> Iterator[ServiceStack]:
    """Private Redis (unless ``redis_url``), temporary storage, an API; all stopped on exit."""
    log_dir = work_dir / "logs"
    log_dir.mkdir(parents=True, exist_ok=True)
    tag = uuid.uuid4().hex[:10]
    redis_proc = None
    if redis_url is None:
        started = _start_private_redis(log_dir)
        if started is None:
            redis_url = "redis://127.0.0.1:6379/13"
        else:
            redis_proc, redis_url = started
    stack = ServiceStack(
        redis_url=redis_url,
        storage=work_dir / "storage",
        queue=f"load-{tag}",
        prefix=f"pbrsr-load-{tag}",
        log_dir=log_dir,
        private_redis=redis_proc is not None,
    )
    try:
        stack.start_api()
        yield stack
    finally:
        stack.close()
        if redis_proc is not None:
            stop_process(redis_proc)
        else:
            with contextlib.suppress(Exception):
                _delete_keys(stack.redis_url, stack.queue, stack.prefix, [])


# ----------------------------------------------------------------------------- payloads
def small_payloads(folder: Path, n: int = 4, size: int = 32) -> list[tuple[str, bytes]]:
    """``n`` small procedural assets (test and demo assets, GLB and .gltf-less) as bytes."""
    from pbrsr_core.asset import make_demo_asset, make_test_asset

    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for i in range(n):
        path = folder / f"small-{i}.glb"
        if i % 2 == 0:
            make_test_asset(path, size=size + 8 * (i // 2), kind="glb")
        else:
            make_demo_asset(path, size=size)
        out.append((path.name, path.read_bytes()))
    return out


def big_payload(folder: Path, target_mb: float, seed: int = 0) -> tuple[str, bytes]:
    """A valid GLB of about ``target_mb`` MB: the demo asset with its base colour replaced by
    an RGB noise texture (PNG cannot compress noise, so the size is predictable)."""
    from pbrsr_core.asset import load_asset, make_demo_asset, save_asset

    folder.mkdir(parents=True, exist_ok=True)
    src = make_demo_asset(folder / "big-src.glb", size=16)
    asset = load_asset(src)
    index = next(
        (im.index for im in asset.images if "baseColor" in im.roles or "base_color" in im.roles),
        asset.images[0].index,
    )
    channels = asset.images[index].channels
    side = max(16, int(np.sqrt(target_mb * _MB / channels)))
    rng = np.random.default_rng(seed)
    noise = rng.integers(0, 256, size=(side, side, channels), dtype=np.uint8)
    pixels = noise.astype(np.float32) / 255.0
    out = folder / "big.glb"
    save_asset(asset, out, new_images={index: pixels})
    return out.name, out.read_bytes()


# ----------------------------------------------------------------------------- measuring
@dataclass
class Recorder:
    """Latencies (s) per request kind, and every error as (kind, description)."""

    latencies: dict[str, list[float]] = field(default_factory=dict)
    errors: list[tuple[str, str]] = field(default_factory=list)
    sizes: dict[str, list[int]] = field(default_factory=dict)

    def ok(self, kind: str, seconds: float, nbytes: int = 0) -> None:
        self.latencies.setdefault(kind, []).append(seconds)
        if nbytes:
            self.sizes.setdefault(kind, []).append(nbytes)

    def error(self, kind: str, what: str) -> None:
        self.errors.append((kind, what))

    def summary(self, wall_s: float) -> dict[str, dict[str, Any]]:
        kinds = sorted(set(self.latencies) | {k for k, _ in self.errors})
        out = {}
        for kind in kinds:
            lat = np.asarray(self.latencies.get(kind, []), dtype=np.float64)
            n_err = sum(1 for k, _ in self.errors if k == kind)
            row: dict[str, Any] = {
                "requests": int(lat.size + n_err),
                "errors": n_err,
                "per_s": float((lat.size + n_err) / wall_s) if wall_s > 0 else 0.0,
                "p50_ms": float(np.percentile(lat, 50) * 1e3) if lat.size else None,
                "p99_ms": float(np.percentile(lat, 99) * 1e3) if lat.size else None,
                "max_ms": float(lat.max() * 1e3) if lat.size else None,
            }
            sizes = self.sizes.get(kind)
            if sizes and lat.size:
                mb = np.asarray(sizes, dtype=np.float64) / _MB
                row["mb_each"] = float(mb.mean())
                row["mb_per_s_each_p50"] = float(np.percentile(mb / lat, 50))
                row["mb_per_s_total"] = float(mb.sum() / wall_s) if wall_s > 0 else 0.0
            out[kind] = row
        return out


async def _request(
    rec: Recorder,
    kind: str,
    call: Any,
    expect: int | tuple[int, ...],
    nbytes: int = 0,
) -> Any:
    """Time ``await call`` (a request coroutine, not yet started); record a success (status
    in ``expect``) or an error."""
    import httpx

    expect = (expect,) if isinstance(expect, int) else expect
    t0 = time.perf_counter()
    try:
        resp = await call
    except httpx.HTTPError as exc:
        rec.error(kind, f"{type(exc).__name__}: {exc}")
        return None
    dt = time.perf_counter() - t0
    if resp.status_code not in expect:
        rec.error(kind, f"HTTP {resp.status_code}: {resp.text[:200]}")
        return None
    rec.ok(kind, dt, nbytes)
    return resp


def upload_request(
    client: Any, payload: tuple[str, bytes], options: dict, fields: dict[str, str] | None = None
) -> Any:
    """The multipart POST /v1/jobs of ``payload`` (not yet awaited with an async client);
    ``fields``: more form fields (``callback_url``, ...)."""
    name, data = payload
    files = {"file": (name, data, "application/octet-stream")}
    form = {"options": json.dumps(options), **(fields or {})}
    return client.post("/v1/jobs", files=files, data=form)


async def _mixed_phase(
    base: str,
    duration: float,
    pollers: int,
    uploaders: int,
    payloads: list[tuple[str, bytes]],
    ids: list[str],
    rec: Recorder,
    timeout: float,
) -> float:
    import httpx

    limits = httpx.Limits(max_connections=pollers + uploaders + 4, max_keepalive_connections=None)
    rng = random.Random(0)
    options = {"method": "bicubic", "scale": 2}
    async with httpx.AsyncClient(base_url=base, timeout=timeout, limits=limits) as client:
        t_end = time.monotonic() + duration

        async def poller(i: int) -> None:
            n = i
            while time.monotonic() < t_end:
                if n % 3 == 0:
                    job_id = rng.choice(ids)
                    await _request(rec, "get_job", client.get(f"/v1/jobs/{job_id}"), 200)
                elif n % 3 == 1:
                    await _request(rec, "list_jobs", client.get("/v1/jobs?limit=20"), 200)
                else:  # the floor a request pays on this server at this load
                    await _request(rec, "healthz", client.get("/healthz"), 200)
                n += 1

        async def uploader(i: int) -> None:
            n = i
            while time.monotonic() < t_end:
                payload = payloads[n % len(payloads)]
                resp = await _request(
                    rec, "upload", upload_request(client, payload, options), 202, len(payload[1])
                )
                if resp is not None:
                    ids.append(resp.json()["id"])
                n += 1

        t0 = time.perf_counter()
        await asyncio.gather(
            *(poller(i) for i in range(pollers)), *(uploader(i) for i in range(uploaders))
        )
        return time.perf_counter() - t0


async def _upload_phase(
    base: str,
    uploaders: int,
    count: int,
    payload: tuple[str, bytes],
    ids: list[str],
    rec: Recorder,
    kind: str = "big_upload",
) -> float:
    """``count`` uploads of ``payload``, ``uploaders`` at a time; new job ids go to ``ids``."""
    import httpx

    options = {"method": "bicubic", "scale": 2}
    queue = list(range(count))
    async with httpx.AsyncClient(base_url=base, timeout=300) as client:

        async def uploader() -> None:
            while queue:
                queue.pop()
                resp = await _request(
                    rec, kind, upload_request(client, payload, options), 202, len(payload[1])
                )
                if resp is not None:
                    ids.append(resp.json()["id"])

        t0 = time.perf_counter()
        await asyncio.gather(*(uploader() for _ in range(min(uploaders, count))))
        return time.perf_counter() - t0


async def _delete_jobs(base: str, ids: list[str], rec: Recorder, concurrency: int = 8) -> None:
    """Cancel (queued: 202) then delete (204) every job in ``ids``."""
    import httpx

    todo = list(ids)
    async with httpx.AsyncClient(base_url=base, timeout=60) as client:

        async def deleter() -> None:
            while todo:
                job_id = todo.pop()
                url = f"/v1/jobs/{job_id}"
                first = await _request(rec, "delete", client.delete(url), (202, 204))
                if first is not None and first.status_code == 202:
                    await _request(rec, "delete", client.delete(url), 204)

        await asyncio.gather(*(deleter() for _ in range(concurrency)))


def job_states(client: Any, wanted: set[str], rec: Recorder) -> dict[str, str]:
    """The status of every job in ``wanted``, read from the pages of ``GET /v1/jobs``."""
    import httpx

    states: dict[str, str] = {}
    url: str | None = "/v1/jobs?limit=100"
    while url:
        try:
            page = client.get(url)
        except httpx.HTTPError as exc:
            rec.error("list_jobs", f"{type(exc).__name__}: {exc}")
            break
        if page.status_code != 200:
            rec.error("list_jobs", f"HTTP {page.status_code}")
            break
        body = page.json()
        states.update({j["id"]: j["status"] for j in body["items"] if j["id"] in wanted})
        url = body.get("next")
    return states


def webhook_secret(client: Any) -> str:
    """The caller's webhook signing secret (``GET /v1/webhook-secret``)."""
    resp = client.get("/v1/webhook-secret")
    if resp.status_code != 200:
        raise LoadBenchError(f"GET /v1/webhook-secret: HTTP {resp.status_code}")
    return str(resp.json()["secret"])


def _drain_phase(
    stack: ServiceStack,
    jobs: int,
    payloads: list[tuple[str, bytes]],
    timeout: float,
    log: Callable[[str], None],
    grace: float = 30.0,
) -> dict[str, Any]:
    """Submit ``jobs`` bicubic jobs, each with a webhook to a local receiver and followed on
    its own event stream (the key's stream open from before the first), and wait until every
    one has ended (or ``timeout``), then up to ``grace`` s for the outcomes on every channel."""
    import httpx

    from .events import WEBHOOK_EVENTS, EventWatch, WebhookReceiver, delivery_report

    rec = Recorder()
    options = {"method": "bicubic", "scale": 2}
    ids: list[str] = []
    curve: list[tuple[float, int]] = []
    with httpx.Client(base_url=stack.base_url, timeout=60) as client:
        receiver = WebhookReceiver(webhook_secret(client))
        with receiver, EventWatch(stack.base_url) as watch:
            fields = {"callback_url": receiver.url, "callback_events": ",".join(WEBHOOK_EVENTS)}
            t0 = time.perf_counter()
            for i in range(jobs):
                t = time.perf_counter()
                try:
                    r = upload_request(client, payloads[i % len(payloads)], options, fields)
                except httpx.HTTPError as exc:
                    rec.error("submit", f"{type(exc).__name__}: {exc}")
                    continue
                if r.status_code != 202:
                    rec.error("submit", f"HTTP {r.status_code}: {r.text[:200]}")
                    continue
                rec.ok("submit", time.perf_counter() - t)
                ids.append(r.json()["id"])
                watch.job(ids[-1])
            submit_s = time.perf_counter() - t0
            deadline = time.monotonic() + timeout
            last_report = 0.0
            while True:
                states = job_states(client, set(ids), rec)
                ended = sum(1 for s in states.values() if s in _TERMINAL)
                elapsed = time.perf_counter() - t0
                curve.append((elapsed, sum(1 for s in states.values() if s == "finished")))
                if elapsed - last_report > 10:
                    log(f"drain: {ended}/{len(ids)} ended after {elapsed:.0f} s")
                    last_report = elapsed
                if ended == len(ids) or time.monotonic() > deadline:
                    break
                time.sleep(0.25)
            total_s = time.perf_counter() - t0
            durations = _run_seconds(client, ids)
            waited = watch.wait_outcomes(ids, grace, receiver)
            events = delivery_report(ids, watch, receiver)
            events["waited_seconds"] = waited
    counts = {s: sum(1 for v in states.values() if v == s) for s in ("queued", "running")}
    counts.update({s: sum(1 for v in states.values() if v == s) for s in _TERMINAL})
    dur = np.asarray(durations, dtype=np.float64)
    return {
        "submitted": len(ids),
        "submit_errors": len(rec.errors),
        "errors": [e for _, e in rec.errors][:20],
        "states": counts,
        "finished": counts["finished"],
        "submit_seconds": submit_s,
        "total_seconds": total_s,
        "jobs_per_s": counts["finished"] / total_s if total_s > 0 else 0.0,
        "job_seconds_p50": float(np.percentile(dur, 50)) if dur.size else None,
        "job_seconds_p99": float(np.percentile(dur, 99)) if dur.size else None,
        "timed_out": sum(counts[s] for s in _TERMINAL) < len(ids),
        "curve": curve,
        "ids": ids,
        "events": events,
    }


def _run_seconds(client: Any, ids: list[str]) -> list[float]:
    """Each ended job's run time (``ended_at - started_at`` of ``GET /v1/jobs/{id}``)."""
    from datetime import datetime

    out = []
    for job_id in ids:
        r = client.get(f"/v1/jobs/{job_id}")
        if r.status_code == 200:
            j = r.json()
            if j.get("started_at") and j.get("ended_at"):
                s = datetime.fromisoformat(j["started_at"])
                e = datetime.fromisoformat(j["ended_at"])
                out.append((e - s).total_seconds())
    return out


# ----------------------------------------------------------------------------- the run
def api_phases(
    stack: ServiceStack,
    work: Path,
    result: dict[str, Any],
    *,
    duration: float,
    baseline: float,
    pollers: int,
    uploaders: int,
    upload_mb: float,
    big_uploads: int,
    request_timeout: float,
    small_size: int,
    log: Callable[[str], None],
) -> None:
    """Phases a and b and the deletion of their jobs (the module docstring) against
    ``stack``'s API, no worker running; their results go into ``result``."""
    if duration <= 0 or pollers < 0 or uploaders < 0:
        raise LoadBenchError("duration must be > 0 and counts >= 0")
    if pollers + uploaders == 0:
        raise LoadBenchError("phase a needs at least one poller or uploader")
    log("building payloads")
    payloads = small_payloads(work / "payloads", size=small_size)
    big = big_payload(work / "payloads", upload_mb) if big_uploads else None
    ids: list[str] = []
    seed_rec = Recorder()
    for i in range(4):  # jobs to poll from the first request on
        asyncio.run(_upload_phase(stack.base_url, 1, 1, payloads[i], ids, seed_rec, "seed"))
    if seed_rec.errors or not ids:
        raise LoadBenchError(f"could not submit the first jobs: {seed_rec.errors[:3]}")

    if baseline > 0 and pollers > 0:
        log(f"baseline: {pollers} pollers alone for {baseline:.0f} s")
        prec = Recorder()
        pwall = asyncio.run(
            _mixed_phase(stack.base_url, baseline, pollers, 0, payloads, ids, prec, request_timeout)
        )
        result["poll_only"] = {
            "wall_seconds": pwall,
            "kinds": prec.summary(pwall),
            "errors": len(prec.errors),
            "error_samples": [f"{k}: {e}" for k, e in prec.errors[:20]],
        }

    log(f"phase a: {pollers} pollers + {uploaders} uploaders for {duration:.0f} s")
    rec = Recorder()
    wall = asyncio.run(
        _mixed_phase(
            stack.base_url, duration, pollers, uploaders, payloads, ids, rec, request_timeout
        )
    )
    result["mixed"] = {
        "wall_seconds": wall,
        "kinds": rec.summary(wall),
        "errors": len(rec.errors),
        "error_samples": [f"{k}: {e}" for k, e in rec.errors[:20]],
        "requests_per_s": sum(len(v) for v in rec.latencies.values()) / wall,
        "latencies_ms": {k: [x * 1e3 for x in v] for k, v in rec.latencies.items()},
    }

    if big is not None:
        mb = len(big[1]) / _MB
        log(f"phase b: {big_uploads} uploads of {mb:.1f} MB, {uploaders} at a time")
        brec = Recorder()
        bwall = asyncio.run(
            _upload_phase(stack.base_url, max(1, uploaders), big_uploads, big, ids, brec)
        )
        result["big"] = {
            "wall_seconds": bwall,
            "mb_each": mb,
            "kinds": brec.summary(bwall),
            "errors": len(brec.errors),
            "error_samples": [f"{k}: {e}" for k, e in brec.errors[:20]],
            "mb_per_s_total": mb * len(brec.latencies.get("big_upload", [])) / bwall,
        }

    log(f"deleting the {len(ids)} jobs of phases a and b")
    drec = Recorder()
    t0 = time.perf_counter()
    asyncio.run(_delete_jobs(stack.base_url, ids, drec))
    result["cleanup"] = {
        "kinds": drec.summary(time.perf_counter() - t0),
        "errors": len(drec.errors),
        "error_samples": [f"{k}: {e}" for k, e in drec.errors[:20]],
    }
    result["ratios"] = _ratios(result)


def run(
    out_dir: Path = Path("bench-out/load"),
    *,
    duration: float = 60.0,
    baseline: float = 10.0,
    pollers: int = 50,
    uploaders: int = 10,
    upload_mb: float = 20.0,
    big_uploads: int | None = None,
    jobs: int = 100,
    workers: int = 2,
    drain_timeout: float = 900.0,
    request_timeout: float = 30.0,
    redis_url: str | None = None,
    small_size: int = 32,
    log: Callable[[str], None] = lambda m: None,
) -> dict[str, Any]:
    """Run the three phases (see the module docstring); returns (and writes) the results.

    ``baseline`` seconds of pollers alone run first (0: skip), to show what the uploads'
    intake costs the pollers. ``big_uploads`` defaults to ``uploaders`` (one big asset each);
    0 skips phase b; ``jobs`` 0 skips phase c. ``redis_url`` None = a private
    ``redis-server`` when installed (else db 13 of 127.0.0.1:6379 with a private prefix).
    """
    if jobs < 0 or workers < 1:
        raise LoadBenchError("jobs must be >= 0 and workers >= 1")
    big_uploads = uploaders if big_uploads is None else big_uploads
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="pbrsr-load-"))
    result: dict[str, Any] = {
        "config": {
            "duration": duration,
            "baseline": baseline,
            "pollers": pollers,
            "uploaders": uploaders,
            "upload_mb": upload_mb,
            "big_uploads": big_uploads,
            "jobs": jobs,
            "workers": workers,
            "cpus": os.cpu_count(),
        }
    }
    try:
        tiny = small_payloads(work / "tiny", n=2, size=16)
        with service_stack(work, redis_url) as stack:
            result["config"]["private_redis"] = stack.private_redis
            log(f"API at {stack.base_url} (redis {'private' if stack.private_redis else 'shared'})")
            api_phases(
                stack,
                work,
                result,
                duration=duration,
                baseline=baseline,
                pollers=pollers,
                uploaders=uploaders,
                upload_mb=upload_mb,
                big_uploads=big_uploads,
                request_timeout=request_timeout,
                small_size=small_size,
                log=log,
            )
            if jobs:
                log(f"phase c: starting {workers} workers")
                t0 = time.perf_counter()
                stack.start_workers(workers)
                start_s = time.perf_counter() - t0
                log(f"phase c: {jobs} bicubic jobs, followed by SSE and webhooks")
                drain = _drain_phase(stack, jobs, tiny, drain_timeout, log)
                drain["workers_start_seconds"] = start_s
                drain["workers_alive"] = sum(1 for p in stack.workers if p.poll() is None)
                result["drain"] = drain
            if not stack.private_redis:
                _delete_keys(stack.redis_url, stack.queue, stack.prefix, [])
    finally:
        shutil.rmtree(work, ignore_errors=True)

    result["ok"] = _passed(result)
    _write(result, out_dir)
    return result


def api_passed(result: dict[str, Any]) -> bool:
    """No error in any API phase of ``result`` that ran."""
    phases = ("poll_only", "mixed", "big", "cleanup")
    return all(result[p]["errors"] == 0 for p in phases if p in result)


def _passed(result: dict[str, Any]) -> bool:
    ok = api_passed(result)
    if "drain" in result:
        d = result["drain"]
        wanted = result["config"]["jobs"]
        ok = ok and d["submit_errors"] == 0 and d["finished"] == d["submitted"] == wanted
        ok = ok and d["events"]["lost"] == 0 and d["events"]["bad_signatures"] == 0
    return bool(ok)


def _write(result: dict[str, Any], out_dir: Path) -> None:
    slim = json.loads(json.dumps(result, default=str))
    slim.get("mixed", {}).pop("latencies_ms", None)
    slim.get("drain", {}).pop("ids", None)
    slim.get("drain", {}).get("events", {}).pop("latencies_ms", None)
    (out_dir / "load.json").write_text(json.dumps(slim, indent=2))
    _plot(result, out_dir / "load.png")


def _plot(result: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(18, 4.5))
    cfg = result["config"]
    title = f"phase a: {cfg['pollers']} pollers + {cfg['uploaders']} uploaders"
    latency_cdf(axes[0], result["mixed"].get("latencies_ms", {}), title, "requests")
    drain = result.get("drain")
    events = drain["events"]["latencies_ms"] if drain else {}
    latency_cdf(axes[2], events, "phase c: event published -> received", "events")
    ax = axes[1]
    if drain and drain["curve"]:
        t, n = zip(*drain["curve"], strict=True)
        ax.plot(t, n, drawstyle="steps-post")
        ax.axhline(drain["submitted"], color="grey", ls="--", lw=1)
        ax.set_title(f"phase c: {drain['submitted']} bicubic jobs, {cfg['workers']} workers")
    else:
        ax.set_title("phase c: skipped")
    ax.set_xlabel("seconds since the first submission")
    ax.set_ylabel("jobs finished")
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def latency_cdf(ax: Any, latencies: dict[str, list[float]], title: str, what: str) -> None:
    """The distribution of each kind's latencies (ms) on ``ax``, log x."""
    for kind, values in sorted(latencies.items()):
        v = np.sort(np.asarray(values))
        if v.size:
            ax.plot(v, np.arange(1, v.size + 1) / v.size, label=f"{kind} (n={v.size})")
    ax.set_xscale("log")
    ax.set_xlabel("latency (ms)")
    ax.set_ylabel(f"fraction of {what}")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    if any(latencies.values()):
        ax.legend()


def _ratios(result: dict[str, Any]) -> list[dict[str, Any]]:
    """p50 of each status read over /healthz's p50 in the same phase, against its target."""
    out = []
    for (kind, phase), target in RATIO_TARGETS.items():
        kinds = result.get(phase, {}).get("kinds", {})
        if kind in kinds and "healthz" in kinds and kinds["healthz"]["p50_ms"]:
            ratio = kinds[kind]["p50_ms"] / kinds["healthz"]["p50_ms"]
            row = {"request": kind, "phase": phase, "ratio": round(ratio, 2), "target": target}
            out.append({**row, "met": ratio <= target})
    return out


def wide_console() -> Any:
    """A rich console at least 110 columns wide (the benchmarks' tables)."""
    from rich.console import Console

    return Console(width=max(Console().width, 110))


def _ms(v: float | None) -> str:
    return "-" if v is None else f"{v:.1f}"


def print_api(out: Any, result: dict[str, Any], title: str) -> None:
    """The API phases of ``result`` on the console ``out``: one row per phase and request
    kind, then the status reads against ``/healthz``."""
    from rich.table import Table

    table = Table(title=title)
    for col in ("phase", "request", "count", "errors", "req/s", "p50 ms", "p99 ms", "max ms"):
        table.add_column(col, justify="left" if col in ("phase", "request") else "right")
    table.add_column("MB/s", justify="right")
    for phase in ("poll_only", "mixed", "big", "cleanup"):
        if phase not in result:
            continue
        for kind, row in result[phase]["kinds"].items():
            mbs = ""
            if "mb_per_s_total" in row:
                mbs = f"{row['mb_per_s_total']:.1f}"
            table.add_row(
                phase,
                kind,
                str(row["requests"]),
                str(row["errors"]),
                f"{row['per_s']:.1f}",
                _ms(row["p50_ms"]),
                _ms(row["p99_ms"]),
                _ms(row["max_ms"]),
                mbs,
            )
    out.print(table)
    if result.get("ratios"):
        t1 = Table(title="status reads against /healthz (p50 over p50, same phase)")
        for col in ("request", "phase", "ratio", "target", "met"):
            t1.add_column(col, justify="left" if col in ("request", "phase") else "right")
        for r in result["ratios"]:
            t1.add_row(
                r["request"], r["phase"], f"{r['ratio']:.2f}x", f"{r['target']:.0f}x", met(r["met"])
            )
        out.print(t1)


def met(ok: bool) -> str:
    """A target's yes/no, coloured."""
    return "[green]yes[/green]" if ok else "[red]no[/red]"


def print_table(result: dict[str, Any]) -> None:
    """The results as rich tables: one row per request kind, then the drain and its events."""
    from rich.table import Table

    out = wide_console()
    print_api(out, result, "pbrsr bench load")
    drain = result.get("drain")
    if drain:
        t2 = Table(title="drain")
        for col in ("workers", "submitted", "finished", "failed", "total s", "jobs/s", "job p50 s"):
            t2.add_column(col, justify="right")
        p50 = drain["job_seconds_p50"]
        t2.add_row(
            str(result["config"]["workers"]),
            str(drain["submitted"]),
            str(drain["finished"]),
            str(drain["states"]["failed"]),
            f"{drain['total_seconds']:.1f}",
            f"{drain['jobs_per_s']:.2f}",
            "-" if p50 is None else f"{p50:.2f}",
        )
        out.print(t2)
        print_events(out, drain["events"])
    out.print("[green]PASS[/green]" if result["ok"] else "[red]FAIL[/red]")


def print_events(out: Any, events: dict[str, Any]) -> None:
    """The event channels of :func:`pbrsr_bench.events.delivery_report` as a table."""
    from rich.table import Table

    table = Table(title=f"events of {events['jobs']} jobs (published -> received)")
    for col in ("channel", "events", "timed", "lost", "p50 ms", "p99 ms", "max ms"):
        table.add_column(col, justify="left" if col == "channel" else "right")
    for name, c in events["channels"].items():
        lost = f"[red]{c['lost']}[/red]" if c["lost"] else "0"
        table.add_row(
            name, str(c["events"]), str(c["timed"]), lost, _ms(c["p50_ms"]), _ms(c["p99_ms"]),
            _ms(c["max_ms"]),
        )  # fmt: skip
    out.print(table)
    notes = [f"{events['reconnects']} stream reconnects", f"{events['stream_errors']} errors"]
    if events["bad_signatures"]:
        notes.append(f"[red]{events['bad_signatures']} bad webhook signatures[/red]")
    for c in events["channels"].values():
        notes.extend(c["lost_samples"][:3])
    out.print("; ".join(notes))
