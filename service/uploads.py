"""Streaming ``multipart/form-data`` upload to storage, with the size limit enforced as it
arrives.

The ``file`` part goes straight to ``<storage>/uploads/<random>.part`` chunk by chunk (never
held whole in memory); once it passes ``max_bytes`` reading stops and the request is answered
413 without consuming the rest. A ``Content-Length`` already over the limit is refused before
a byte is read. Small text fields (``options``) are collected up to ``MAX_FIELD_BYTES``.
With ``digest=True`` the file part is hashed (SHA-256) as it streams, for idempotency keys.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

from fastapi import Request
from python_multipart.multipart import MultipartParser, parse_options_header

from .problems import ProblemError

MAX_FIELD_BYTES = 64 * 1024
MULTIPART_OVERHEAD = 64 * 1024  # boundaries, part headers and the options field
TEXT_FIELDS = ("options", "callback_url", "callback_events", "priority")


@dataclass
class Upload:
    """What a POST /v1/jobs carried. ``path`` is None when no ``file`` part came; ``sha256``
    is the file's hex digest when it was asked for."""

    path: Path | None = None
    size: int = 0
    sha256: str | None = None
    filename: str | None = None
    fields: dict[str, str] = field(default_factory=dict)


def _too_large(max_bytes: int) -> ProblemError:
    mb = max_bytes / (1024 * 1024)
    return ProblemError(
        413,
        "limit-exceeded",
        f"the upload is larger than this server's limit of {mb:.4g} MB",
        headers={"Connection": "close"},
    )


async def receive_upload(
    request: Request, dest: Path, max_bytes: int, *, digest: bool = False
) -> Upload:
    """Parse the request body into ``dest`` (the file part) and small fields.

    Raises ProblemError 415 (not multipart), 413 (over ``max_bytes``), 400 (malformed).
    On any error ``dest`` is removed.
    """
    ctype, params = parse_options_header(request.headers.get("content-type"))
    if ctype != b"multipart/form-data" or b"boundary" not in params:
        raise ProblemError(
            415,
            "unsupported-media-type",
            "send the asset as multipart/form-data with a 'file' part (and optional 'options')",
        )
    length = request.headers.get("content-length")
    if length is not None and length.isdigit() and int(length) > max_bytes + MULTIPART_OVERHEAD:
        raise _too_large(max_bytes)

    upload = Upload()
    state: dict = {"name": None, "filename": None, "headers": {}, "hname": b"", "hval": b""}
    text = bytearray()
    sink = {"fh": None}
    hasher = hashlib.sha256() if digest else None
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
        if name == "file":
            if upload.path is not None:
                errors.append(ProblemError(400, "bad-request", "send exactly one 'file' part"))
                return
            upload.filename = disp.get(b"filename", b"").decode("utf-8", "replace") or None
            upload.path = dest
            sink["fh"] = open(dest, "wb")  # noqa: SIM115 - closed in on_part_end / finally
        text.clear()

    def on_part_data(data: bytes, start: int, end: int) -> None:
        if errors:
            return
        chunk = data[start:end]
        if state["name"] == "file" and sink["fh"] is not None:
            upload.size += len(chunk)
            if upload.size > max_bytes:
                errors.append(_too_large(max_bytes))
                return
            sink["fh"].write(chunk)
            if hasher is not None:
                hasher.update(chunk)
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
            if hasher is not None:
                upload.sha256 = hasher.hexdigest()
        elif state["name"] in TEXT_FIELDS:
            upload.fields[state["name"]] = text.decode("utf-8", "replace")
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
        _discard(sink, dest)
        raise
    except Exception as exc:  # malformed multipart (python_multipart raises its own errors)
        _discard(sink, dest)
        from python_multipart.exceptions import FormParserError

        if isinstance(exc, FormParserError | ValueError):
            raise ProblemError(400, "bad-request", "the multipart body is malformed") from None
        raise
    if sink["fh"] is not None:  # body ended inside the file part
        _discard(sink, dest)
        raise ProblemError(400, "bad-request", "the upload ended early (truncated body)")
    return upload


def _discard(sink: dict, dest: Path) -> None:
    if sink["fh"] is not None:
        sink["fh"].close()
        sink["fh"] = None
    dest.unlink(missing_ok=True)
