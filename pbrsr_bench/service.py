"""``pbrsr bench service``: the job service against the CLI, and N workers against one.

Everything runs on the processes of :func:`pbrsr_bench.load.service_stack` (one API, a
private Redis, temporary storage, worker processes started and idle before a clock starts),
with one asset (the procedural demo asset, or a shared asset, degraded by ``scale`` first as
the other benchmarks do) and one set of options:

a. ``api`` (``duration`` > 0): the polling and upload phases of ``pbrsr bench load``.
b. ``single``: one worker. One job's wall time through the service, from the start of its
   upload to the receipt of its ``succeeded`` event on its event stream, against
   ``pbrsr upscale`` run as a subprocess on the same file with the same options and the
   threads the service's run used (process start to exit); the pipeline's own
   ``wall_seconds`` of each is reported beside them. Target: service / CLI at most
   ``CLI_RATIO_TARGET``.
c. ``sequential``: ``jobs`` jobs submitted together to that one worker, which runs them one
   after another; ``parallel``: the same jobs on ``workers`` workers started afresh. Each
   batch's throughput is its jobs over the time from the first upload to the last outcome.
   Target: parallel's at least sequential's (``THROUGHPUT_TARGET``).

Threads: workers choose their own (``PBRSR_WORKER_THREADS`` unset: the usable cores divided
among the workers registered on this host, :mod:`worker.threads`); every run reports the
threads it used (its report's ``threads``). The workers preload the prior the options name,
and no run keeps pseudo-GT between runs (``PBRSR_PSEUDO_GT_CACHE_MB=0``): the jobs are
identical, and a cache hit would time the cache. ``run(...)`` returns a JSON-able dict (also
``out_dir/service.json``), ``print_table`` prints it, ``service.png`` plots it.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pbrsr_core.options import UpscaleOptions

from .load import (
    LoadBenchError,
    ServiceStack,
    api_passed,
    api_phases,
    latency_cdf,
    met,
    print_api,
    service_stack,
    upload_request,
    wide_console,
)
from .shared import SHARED_ASSETS

CLI_RATIO_TARGET = 1.2  # a job through the service over the same run of `pbrsr upscale`
THROUGHPUT_TARGET = 1.0  # N workers' jobs per second over one worker's, same jobs
_NO_CACHE = {"PBRSR_PSEUDO_GT_CACHE_MB": "0"}


def input_payload(gt_path: Path, scale: int, work: Path) -> Path:
    """The benchmark's input: ``gt_path`` degraded by ``scale`` (``pbrsr degrade``), as one
    file: the .glb, or a .zip of the .gltf's folder."""
    from pbrsr_core.degrade import degrade_asset

    lr = degrade_asset(gt_path, work / "lr" / gt_path.name, scale)[0]
    if lr.suffix.lower() == ".glb":
        return lr
    out = work / f"{lr.stem}.zip"
    with zipfile.ZipFile(out, "w") as zf:
        for path in sorted(lr.parent.rglob("*")):
            if path.is_file():
                zf.write(path, path.relative_to(lr.parent).as_posix())
    return out


def submit_and_wait(
    stack: ServiceStack, payload: Path, options: dict[str, Any], count: int, timeout: float
) -> dict[str, Any]:
    """Upload ``payload`` ``count`` times and wait for every job's outcome on its event
    stream. Returns the seconds from the first upload to each outcome (sorted), the
    outcomes, and the threads and pipeline ``wall_seconds`` each job reported."""
    import httpx

    from .events import EventWatch

    data = (payload.name, payload.read_bytes())
    watch = EventWatch(stack.base_url).start(key_stream=False)
    try:
        with httpx.Client(base_url=stack.base_url, timeout=300) as client:
            t0 = time.time()
            ids = []
            for _ in range(count):
                resp = upload_request(client, data, options)
                if resp.status_code != 202:
                    raise LoadBenchError(
                        f"upload refused: HTTP {resp.status_code} {resp.text[:200]}"
                    )
                ids.append(resp.json()["id"])
                watch.job(ids[-1])
            ends = [watch.wait_terminal(job_id, timeout) for job_id in ids]
    finally:
        watch.close()
    summaries = [e.data.get("summary") or {} for e in ends]
    return {
        "jobs": count,
        "outcomes": [e.type for e in ends],
        "errors": [e.data.get("error") for e in ends if e.type != "succeeded"],
        "done_seconds": sorted(e.at - t0 for e in ends),
        "seconds": max(e.at for e in ends) - t0,
        "threads": [s.get("threads") for s in summaries],
        "pipeline_seconds": [s.get("wall_seconds") for s in summaries],
    }


