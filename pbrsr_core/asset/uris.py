"""Safe handling of glTF ``uri`` strings: data URIs and files inside the asset's folder only."""

from __future__ import annotations

import base64
import binascii
import errno
import re
import urllib.parse
from pathlib import Path, PurePosixPath

from ..errors import InvalidAsset, LimitExceeded, UnprocessableAsset

_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.\-]*:")
_SAFE_CHARS = re.compile(r"[^A-Za-z0-9._\-]+")


def is_data_uri(uri: str) -> bool:
    return uri[:5].lower() == "data:"


def decode_data_uri(uri: str, max_bytes: int, what: str) -> tuple[bytes, str | None]:
    """``data:[mime][;base64],payload`` -> (bytes, mime). Raises LimitExceeded when the
    decoded size would be over ``max_bytes`` (checked before decoding), InvalidAsset when the
    URI is malformed."""
    head, sep, payload = uri.partition(",")
    if not sep:
        raise InvalidAsset(f"{what} has a malformed data URI (no ',')")
    params = head[5:].split(";")
    mime = params[0] or None
    if len(payload) * 3 // 4 > max_bytes:
        raise LimitExceeded(
            f"{what} has a data URI of about {len(payload) * 3 // 4} bytes; the limit is "
            f"{max_bytes} bytes"
        )
    if "base64" in (p.strip().lower() for p in params[1:]):
        try:
            data = base64.b64decode(payload.strip(), validate=True)
        except (binascii.Error, ValueError) as exc:
            raise InvalidAsset(f"{what} has a data URI that is not valid base64") from exc
    else:
        data = urllib.parse.unquote_to_bytes(payload)
    if len(data) > max_bytes:
        raise LimitExceeded(f"{what} has a data URI over the limit of {max_bytes} bytes")
    return data, mime


def relative_path(uri: str, what: str) -> PurePosixPath:
    """The asset-relative path a (non-data) ``uri`` names, refusing anything that could leave
    the asset's folder: schemes (``file:``, ``http:``...), absolute paths, ``..`` segments,
    backslashes, NUL bytes, empty names."""
    if _SCHEME.match(uri) or uri.startswith("//"):
        raise InvalidAsset(
            f"{what} refers to '{uri[:80]}': only files inside the asset's folder and data "
            "URIs are allowed"
        )
    rel = urllib.parse.unquote(uri)
    if (
        not rel
        or "\x00" in rel
        or "\\" in rel
        or rel.startswith("/")
        or re.match(r"^[A-Za-z]:", rel)
    ):
        raise InvalidAsset(f"{what} refers to '{uri[:80]}', which is not a relative file name")
    parts = PurePosixPath(rel).parts
    if any(p == ".." for p in parts) or not parts:
        raise InvalidAsset(f"{what} refers to '{uri[:80]}', outside the asset's folder")
    return PurePosixPath(*[p for p in parts if p != "."])


def resolve_inside(folder: Path, rel: PurePosixPath, what: str) -> Path:
    """``folder / rel`` after following symlinks, refused unless it stays inside ``folder``."""
    base = folder.resolve()
    target = (base / Path(*rel.parts)).resolve()
    if target != base and base not in target.parents:
        raise InvalidAsset(f"{what} refers to '{rel}', outside the asset's folder")
    return target


def read_resource(folder: Path, uri: str, max_bytes: int, what: str) -> bytes:
    """The bytes of a relative ``uri`` inside ``folder``: InvalidAsset when missing or unsafe,
    UnprocessableAsset when the file system cannot open it (a name too long for it, no
    permission, a link loop)."""
    rel = relative_path(uri, what)
    try:
        path = resolve_inside(folder, rel, what)
        if not path.is_file():
            raise InvalidAsset(f"{what} refers to '{short_name(rel)}', which is missing")
        size = path.stat().st_size
        if size > max_bytes:
            raise LimitExceeded(
                f"{what}: the file '{short_name(rel)}' is {size} bytes; the limit is {max_bytes}"
            )
        return path.read_bytes()
    except (OSError, RuntimeError) as exc:  # RuntimeError: Path.resolve on a link loop
        raise UnprocessableAsset(_unopenable(rel, what, exc)) from None


def short_name(rel: PurePosixPath) -> str:
    """A file name for a message: at most 80 characters, the length named when it is cut."""
    text = str(rel)
    return text if len(text) <= 80 else f"{text[:80]}... ({len(text)} characters)"


def _unopenable(rel: PurePosixPath, what: str, exc: BaseException) -> str:
    """Why the file ``rel`` cannot be opened, without server paths."""
    if isinstance(exc, OSError) and exc.errno == errno.ENAMETOOLONG:
        reason = "its name is too long for the file system"
    elif isinstance(exc, OSError):
        reason = (exc.strerror or type(exc).__name__).lower()
    else:
        reason = "a link loops"
    return f"{what} refers to '{short_name(rel)}', which cannot be opened: {reason}"


def safe_stem(name: str, default: str = "image") -> str:
    """A file-name-safe stem (ASCII letters, digits, '.', '_', '-') from any label."""
    stem = PurePosixPath(name).stem if name else ""
    stem = _SAFE_CHARS.sub("_", stem).strip("._")
    return stem[:80] or default


def encode_uri(rel: str) -> str:
    """Percent-encode a relative path for a glTF uri (keeps '/')."""
    return urllib.parse.quote(rel, safe="/")
