"""The RQ job function: one upscale run of one stored job.

``run_job(job_id)`` is what the API enqueues (by its dotted name, so the API never imports
this module). It reads the job's manifest and copies its input from the object store
(:class:`~pbrsr_jobs.store.JobFiles`: a shared folder or an S3 bucket) into a
``.tmp-input-*`` folder of this machine, runs :func:`pbrsr_core.pipeline.upscale_asset` on
it with a :class:`~worker.progress.JobReporter` as the progress callback, and publishes the
result:

1. the pipeline writes the bundle's files into a fresh ``jobs/<id>/.tmp-output-*`` folder
   and every map's LR/HR detail crops (:mod:`pbrsr_core.crops`) into a ``.tmp-crops-*``
   folder,
2. thumbnails of every HR map go to a ``.tmp-thumbs-*`` folder,
3. the zip is written as ``.tmp-bundle-*.zip``,
4. the thumbnails, the crops, the bundle's files and then the zip are stored as the job's
   objects
   (``JobFiles.publish_result``: what an earlier attempt stored goes first, and what this one
   stored goes again if storing fails), and only then ``meta['state']`` becomes
   ``finished``.

A reader therefore never sees half a bundle; a run that dies leaves only ``.tmp-*`` entries,
removed by the next attempt or by expiry. A job that ends frees this machine's working
files (``JobLayout.release``). User errors (``PbrsrError``) and cancellation end
the run *normally* (RQ would otherwise retry them) with the outcome in ``meta``; internal
errors get a generic message in ``meta`` and their traceback in the worker log. RQ's retries
are kept for what they are for: a worker that died mid-job.
"""

from __future__ import annotations

import errno
import gc
import logging
import os
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pbrsr_core.errors import Cancelled, PbrsrError, StorageError
from pbrsr_core.map_table import map_rows
from pbrsr_jobs.objstore import StoreUnavailable, open_store
from pbrsr_jobs.settings import Settings
from pbrsr_jobs.store import JobFiles, JobIndex, JobLayout, JobState, resolve_options

from .cancel import CancelWatchdog
from .progress import JobReporter

log = logging.getLogger("pbrsr.worker")

THUMB_SIZE = 256
_STORED = {".png", ".jpg", ".jpeg", ".glb", ".exr", ".ktx2", ".webp", ".avif"}


@dataclass
class WorkerContext:
    """What every job in this process shares (built once per worker process)."""

    settings: Settings
    layout: JobLayout
    files: JobFiles
    index: JobIndex
    device: str  # resolved: "cpu", "cuda", "cuda:1"
    worker_name: str = "worker"


_CONTEXT: WorkerContext | None = None


def set_context(ctx: WorkerContext) -> None:
    global _CONTEXT
    _CONTEXT = ctx


def get_context(connection: Any) -> WorkerContext:
    """The process's context; built from the environment on first use if the runner did not."""
    global _CONTEXT
    if _CONTEXT is None:
        from pbrsr_core.device import resolve_device

        settings = Settings()
        _CONTEXT = WorkerContext(
            settings=settings,
            layout=JobLayout(settings.prepare_storage()),
            files=JobFiles(open_store(settings)),
            index=JobIndex(connection, settings.key_prefix),
            device=str(resolve_device(settings.device)),
        )
    return _CONTEXT