def run_cli(
    stack: ServiceStack, payload: Path, options: dict[str, Any], threads: int, work: Path
) -> dict[str, Any]:
    """``pbrsr upscale`` on ``payload`` as a subprocess with the job's ``options`` on the
    CPU (as the stack's workers), torch and numba limited to ``threads``; its wall time
    (process start to exit) and its report."""
    out = work / "cli-out"
    args = [sys.executable, "-m", "pbrsr_core", "upscale", str(payload), "-o", str(out), "-q"]
    for name, value in {**options, "device": "cpu"}.items():
        args += [f"--{name}", str(value)]
    env = {**stack.env(), **_NO_CACHE, "OMP_NUM_THREADS": str(threads)}
    env["NUMBA_NUM_THREADS"] = str(threads)
    t0 = time.perf_counter()
    proc = subprocess.run(args, env=env, capture_output=True, text=True, check=False)
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        raise LoadBenchError(f"pbrsr upscale exited {proc.returncode}: {proc.stderr[-500:]}")
    report = json.loads((out / "report.json").read_text())
    return {
        "seconds": seconds,
        "pipeline_seconds": report["wall_seconds"],
        "threads": report["threads"],
    }


def run(
    out_dir: Path = Path("bench-out/service"),
    *,
    asset: str = "procedural",
    method: str = "pbrsr",
    preset: str = "fast",
    scale: int = 4,
    workers: int = 2,
    jobs: int = 0,
    procedural_size: int = 1536,
    duration: float = 15.0,
    pollers: int = 50,
    uploaders: int = 10,
    upload_mb: float = 20.0,
    job_timeout: float = 1800.0,
    request_timeout: float = 30.0,
    redis_url: str | None = None,
    shared: Path = SHARED_ASSETS,
    log: Callable[[str], None] = lambda m: None,
) -> dict[str, Any]:
    """Run the phases of the module docstring; returns (and writes) the results.

    ``asset``: ``procedural`` (the demo asset with ``procedural_size``² maps) or a folder of
    ``shared``; ``jobs`` 0: as many as ``workers``; ``duration`` 0 skips the API phases.
    An impossible choice (unknown asset or options, counts below 1) is a ValueError.
    """
    from pbrsr_core.errors import PbrsrError
    from pbrsr_core.optim.presets import get_preset

    from .upscale import bench_assets

    if workers < 1 or jobs < 0 or duration < 0:
        raise ValueError("workers must be >= 1, jobs and duration >= 0")
    jobs = jobs or workers
    try:
        get_preset(preset)
    except PbrsrError as exc:
        raise ValueError(exc.message) from None
    opts = UpscaleOptions(method=method, preset=preset, scale=scale)
    options = {k: getattr(opts, k) for k in ("method", "preset", "scale", "prior")}
    preload = "" if method == "bicubic" else opts.prior
    worker_env = {**_NO_CACHE, "PBRSR_PRELOAD_PRIORS": preload}
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="pbrsr-bench-service-"))
    result: dict[str, Any] = {
        "config": {
            "asset": asset,
            "options": options,
            "workers": workers,
            "jobs": jobs,
            "cpus": os.cpu_count(),
            "duration": duration,
            "pollers": pollers,
            "uploaders": uploaders,
        }
    }
    try:
        procedural = asset == "procedural"
        names = None if procedural else [asset]
        todo = dict(
            bench_assets(work, procedural, procedural_size, shared, names, log, not procedural)
        )
        if asset not in todo:
            raise ValueError(f"asset {asset!r} not found (procedural, or a folder of {shared})")
        log(f"{asset}: degrade x{scale}")
        payload = input_payload(todo[asset], scale, work)
        result["config"]["input_mb"] = payload.stat().st_size / 2**20
        with service_stack(work, redis_url) as stack:
            result["config"]["private_redis"] = stack.private_redis
            if duration > 0:
                api_phases(
                    stack,
                    work,
                    result,
                    duration=duration,
                    baseline=duration,
                    pollers=pollers,
                    uploaders=uploaders,
                    upload_mb=upload_mb,
                    big_uploads=uploaders,
                    request_timeout=request_timeout,
                    small_size=32,
                    log=log,
                )
            log("starting 1 worker")
            stack.start_workers(1, env=worker_env)
            log(f"one job through the service ({method}, {preset}, x{scale})")
            service = submit_and_wait(stack, payload, options, 1, job_timeout)
            if service["errors"]:
                raise LoadBenchError(f"the service's job failed: {service['errors'][0]}")
            threads = service["threads"][0] or 1
            log(f"the same with pbrsr upscale, {threads} threads")
            cli = run_cli(stack, payload, options, threads, work)
            result["single"] = _single(service, cli)
            log(f"{jobs} jobs on 1 worker")
            result["sequential"] = submit_and_wait(stack, payload, options, jobs, job_timeout)
            stack.stop_workers()
            log(f"{jobs} jobs on {workers} workers")
            stack.start_workers(workers, env=worker_env)
            result["parallel"] = submit_and_wait(stack, payload, options, jobs, job_timeout)
    finally:
        shutil.rmtree(work, ignore_errors=True)

    result["throughput"] = _throughput(result["sequential"], result["parallel"], workers)
    result["ok"] = _passed(result)
    slim = json.loads(json.dumps(result, default=str))
    slim.get("mixed", {}).pop("latencies_ms", None)
    (out_dir / "service.json").write_text(json.dumps(slim, indent=2))
    plot(result, out_dir / "service.png")
    return result


