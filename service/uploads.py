"""Streaming ``multipart/form-data`` upload to storage, with the size limit enforced as it
arrives.

Each ``file`` part goes straight to ``<storage>/uploads/<random>.part`` chunk by chunk (never
held whole in memory); once one passes ``max_bytes`` reading stops and the request is
answered 413 without consuming the rest. A ``Content-Length`` already over what the request
may carry is refused before a byte is read. Small text fields (``options``) are collected up
to ``MAX_FIELD_BYTES``. With ``digest=True`` each file part is hashed (SHA-256) as it
streams, for idempotency keys. ``POST /v1/jobs`` takes one file part
(:func:`receive_upload`), ``POST /v1/batches`` up to ``PBRSR_MAX_BATCH_FILES``
(:func:`receive_uploads`).
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from fastapi import Request
from python_multipart.multipart import MultipartParser, parse_options_header

from pbrsr_jobs.store import safe_display_name

from .problems import ProblemError

MAX_FIELD_BYTES = 64 * 1024
MULTIPART_OVERHEAD = 64 * 1024  # boundaries, part headers and the options field
TEXT_FIELDS = ("options", "callback_url", "callback_events", "priority")


@dataclass
class Upload:
    """One file a POST carried, with the form's text fields (shared by every file of the
    request). ``path`` is None when no ``file`` part came; ``sha256`` is the file's hex digest
    when it was asked for."""

    path: Path | None = None
    size: int = 0
    sha256: str | None = None
    filename: str | None = None
    fields: dict[str, str] = field(default_factory=dict)


def file_label(number: int, filename: str | None) -> str:
    """How a problem body names the ``number``-th file of a batch (1-based), with its
    sanitised name."""
    return f"file {number} ({safe_display_name(filename, fallback='unnamed')})"


def _too_large(max_bytes: int, what: str = "the upload") -> ProblemError:
    mb = max_bytes / (1024 * 1024)
    return ProblemError(
        413,
        "limit-exceeded",
        f"{what} is larger than this server's limit of {mb:.4g} MB",
        headers={"Connection": "close"},
    )


async def receive_upload(
    request: Request, dest: Path, max_bytes: int, *, digest: bool = False
) -> Upload:
    """Parse the request body into ``dest`` (the one file part) and small fields.

    Raises ProblemError 415 (not multipart), 413 (over ``max_bytes``), 400 (malformed, or
    more than one file part). On any error ``dest`` is removed.
    """
    uploads, fields = await receive_uploads(request, lambda: dest, max_bytes, 1, digest=digest)
    return uploads[0] if uploads else Upload(fields=fields)


async def receive_uploads(
    request: Request,
    new_path: Callable[[], Path],
    max_bytes: int,
    max_files: int,
    *,
    digest: bool = False,
) -> tuple[list[Upload], dict[str, str]]:
    """Parse the request body: each ``file`` part (at most ``max_files``, each at most
    ``max_bytes``) into a fresh ``new_path()``, and the small fields. Returns the files in
    the order they came, each with the shared fields, and the fields.

    Raises ProblemError 415 (not multipart), 413 (a file over ``max_bytes``, or more than
    ``max_files`` files when that is above 1), 400 (malformed, or a second file part when
    ``max_files`` is 1). On any error every file written is removed.
    """
    ctype, params = parse_options_header(request.headers.get("content-type"))
    if ctype != b"multipart/form-data" or b"boundary" not in params:
        raise ProblemError(
            415,
            "unsupported-media-type",
            "send the asset as multipart/form-data with a 'file' part (and optional 'options')",
        )
    length = request.headers.get("content-length")
    most = max_files * (max_bytes + MULTIPART_OVERHEAD)
    if length is not None and length.isdigit() and int(length) > most:
        raise _too_large(max_files * max_bytes, "the request" if max_files > 1 else "the upload")

    fields: dict[str, str] = {}
    uploads: list[Upload] = []
    state: dict = {"name": None, "filename": None, "headers": {}, "hname": b"", "hval": b""}
    text = bytearray()
    sink: dict = {"fh": None, "upload": None}
    hasher = {"h": None}
    errors: list[ProblemError] = []

    def on_header_field(data: bytes, start: int, end: int) -> None:
        state["hname"] += data[start:end]

    def on_header_value(data: bytes, start: int, end: int) -> None:
        state["hval"] += data[start:end]

    def on_header_end() -> None:
        state["headers"][state["hname"].decode("latin-1").lower()] = state["hval"]
        state["hname"], state["hval"] = b"", b""

    def on_headers_finished() -> None:
        _, disp = parse_options_header(state["headers"].get("content-disposition", b""))
        name = disp.get(b"name", b"").decode("utf-8", "replace")
        state["name"] = name
        if name == "file" and not errors:
            if len(uploads) == max_files:
                errors.append(
                    ProblemError(400, "bad-request", "send exactly one 'file' part")
                    if max_files == 1
                    else ProblemError(
                        413, "limit-exceeded", f"a batch holds at most {max_files} files"
                    )
                )
                return
            filename = disp.get(b"filename", b"").decode("utf-8", "replace") or None
            upload = Upload(path=new_path(), filename=filename, fields=fields)
            uploads.append(upload)
            sink["upload"] = upload
            sink["fh"] = open(upload.path, "wb")  # noqa: SIM115 - closed in on_part_end / finally
            hasher["h"] = hashlib.sha256() if digest else None
        text.clear()

    def on_part_data(data: bytes, start: int, end: int) -> None:
        if errors:
            return
        chunk = data[start:end]
        if state["name"] == "file" and sink["fh"] is not None:
            upload = sink["upload"]
            upload.size += len(chunk)
            if upload.size > max_bytes:
                what = "the upload"
                if max_files > 1:
                    what = file_label(len(uploads), upload.filename)
                errors.append(_too_large(max_bytes, what))
                return
            sink["fh"].write(chunk)
            if hasher["h"] is not None:
                hasher["h"].update(chunk)
        elif state["name"] in TEXT_FIELDS:
            if len(text) + len(chunk) > MAX_FIELD_BYTES:
                errors.append(
                    ProblemError(413, "limit-exceeded", f"field '{state['name']}' is over 64 KB")
                )
                return
            text.extend(chunk)

    def on_part_end() -> None:
        if state["name"] == "file" and sink["fh"] is not None:
            sink["fh"].close()
            sink["fh"] = None
            if hasher["h"] is not None:
                sink["upload"].sha256 = hasher["h"].hexdigest()
        elif state["name"] in TEXT_FIELDS:
            fields[state["name"]] = text.decode("utf-8", "replace")
        state["name"] = None
        state["headers"] = {}

    parser = MultipartParser(
        params[b"boundary"],
        {
            "on_header_field": on_header_field,
            "on_header_value": on_header_value,
            "on_header_end": on_header_end,
            "on_headers_finished": on_headers_finished,
            "on_part_data": on_part_data,
            "on_part_end": on_part_end,
        },
    )
    try:
        async for chunk in request.stream():
            if chunk:
                parser.write(chunk)
            if errors:
                raise errors[0]
        parser.finalize()
        if errors:
            raise errors[0]
    except ProblemError:
        _discard(sink, uploads)
        raise
    except BaseException as exc:  # malformed multipart (python_multipart raises its own errors)
        _discard(sink, uploads)
        from python_multipart.exceptions import FormParserError

        if isinstance(exc, FormParserError | ValueError):
            raise ProblemError(400, "bad-request", "the multipart body is malformed") from None
        raise
    if sink["fh"] is not None:  # body ended inside a file part
        _discard(sink, uploads)
        raise ProblemError(400, "bad-request", "the upload ended early (truncated body)")
    return uploads, fields


def discard_uploads(uploads: list[Upload]) -> None:
    """Delete the files of ``uploads`` that are still in the uploads folder."""
    for upload in uploads:
        if upload.path is not None:
            upload.path.unlink(missing_ok=True)


def _discard(sink: dict, uploads: list[Upload]) -> None:
    if sink["fh"] is not None:
        sink["fh"].close()
        sink["fh"] = None
    discard_uploads(uploads)