def run_job(job_id: str) -> dict[str, Any]:
    """Run stored job ``job_id`` (called by RQ inside a worker). Returns a short summary."""
    from rq import get_current_job
    from rq.timeouts import JobTimeoutException

    job = get_current_job()
    if job is None or job.id != job_id:
        raise RuntimeError("run_job must run inside the RQ job of the same id")
    ctx = get_context(job.connection)
    layout, files, index = ctx.layout, ctx.files, ctx.index
    attempt = int(job.meta.get("attempt", 0)) + 1
    method = str((job.meta.get("options") or {}).get("method", "pbrsr"))
    reporter = JobReporter(job, index, interval_s=ctx.settings.progress_interval_s, method=method)

    if index.cancel_requested(job_id):
        reporter.finish(JobState.CANCELED)
        layout.release(job_id)
        return {"state": JobState.CANCELED.value}

    layout.clear_tmp(job_id)  # what an earlier attempt on a dead worker left behind
    reporter.start(attempt, ctx.worker_name)
    log.info("job %s: attempt %d on %s", job_id, attempt, ctx.device)
    tmp_paths: list[Path] = []
    try:
        manifest = files.read_manifest(job_id)
        options = resolve_options(manifest.options, ctx.settings, device=ctx.device)
        in_tmp = layout.tmp_dir(job_id, "input")
        tmp_paths.append(in_tmp)
        files.fetch_input(job_id, in_tmp)
        input_path = in_tmp / manifest.input
        out_tmp = layout.tmp_dir(job_id, "output")
        crops_tmp = layout.tmp_dir(job_id, "crops")
        tmp_paths += [out_tmp, crops_tmp]
        from pbrsr_core.crops import read_crop_index
        from pbrsr_core.footprint import memory_budget
        from pbrsr_core.pipeline import upscale_asset

        with CancelWatchdog(index, job_id):
            report = upscale_asset(
                input_path,
                out_tmp,
                options,
                progress=reporter,
                limits=ctx.settings.limits(),
                work_dir=layout.work_dir(job_id),
                # refused, not killed, when it cannot fit
                memory_budget=memory_budget(ctx.settings.worker_memory_mb),
                crops_dir=crops_tmp,
            )
            reporter.check_cancel()
            reporter(_bundle_event())
            thumbs_tmp = layout.tmp_dir(job_id, "thumbs")
            tmp_paths.append(thumbs_tmp)
            write_thumbnails(out_tmp / "maps", thumbs_tmp)
            bundle_tmp = layout.job_dir(job_id) / f".tmp-bundle-{os.getpid()}-{time.time_ns()}.zip"
            tmp_paths.append(bundle_tmp)
            write_bundle_zip(out_tmp, bundle_tmp)
        # published only after the watchdog is disarmed: a cancel cannot cut this short
        names = files.publish_result(job_id, out_tmp, thumbs_tmp, crops_tmp, bundle_tmp)
        summary = _summary(report)
        # the names the API links to: a status read lists nothing
        job.meta["files"] = {
            **names,
            "crops": read_crop_index(crops_tmp),
            "model": report["input"],
        }
        reporter.finish(JobState.FINISHED, summary=summary)
        log.info("job %s: finished", job_id)
        return {"state": JobState.FINISHED.value, **summary}
    except Cancelled:
        _remove_all(tmp_paths)  # before the state changes: a reader never sees leftovers
        log.info("job %s: canceled", job_id)
        reporter.finish(JobState.CANCELED)
        return {"state": JobState.CANCELED.value}
    except PbrsrError as exc:
        _remove_all(tmp_paths)  # before the state changes: a reader never sees leftovers
        log.info("job %s: failed: %s", job_id, exc.message)
        reporter.finish(JobState.FAILED, error=exc.message, code=exc.code)
        return {"state": JobState.FAILED.value}
    except JobTimeoutException:
        _remove_all(tmp_paths)  # before the state changes: a reader never sees leftovers
        message = (
            f"the job ran longer than the server's limit of {ctx.settings.job_timeout} s; "
            "try a faster preset or a smaller scale"
        )
        reporter.finish(JobState.FAILED, error=message, code="timeout")
        return {"state": JobState.FAILED.value}
    except StoreUnavailable as exc:
        _remove_all(tmp_paths)  # before the state changes: a reader never sees leftovers
        log.warning("job %s: storage unavailable: %s", job_id, exc)
        err = StorageError("the job storage was unavailable (the server's object store)")
        reporter.finish(JobState.FAILED, error=err.message, code=err.code)
        return {"state": JobState.FAILED.value}
    except OSError as exc:
        _remove_all(tmp_paths)  # before the state changes: a reader never sees leftovers
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            err = StorageError("the server ran out of disk space while writing the result")
        else:
            log.exception("job %s: storage error", job_id)
            err = StorageError("the server could not write the result (storage error)")
        reporter.finish(JobState.FAILED, error=err.message, code=err.code)
        return {"state": JobState.FAILED.value}
    except Exception:
        _remove_all(tmp_paths)  # before the state changes: a reader never sees leftovers
        log.exception("job %s: internal error", job_id)
        reporter.finish(
            JobState.FAILED,
            error=f"internal error while processing the job (reference {job_id}); "
            "the server's administrator can find the details in the worker log",
            code="internal-error",
        )
        return {"state": JobState.FAILED.value}
    finally:
        _remove_all(tmp_paths)
        layout.release(job_id)  # the job has ended (a worker that died never gets here)
        _free_memory()