def _single(service: dict[str, Any], cli: dict[str, Any]) -> dict[str, Any]:
    ratio = service["seconds"] / cli["seconds"]
    return {
        "service_seconds": service["seconds"],
        "service_pipeline_seconds": service["pipeline_seconds"][0],
        "service_threads": service["threads"][0],
        "cli_seconds": cli["seconds"],
        "cli_pipeline_seconds": cli["pipeline_seconds"],
        "cli_threads": cli["threads"],
        "ratio": ratio,
        "target": CLI_RATIO_TARGET,
        "met": ratio <= CLI_RATIO_TARGET,
    }


def _throughput(seq: dict[str, Any], par: dict[str, Any], workers: int) -> dict[str, Any]:
    for batch, n in ((seq, 1), (par, workers)):
        batch["workers"] = n
        batch["jobs_per_minute"] = 60.0 * batch["jobs"] / batch["seconds"]
    ratio = par["jobs_per_minute"] / seq["jobs_per_minute"]
    return {"ratio": ratio, "target": THROUGHPUT_TARGET, "met": ratio >= THROUGHPUT_TARGET}


def _passed(result: dict[str, Any]) -> bool:
    """No API error and every job of the batches succeeded (the targets are reported, not
    required)."""
    batches = (result["sequential"], result["parallel"])
    return api_passed(result) and not any(b["errors"] for b in batches)


def plot(result: dict[str, Any], path: Path) -> None:
    """Wall times of the single job, each batch's outcomes over time, and the API's
    latencies when they were measured."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, axes = plt.subplots(1, 3, figsize=(18, 4.5))
    single = result["single"]
    ax = axes[0]
    labels = ["CLI process", "CLI pipeline", "service job", "service pipeline"]
    keys = ["cli_seconds", "cli_pipeline_seconds", "service_seconds", "service_pipeline_seconds"]
    ax.bar(labels, [single[k] for k in keys], color=["C0", "C0", "C1", "C1"])
    ax.set_ylabel("seconds")
    ax.set_title(f"one job: service / CLI = {single['ratio']:.2f}x")
    ax = axes[1]
    for name in ("sequential", "parallel"):
        batch = result[name]
        t = np.concatenate([[0.0], batch["done_seconds"]])
        n = np.arange(t.size)
        label = f"{batch['workers']} worker(s): {batch['jobs_per_minute']:.2f} jobs/min"
        ax.plot(t, n, drawstyle="steps-post", label=label)
    ax.set_xlabel("seconds since the first upload")
    ax.set_ylabel("jobs ended")
    ax.set_title(
        f"{result['config']['jobs']} jobs: throughput x{result['throughput']['ratio']:.2f}"
    )
    ax.grid(True, alpha=0.3)
    ax.legend()
    mixed = result.get("mixed", {})
    cfg = result["config"]
    title = f"API: {cfg['pollers']} pollers + {cfg['uploaders']} uploaders"
    latency_cdf(
        axes[2], mixed.get("latencies_ms", {}), title if mixed else "API: skipped", "requests"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def print_table(result: dict[str, Any]) -> None:
    """The API phases (when run), the single job against the CLI, and the two batches."""
    from rich.table import Table

    out = wide_console()
    if "mixed" in result:
        print_api(out, result, "pbrsr bench service: the API")
    s = result["single"]
    o = result["config"]["options"]
    t1 = Table(title=f"one job ({o['method']}, {o['preset']}, x{o['scale']}): service against CLI")
    for col in ("run", "wall s", "pipeline s", "outside the pipeline s", "threads"):
        t1.add_column(col, justify="left" if col == "run" else "right")
    for label, key in (
        ("pbrsr upscale (process start to exit)", "cli"),
        ("service (upload to succeeded event)", "service"),
    ):
        wall, pipeline = s[f"{key}_seconds"], s[f"{key}_pipeline_seconds"]
        t1.add_row(
            label,
            f"{wall:.2f}",
            f"{pipeline:.2f}",
            f"{wall - pipeline:.2f}",
            str(s[f"{key}_threads"]),
        )
    out.print(t1)
    out.print(f"service / CLI: {s['ratio']:.2f}x (target <= {s['target']}x): {met(s['met'])}")
    t2 = Table(title=f"{result['config']['jobs']} jobs: N workers against one")
    for col in ("workers", "threads per job", "seconds", "jobs/min", "pipeline s (mean)", "failed"):
        t2.add_column(col, justify="right")
    for name in ("sequential", "parallel"):
        b = result[name]
        runs = [v for v in b["pipeline_seconds"] if v is not None]
        t2.add_row(
            str(b["workers"]),
            ",".join(str(t) for t in sorted(set(b["threads"]), key=str)),
            f"{b['seconds']:.2f}",
            f"{b['jobs_per_minute']:.2f}",
            f"{sum(runs) / len(runs):.2f}" if runs else "-",
            str(len(b["errors"])),
        )
    out.print(t2)
    tp = result["throughput"]
    ratio = f"{tp['ratio']:.2f}x (target >= {tp['target']}x)"
    out.print(f"throughput, {result['config']['workers']} workers / 1: {ratio}: {met(tp['met'])}")
    out.print("[green]PASS[/green]" if result["ok"] else "[red]FAIL[/red]")