def _bundle_event():
    from pbrsr_core.progress import Progress

    return Progress(stage="bundle", step=0, total=1)


def _summary(report: dict[str, Any]) -> dict[str, Any]:
    keys = ("wall_seconds", "device", "threads", "timings", "metrics", "final_losses", "lr_model")
    out = {k: report[k] for k in keys if k in report}
    out["maps"] = [img.get("file") for img in report.get("images", []) if isinstance(img, dict)]
    out["map_rows"] = map_rows(report)
    return out


def _free_memory() -> None:
    gc.collect()
    try:
        import torch

        if torch.cuda.is_available():
            torch.cuda.empty_cache()
    except Exception:  # noqa: BLE001 - freeing memory is best effort
        pass


def write_bundle_zip(src: Path, dest: Path) -> None:
    """Zip every file under ``src`` (relative names) into ``dest``; images stored, text deflated."""
    with zipfile.ZipFile(dest, "w", allowZip64=True) as zf:
        for path in sorted(src.rglob("*")):
            if path.is_symlink() or not path.is_file():
                continue
            rel = path.relative_to(src).as_posix()
            method = zipfile.ZIP_STORED if path.suffix.lower() in _STORED else zipfile.ZIP_DEFLATED
            zf.write(path, rel, compress_type=method)


def write_thumbnails(maps_dir: Path, dest: Path, size: int = THUMB_SIZE) -> list[str]:
    """A PNG thumbnail (longest side <= ``size``, 8-bit RGB/RGBA) of every map in ``maps_dir``."""
    import OpenImageIO as oiio

    names = []
    if not maps_dir.is_dir():
        return names
    for path in sorted(maps_dir.iterdir()):
        if not path.is_file() or path.suffix.lower() not in (".png", ".exr", ".jpg", ".jpeg"):
            continue
        buf = oiio.ImageBuf(str(path))
        if buf.has_error:
            log.warning("thumbnail: cannot read %s", path.name)
            continue
        pixels = np.asarray(buf.get_pixels(oiio.FLOAT), dtype=np.float32)
        small = _box_downsample(pixels, size)
        small = np.clip(np.nan_to_num(small), 0.0, 1.0)
        out = (small * 255.0 + 0.5).astype(np.uint8)
        h, w, c = out.shape
        spec = oiio.ImageSpec(w, h, c, oiio.UINT8)
        name = path.stem + ".png"
        writer = oiio.ImageOutput.create(str(dest / name))
        if writer is None or not writer.open(str(dest / name), spec):
            raise StorageError("could not write a thumbnail")
        writer.write_image(out)
        writer.close()
        names.append(name)
    return names


def _box_downsample(pixels: np.ndarray, size: int) -> np.ndarray:
    """(H, W, C) -> (h, w, C) with max(h, w) <= size, by averaging integer blocks."""
    if pixels.ndim == 2:
        pixels = pixels[:, :, None]
    h, w = pixels.shape[:2]
    f = max(1, -(-max(h, w) // size))
    if f == 1:
        return pixels
    hh, ww = h // f * f, w // f * f
    block = pixels[:hh, :ww].reshape(hh // f, f, ww // f, f, pixels.shape[2])
    return block.mean(axis=(1, 3))


def _remove_all(paths: list[Path]) -> None:
    """Remove a run's temporary files and folders (idempotent)."""
    from pbrsr_jobs.store import _remove

    for path in paths:
        if path.exists():
            _remove(path)
